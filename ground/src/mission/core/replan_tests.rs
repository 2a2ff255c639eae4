//! Membership changes in the core: a lost drone's work (a chase included) handed to a replan,
//! a joined drone, and the monolithic variant, on hand-built snapshots.

use super::book::{ActivePlan, PlanBook};
use super::*;
use crate::mission::config::Mode;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionUpdate};
use crate::mission::resume::PlanTask;
use crate::swarm::{SwarmChange, SwarmView, test_status};
use std::time::Instant;
use tacos_prompts::render::{HistoryEntry, TaskStatus};
use tacos_prompts::{ActionName, Call};
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionProgress, ActionState};
use tacos_shared::{DroneId, DroneMode};

fn id(name: &str) -> DroneId {
    DroneId::new(name).expect("valid")
}

/// alfa flying to car_3 (seq 2), bravo chasing the van (seq 4, its task done: at its station).
pub(super) fn chase() -> (PlanBook, Snapshot) {
    let now = Instant::now();
    let mut swarm = SwarmView::default();
    let mut alfa = test_status("alfa", DroneMode::Flying);
    alfa.action = Some(ActionProgress {
        seq: 2,
        task_id: Some("T2".into()),
        action: Action::Hold,
        state: ActionState::Running { progress: 0.3 },
    });
    swarm.apply_status(alfa, now);
    let mut bravo = test_status("bravo", DroneMode::Tracking);
    bravo.action = Some(ActionProgress {
        seq: 4,
        task_id: Some("T1".into()),
        action: Action::StartTracking {
            target: "van".into(),
        },
        state: ActionState::Done,
    });
    swarm.apply_status(bravo, now);
    let task = |call: Call, status: TaskStatus, sent: (&str, u64)| PlanTask {
        call,
        status,
        sent: Some((id(sent.0), sent.1)),
        failures: 0,
    };
    let book = PlanBook {
        plan: Some(ActivePlan {
            reasoning: "chase".into(),
            tasks: vec![
                task(
                    Call::named("T1", "bravo", ActionName::StartTracking, "van"),
                    TaskStatus::Done,
                    ("bravo", 4),
                ),
                task(
                    Call::named("T2", "alfa", ActionName::Goto, "car_3"),
                    TaskStatus::Running,
                    ("alfa", 2),
                ),
            ],
            cycles: 3,
            stuck_since: None,
        }),
        mnl: Default::default(),
    };
    let snap = Snapshot {
        swarm,
        targets: Vec::new(),
        now,
        ground: 1,
    };
    (book, snap)
}

#[test]
fn a_tracker_lost_mid_chase_hands_the_chase_to_a_replan() {
    let (mut book, snap) = chase();
    let effects = membership_changed(
        &mut book,
        &snap,
        Mode::Tacos,
        &SwarmChange::Left(id("bravo")),
    );
    let text = "bravo became unavailable".to_owned();
    assert_eq!(
        effects,
        [
            Effect::Note(Record::Event { text: text.clone() }),
            Effect::Tell(MissionUpdate::Event {
                topic: EventTopic::Failure,
                text: text.clone(),
            }),
            Effect::Remember(HistoryEntry::Event(text.clone())),
            Effect::Note(Record::Replan { reason: text }),
            Effect::Replan(
                "(automatic replan) bravo became unavailable: reassign its unfinished subtasks \
                 (T1 bravo start_tracking(van)) and keep the mission going"
                    .into()
            ),
        ]
    );
    let statuses: Vec<TaskStatus> = book.tasks().map(|t| t.status.clone()).collect();
    assert_eq!(
        statuses,
        [TaskStatus::Failed("drone lost".into()), TaskStatus::Running]
    );
}

#[test]
fn a_drone_that_joins_replans_only_work_under_way() {
    let (mut book, snap) = chase();
    let joined = SwarmChange::Joined(id("charlie"));
    let effects = membership_changed(&mut book, &snap, Mode::Wor, &joined);
    assert_eq!(
        effects.last(),
        Some(&Effect::Replan(
            "(automatic replan) charlie joined the swarm: reassign its unfinished subtasks and \
             keep the mission going"
                .into()
        ))
    );
    let mut idle = PlanBook::default();
    let effects = membership_changed(&mut idle, &snap, Mode::Tacos, &joined);
    assert!(
        !effects.iter().any(|e| matches!(e, Effect::Replan(_))),
        "{effects:?}"
    );
    // A status change is no membership change.
    let status = SwarmChange::Status(id("alfa"));
    assert_eq!(
        membership_changed(&mut book, &snap, Mode::Tacos, &status),
        []
    );
}

#[test]
fn the_monolithic_model_hears_of_a_lost_drone_and_its_claim_is_withdrawn() {
    let (_, snap) = chase();
    let mut book = PlanBook::default();
    book.mnl.active = true;
    book.mnl.claimed_done = true;
    let effects = membership_changed(&mut book, &snap, Mode::Mnl, &SwarmChange::Left(id("alfa")));
    assert_eq!(effects.len(), 2, "told and logged, no replan: {effects:?}");
    assert_eq!(book.mnl.executed, ["event: alfa became unavailable"]);
    assert!(!book.mnl.claimed_done);
}

/// A drone PX4 took out of offboard is said to be PX4's, in PX4's mode, with what takes it back.
#[test]
fn a_drone_px4_took_over_is_named_as_px4s_when_it_leaves() {
    let (_, mut snap) = chase();
    let mut alfa = test_status("alfa", DroneMode::Flying);
    alfa.autopilot_took_over = Some(tacos_shared::px4_mode::Px4Mode::Position);
    snap.swarm.apply_status(alfa, snap.now);
    let mut book = PlanBook::default();
    book.mnl.active = true;
    membership_changed(&mut book, &snap, Mode::Mnl, &SwarmChange::Left(id("alfa")));
    assert_eq!(
        book.mnl.executed,
        [
            "event: alfa became unavailable: PX4 left offboard and flies it in Position (a hold or \
          land takes it back)"
        ]
    );
}

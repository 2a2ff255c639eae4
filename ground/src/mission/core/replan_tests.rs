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

/// The replan for a lost drone hands on its work alone; the work the other drones still had
/// pending stays in the plan before it (`replan-keeps-pending`), alfa's running goto running.
#[test]
fn a_replan_that_hands_on_only_the_lost_work_keeps_the_rest() {
    use super::calls::Coordination;
    let (mut book, snap) = chase();
    if let Some(plan) = book.plan.as_mut() {
        plan.tasks.push(PlanTask {
            call: Call::named("T3", "alfa", ActionName::Goto, "car_5"),
            status: TaskStatus::NotStarted,
            sent: None,
            failures: 0,
        });
    }
    let gate = super::cycle_reply_tests::gate();
    let mut core = super::step_tests::core(Mode::Tacos);
    core.book = book;
    let effects = membership_changed(
        &mut core.book,
        &snap,
        Mode::Tacos,
        &SwarmChange::Left(id("bravo")),
    );
    let Some(Effect::Replan(why)) = effects.last().cloned() else {
        panic!("no replan: {effects:?}");
    };
    core.step(
        Input::Coordinate(Coordination::Replan(why.clone())),
        &snap,
        &gate,
    );
    let effects = core.step(
        Input::CoordinatorReply {
            instruction: why,
            grounded: Vec::new(),
            answer: Ok((
                "Alfa takes over the chase.".into(),
                vec![Call::named("T1", "alfa", ActionName::StartTracking, "van")],
                None,
            )),
        },
        &snap,
        &gate,
    );
    let plan: Vec<(String, TaskStatus)> = (core.book.tasks())
        .map(|t| (t.call.to_string(), t.status.clone()))
        .collect();
    assert_eq!(
        plan,
        [
            ("T2 alfa goto(car_3)".to_owned(), TaskStatus::Running),
            ("T3 alfa goto(car_5)".to_owned(), TaskStatus::NotStarted),
            (
                "T1 alfa start_tracking(van)".to_owned(),
                TaskStatus::NotStarted
            ),
        ]
    );
    assert!(
        effects.iter().any(|e| matches!(e,
            Effect::Note(Record::AidFired { aid, .. }) if *aid == crate::mission::aids::Aid::ReplanKeepsPending)),
        "{effects:?}"
    );
    // With the aid off, the plan is the model's alone.
    let (book, snap) = chase();
    let mut core = super::step_tests::core(Mode::Tacos);
    core.aids = core
        .aids
        .with(crate::mission::aids::Aid::ReplanKeepsPending, false);
    core.book = book;
    core.step(
        Input::Coordinate(Coordination::Replan("r".into())),
        &snap,
        &gate,
    );
    core.step(
        Input::CoordinatorReply {
            instruction: "r".into(),
            grounded: Vec::new(),
            answer: Ok((
                "r".into(),
                vec![Call::named("T1", "alfa", ActionName::Hold, "none")],
                None,
            )),
        },
        &snap,
        &gate,
    );
    let plan: Vec<String> = core.book.tasks().map(|t| t.call.to_string()).collect();
    assert_eq!(plan, ["T1 alfa hold()"]);
}

//! The core's rules on hand-built snapshots: no process, no clock, no channel.

use super::book::{Monolithic, STUCK_AFTER};
use super::outcomes::{following_of, judge_monolithic};
use super::start::startable;
use super::*;
use crate::mission::config::Mode;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionUpdate};
use crate::mission::resolve::{claimed_points, position_of, resolve};
use crate::mission::resume::PlanTask;
use crate::safety::SafetyGate;
use crate::swarm::{SwarmView, test_status};
use std::time::{Duration, Instant};
use tacos_prompts::render::{HistoryEntry, TaskStatus};
use tacos_prompts::{ActionName, Call};
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionProgress, ActionState, DroneStatus, FailureReason};
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, DroneMode, Vec3};

const GROUND: u64 = 1;

pub(super) fn gate() -> SafetyGate {
    SafetyGate::new(Scenario::builtin("city").expect("city"))
}

fn id(name: &str) -> DroneId {
    DroneId::new(name).expect("valid")
}

/// A snapshot of the city at `now` with no drone heard yet.
pub(super) fn empty(now: Instant) -> Snapshot {
    Snapshot {
        swarm: SwarmView::default(),
        targets: Vec::new(),
        now,
        ground: GROUND,
    }
}

/// `name` in `mode` above its pad (10 m up when airborne), heard just now, doing `action`.
pub(super) fn heard(
    snap: &mut Snapshot,
    name: &str,
    mode: DroneMode,
    action: Option<ActionProgress>,
) {
    let home = gate()
        .scenario()
        .drones
        .iter()
        .find(|d| d.id.as_str() == name)
        .expect("a drone of the city")
        .home;
    let mut status = test_status(name, mode);
    status.position = Vec3::new(home.x, home.y, if mode.is_airborne() { 10.0 } else { 0.0 });
    status.action = action;
    heard_as(snap, status);
}

fn heard_as(snap: &mut Snapshot, status: DroneStatus) {
    snap.swarm.apply_status(status, snap.now);
}

pub(super) fn progress(seq: u64, action: Action, state: ActionState) -> Option<ActionProgress> {
    Some(ActionProgress {
        seq,
        task_id: None,
        action,
        state,
    })
}

fn task(call: Call, status: TaskStatus, sent: Option<(&str, u64)>, failures: u32) -> PlanTask {
    PlanTask {
        call,
        status,
        sent: sent.map(|(d, seq)| (id(d), seq)),
        failures,
    }
}

fn book(tasks: Vec<PlanTask>) -> PlanBook {
    PlanBook {
        plan: Some(ActivePlan {
            reasoning: "test".into(),
            tasks,
            cycles: 2,
            stuck_since: None,
        }),
        mnl: Default::default(),
    }
}

/// alfa flying, reporting that its goto (seq 7) ended in `state`; the book has T1, that goto,
/// running after `failures` failures.
fn alfa_goto_ended(snap: &mut Snapshot, state: ActionState, failures: u32) -> PlanBook {
    let target = Vec3::new(0.0, 0.0, 10.0);
    let ended = progress(7, Action::Goto { target }, state);
    heard(snap, "alfa", DroneMode::Flying, ended);
    let running = TaskStatus::Running;
    book(vec![task(
        goto("T1", "alfa", "car_2"),
        running,
        Some(("alfa", 7)),
        failures,
    )])
}

/// alfa flying to car_2 (sent as `seq`), then to car_3; bravo to car_4.
fn alfa_busy_then_bravo(seq: u64) -> PlanBook {
    book(vec![
        task(
            goto("T1", "alfa", "car_2"),
            TaskStatus::Running,
            Some(("alfa", seq)),
            0,
        ),
        task(goto("T2", "alfa", "car_3"), TaskStatus::NotStarted, None, 0),
        task(
            goto("T3", "bravo", "car_4"),
            TaskStatus::NotStarted,
            None,
            0,
        ),
    ])
}

pub(super) fn rules(gate: &SafetyGate) -> Rules<'_> {
    Rules {
        gate,
        mode: Mode::Tacos,
        max_task_failures: 3,
    }
}

pub(super) fn goto(task: &str, drone: &str, place: &str) -> Call {
    Call::named(task, drone, ActionName::Goto, place)
}

#[test]
fn a_reported_outcome_ends_its_task_and_the_last_one_completes_the_plan() {
    let gate = gate();
    let mut snap = empty(Instant::now());
    let done = progress(5, Action::ArmTakeoff, ActionState::Done);
    heard(&mut snap, "alfa", DroneMode::Flying, done);
    let take_off = Call::named("T1", "alfa", ActionName::ArmTakeoff, "none");
    let mut book = book(vec![task(
        take_off.clone(),
        TaskStatus::Running,
        Some(("alfa", 5)),
        0,
    )]);
    let (effects, changed) = poll(&mut book, &snap, &rules(&gate));
    assert!(changed);
    assert_eq!(book.plan, None);
    assert_eq!(
        effects,
        vec![
            Effect::Note(Record::ActionOutcome {
                drone: "alfa".into(),
                task: Some("T1".into()),
                seq: 5,
                outcome: "done".into(),
                failure: None,
            }),
            Effect::Tell(MissionUpdate::Outcome {
                drone: "alfa".into(),
                action: "T1 alfa arm_takeoff()".into(),
                outcome: "done".into(),
                failed: false,
            }),
            Effect::WorkReplaced,
            Effect::Remember(HistoryEntry::Executed {
                call: take_off,
                outcome: "done".into(),
            }),
            Effect::PlanCycles(2),
            Effect::Note(Record::PlanComplete { cycles: 2 }),
            Effect::Tell(MissionUpdate::PlanComplete { cycles: 2 }),
        ]
    );
}

#[test]
fn the_same_book_and_snapshot_give_the_same_effects() {
    let gate = gate();
    let mut snap = empty(Instant::now());
    let failed = ActionState::Failed(FailureReason::TimedOut);
    heard(
        &mut snap,
        "alfa",
        DroneMode::Flying,
        progress(4, Action::Hold, failed),
    );
    heard(&mut snap, "bravo", DroneMode::Flying, None);
    let tasks = vec![
        task(
            goto("T1", "alfa", "car_2"),
            TaskStatus::Running,
            Some(("alfa", 4)),
            0,
        ),
        task(
            Call::named("T2", "bravo", ActionName::ArmTakeoff, "none"),
            TaskStatus::NotStarted,
            None,
            0,
        ),
        task(
            goto("T3", "bravo", "car_3"),
            TaskStatus::NotStarted,
            None,
            0,
        ),
    ];
    let (mut first, mut second) = (book(tasks.clone()), book(tasks));
    let a = poll(&mut first, &snap, &rules(&gate));
    let b = poll(&mut second, &snap, &rules(&gate));
    assert_eq!(a, b);
    assert_eq!(first, second);
    // And what they decided: alfa's task failed, bravo's take-off already holds.
    let plan = first.plan.expect("the plan goes on");
    assert_eq!(plan.tasks[0].status, TaskStatus::Failed("timed out".into()));
    assert_eq!(plan.tasks[1].status, TaskStatus::Done);
    assert_eq!(plan.tasks[2].status, TaskStatus::NotStarted);
}

#[test]
fn a_task_that_fails_three_times_gives_its_plan_up_with_the_last_reason() {
    let gate = gate();
    let mut snap = empty(Instant::now());
    let why = FailureReason::Unreachable("no progress".into());
    let mut book = alfa_goto_ended(&mut snap, ActionState::Failed(why.clone()), 2);
    let (effects, _) = poll(&mut book, &snap, &rules(&gate));
    assert_eq!(book.plan, None);
    let why = format!("T1 alfa goto(car_2) failed 3 times (last: {why})");
    assert!(effects.contains(&Effect::Note(Record::PlanEnded {
        how: format!("abandoned: {why}")
    })));
    assert_eq!(
        effects.last(),
        Some(&Effect::Tell(MissionUpdate::Error(format!(
            "the plan was given up: {why}"
        ))))
    );
}

#[test]
fn a_failed_task_can_start_again_on_any_ready_drone_of_the_swarm() {
    let gate = gate();
    let mut snap = empty(Instant::now());
    let mut book = alfa_goto_ended(&mut snap, ActionState::Failed(FailureReason::TimedOut), 0);
    heard(&mut snap, "bravo", DroneMode::Flying, None);
    heard(&mut snap, "charlie", DroneMode::Idle, None);
    poll(&mut book, &snap, &rules(&gate));
    let plan = book
        .plan
        .as_ref()
        .expect("one failure does not end the plan");
    let drones: Vec<String> = startable(plan, &Start::new(&snap, &gate, &book))
        .into_iter()
        .map(|c| c.drone)
        .collect();
    // charlie is on the ground: the gate refuses a goto before take-off.
    assert_eq!(drones, ["alfa", "bravo"]);
}

#[test]
fn a_goto_to_where_the_drone_hovers_is_done_without_flying() {
    let gate = gate();
    let mut snap = empty(Instant::now());
    heard(&mut snap, "alfa", DroneMode::Flying, None);
    let there = goto("T1", "alfa", "car_2");
    let claimed = claimed_points(&snap.swarm, "alfa", snap.now);
    let position = position_of(&snap.swarm, "alfa");
    let Ok(Action::Goto { target }) = resolve(&there, gate.scenario(), &[], &claimed, position)
    else {
        panic!("car_2 resolves to a point");
    };
    let mut status = test_status("alfa", DroneMode::Flying);
    status.position = target;
    heard_as(&mut snap, status);
    let mut book = book(vec![task(there, TaskStatus::NotStarted, None, 0)]);
    let (effects, changed) = poll(&mut book, &snap, &rules(&gate));
    assert!(changed);
    assert_eq!(book.plan, None, "the plan is complete");
    assert_eq!(
        effects[0],
        Effect::Note(Record::Event {
            text: "T1 alfa goto(car_2): already there: nothing to do".into()
        })
    );
}

#[test]
fn a_landing_after_a_take_off_waits_for_the_take_off_even_on_the_ground() {
    let gate = gate();
    let mut snap = empty(Instant::now());
    heard(&mut snap, "alfa", DroneMode::Idle, None);
    let mut book = book(vec![
        task(
            Call::named("T1", "alfa", ActionName::ArmTakeoff, "none"),
            TaskStatus::NotStarted,
            None,
            0,
        ),
        task(
            Call::named("T2", "alfa", ActionName::Land, "none"),
            TaskStatus::NotStarted,
            None,
            0,
        ),
    ]);
    let (effects, changed) = poll(&mut book, &snap, &rules(&gate));
    assert!(!changed && effects.is_empty(), "{effects:?}");
    // Airborne and idle, the take-off holds; the landing is the next step, not done.
    heard(&mut snap, "alfa", DroneMode::Flying, None);
    poll(&mut book, &snap, &rules(&gate));
    let statuses: Vec<TaskStatus> = book.tasks().map(|t| t.status.clone()).collect();
    assert_eq!(statuses, [TaskStatus::Done, TaskStatus::NotStarted]);
}

#[test]
fn a_plan_for_an_unavailable_drone_is_given_up_after_the_stuck_time_saying_why() {
    let gate = gate();
    let t0 = Instant::now();
    let mut snap = empty(t0);
    heard(&mut snap, "alfa", DroneMode::Flying, None);
    // alfa's last status is now 2 s old: its link is stale.
    snap.now = t0 + Duration::from_secs(2);
    let mut book = book(vec![task(
        goto("T1", "alfa", "car_2"),
        TaskStatus::NotStarted,
        None,
        0,
    )]);
    let start = Start::new(&snap, &gate, &book);
    let plan = book.plan.as_ref().expect("plan");
    assert_eq!(startable(plan, &start), []);
    assert_eq!(
        start.blocker(&plan.tasks[0].call).as_deref(),
        Some("alfa is unavailable")
    );
    assert_eq!(give_up_if_stuck(&mut book, &snap, &gate), []);
    snap.now += STUCK_AFTER - Duration::from_secs(1);
    assert_eq!(give_up_if_stuck(&mut book, &snap, &gate), []);
    snap.now += Duration::from_secs(1);
    let effects = give_up_if_stuck(&mut book, &snap, &gate);
    assert_eq!(book.plan, None);
    let Some(Effect::Tell(MissionUpdate::Error(text))) = effects.last() else {
        panic!("the pilot is told: {effects:?}");
    };
    assert_eq!(
        text,
        "the plan was given up: nothing has run or could start for 20 s; waiting: T1 alfa \
         goto(car_2) (alfa is unavailable). Give the work to another drone or place, or land"
    );
}

#[test]
fn a_running_task_keeps_a_plan_from_being_stuck() {
    let gate = gate();
    let mut snap = empty(Instant::now());
    heard(&mut snap, "alfa", DroneMode::Flying, None);
    let mut book = book(vec![task(
        goto("T1", "alfa", "car_2"),
        TaskStatus::Running,
        Some(("alfa", 3)),
        0,
    )]);
    for _ in 0..3 {
        assert_eq!(give_up_if_stuck(&mut book, &snap, &gate), []);
        snap.now += STUCK_AFTER;
    }
    assert!(book.plan.is_some());
}

#[test]
fn a_target_lost_after_tracking_fails_the_done_task() {
    let gate = gate();
    let mut snap = empty(Instant::now());
    let tracking = Action::StartTracking {
        target: "van".into(),
    };
    let lost = ActionState::Failed(FailureReason::TargetLost("van".into()));
    heard(
        &mut snap,
        "alfa",
        DroneMode::Flying,
        progress(9, tracking, lost),
    );
    let follow = Call::named("T1", "alfa", ActionName::StartTracking, "van");
    let mut book = book(vec![task(follow, TaskStatus::Done, Some(("alfa", 9)), 0)]);
    let (effects, changed) = poll(&mut book, &snap, &rules(&gate));
    assert!(changed);
    let plan = book
        .plan
        .expect("the plan goes on: the Supervisor can give it again");
    assert!(matches!(&plan.tasks[0].status, TaskStatus::Failed(why) if why.contains("van")));
    assert!(
        effects
            .iter()
            .any(|e| matches!(e, Effect::Tell(MissionUpdate::Outcome { failed: true, .. })))
    );
}

#[test]
fn a_lost_drone_leaves_its_work_and_the_target_it_followed() {
    let mut snap = empty(Instant::now());
    let tracking = Action::StartTracking {
        target: "van".into(),
    };
    let running = ActionState::Running { progress: 0.5 };
    heard(
        &mut snap,
        "alfa",
        DroneMode::Tracking,
        progress(3, tracking, running),
    );
    let alfa = id("alfa");
    let following = following_of(&snap, &alfa);
    assert_eq!(following.as_deref(), Some("van"));
    // The tracking was not a task of this plan: the replan is told to hand it on too.
    let mut plan = alfa_busy_then_bravo(2);
    plan.fail_tasks_of(&alfa, following.as_deref(), "drone lost");
    assert_eq!(
        plan.tasks().next().map(|t| t.status.clone()),
        Some(TaskStatus::Failed("drone lost".into()))
    );
    assert_eq!(
        plan.unfinished_work_of(&alfa, following),
        [
            "T1 alfa goto(car_2)",
            "T2 alfa goto(car_3)",
            "alfa start_tracking(van)"
        ]
    );
}

#[test]
fn a_drone_busy_with_a_sent_action_or_following_another_ground_takes_nothing() {
    let gate = gate();
    let mut snap = empty(Instant::now());
    heard(&mut snap, "alfa", DroneMode::Flying, None);
    let mut bravo = test_status("bravo", DroneMode::Flying);
    bravo.position = Vec3::new(30.0, -132.5, 10.0);
    bravo.ground = Some(GROUND + 1);
    heard_as(&mut snap, bravo);
    // alfa's status does not show the sent action yet; the book does.
    let book = alfa_busy_then_bravo(1);
    let start = Start::new(&snap, &gate, &book);
    let plan = book.plan.as_ref().expect("plan");
    assert_eq!(
        start.blocker(&plan.tasks[1].call).as_deref(),
        Some("alfa is busy with another action")
    );
    assert_eq!(
        start.blocker(&plan.tasks[2].call).as_deref(),
        Some("bravo follows another ground station (2) until it falls silent")
    );
    assert_eq!(startable(plan, &start), []);
}

#[test]
fn monolithic_work_is_complete_when_its_claim_stands_and_nothing_it_sent_runs() {
    let mut mnl = Monolithic {
        active: true,
        claimed_done: true,
        cycles: 3,
        tasks: vec![task(
            goto("A1", "alfa", "car_2"),
            TaskStatus::Running,
            Some(("alfa", 1)),
            0,
        )],
        ..Default::default()
    };
    assert_eq!(judge_monolithic(&mut mnl), []);
    mnl.tasks[0].status = TaskStatus::Done;
    assert_eq!(
        judge_monolithic(&mut mnl),
        [
            Effect::PlanCycles(3),
            Effect::Note(Record::PlanComplete { cycles: 3 }),
            Effect::Tell(MissionUpdate::PlanComplete { cycles: 3 }),
        ]
    );
    assert!(!mnl.active);
}

#[test]
fn a_plan_ended_otherwise_than_complete_says_how() {
    let plan = ActivePlan {
        reasoning: String::new(),
        tasks: Vec::new(),
        cycles: 1,
        stuck_since: None,
    };
    assert_eq!(
        plan_ended(plan, "interrupted by a direct command"),
        [
            Effect::WorkReplaced,
            Effect::Note(Record::PlanEnded {
                how: "interrupted by a direct command".into()
            }),
            Effect::Tell(MissionUpdate::Event {
                topic: EventTopic::PlanEnded,
                text: "plan ended: interrupted by a direct command".into()
            }),
        ]
    );
}

#[test]
fn an_effect_that_holds_is_not_offered_again() {
    assert!(effect_holds(ActionName::ArmTakeoff, DroneMode::Flying));
    assert!(!effect_holds(ActionName::ArmTakeoff, DroneMode::Idle));
    assert!(effect_holds(ActionName::Land, DroneMode::Idle));
    assert!(!effect_holds(ActionName::Land, DroneMode::Flying));
    assert!(effect_holds(ActionName::StopTracking, DroneMode::Flying));
    assert!(!effect_holds(ActionName::StopTracking, DroneMode::Tracking));
    assert!(!effect_holds(ActionName::Goto, DroneMode::Flying));
}

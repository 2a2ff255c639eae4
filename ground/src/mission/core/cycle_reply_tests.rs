//! A cycle's reply and its sends in the core (`core::cycle_reply`): one `Effect::Send` at a
//! time, each booked when its result comes back; a call the gate refuses by the time it is to
//! go; an early call and the whole reply; a failed send; a reply for work that ended.

use super::step_tests::core;
use super::*;
use crate::mission::config::Mode;
use crate::mission::log::Record;
use crate::mission::report::{MissionError, MissionUpdate};
use crate::safety::{CheckedAction, SafetyGate};
use crate::swarm::{SwarmView, test_status};
use std::time::{Duration, Instant};
use tacos_prompts::render::TaskStatus;
use tacos_prompts::{ActionName, Call};
use tacos_shared::DroneMode;
use tacos_shared::action::Action;
use tacos_shared::scenario::Scenario;

pub(super) fn gate() -> SafetyGate {
    SafetyGate::new(Scenario::builtin("city").expect("city"))
}

/// alfa, bravo and charlie on the ground, heard at `now`; `gone` is not heard at all.
pub(super) fn grounded(now: Instant, gone: Option<&str>) -> Snapshot {
    let mut swarm = SwarmView::default();
    for name in ["alfa", "bravo", "charlie"] {
        if Some(name) != gone {
            swarm.apply_status(test_status(name, DroneMode::Idle), now);
        }
    }
    Snapshot {
        swarm,
        targets: Vec::new(),
        now,
        ground: 1,
    }
}

fn take_off(task: &str, drone: &str) -> Call {
    Call::named(task, drone, ActionName::ArmTakeoff, "none")
}

/// A Tacos core with the plan "T1 alfa, T2 bravo, T3 charlie: take off" in force, and a
/// Supervisor call started.
fn planned(snap: &Snapshot, gate: &SafetyGate) -> Core {
    let mut core = core(Mode::Tacos);
    let calls = vec![
        take_off("T1", "alfa"),
        take_off("T2", "bravo"),
        take_off("T3", "charlie"),
    ];
    core.step(
        Input::CoordinatorReply {
            instruction: "all take off".into(),
            grounded: vec!["alfa".into(), "bravo".into(), "charlie".into()],
            answer: Ok(("All up.".into(), calls, None)),
        },
        snap,
        gate,
    );
    start_due_cycle(&mut core, snap, gate);
    core
}

/// Starts the cycle that is due as the driver does (`Input::CallDue`): its call is in flight.
pub(super) fn start_due_cycle(core: &mut Core, snap: &Snapshot, gate: &SafetyGate) -> CycleStart {
    let effects = core.step(Input::CallDue, snap, gate);
    effects
        .into_iter()
        .find_map(|e| match e {
            Effect::Ask(Ask::Cycle(start)) => Some(start),
            _ => None,
        })
        .expect("a cycle is due, with a decision to make")
}

fn checked(gate: &SafetyGate, snap: &Snapshot, drone: &str) -> CheckedAction {
    gate.check(&snap.swarm, drone, &Action::ArmTakeoff, snap.now)
        .expect("a grounded drone may take off")
}

fn choice(gate: &SafetyGate, snap: &Snapshot, calls: &[Call]) -> CycleChoice {
    CycleChoice {
        reasoning: "Up they go.".into(),
        claim: false,
        all_passed: true,
        accepted: calls
            .iter()
            .map(|c| (c.clone(), checked(gate, snap, &c.drone)))
            .collect(),
        later: Vec::new(),
    }
}

/// The cycle call answers with the whole reply of `calls`, judged on `judged`, taken in on
/// `snap`.
fn answer(
    core: &mut Core,
    gate: &SafetyGate,
    (judged, snap): (&Snapshot, &Snapshot),
    calls: &[Call],
) -> Vec<Effect> {
    core.step(
        Input::CycleReply(Ok(choice(gate, judged, calls))),
        snap,
        gate,
    )
}

fn sends(effects: &[Effect]) -> Vec<(String, String)> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Send { checked, task } => Some((task.clone(), checked.drone().to_string())),
            _ => None,
        })
        .collect()
}

fn cycles_logged(effects: &[Effect]) -> Vec<Vec<String>> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Note(Record::SupervisorCycle { actions, .. }) => Some(actions.clone()),
            _ => None,
        })
        .collect()
}

fn statuses(core: &Core) -> Vec<TaskStatus> {
    core.book
        .plan
        .as_ref()
        .map(|p| p.tasks.iter().map(|t| t.status.clone()).collect())
        .unwrap_or_default()
}

#[test]
fn a_reply_s_calls_go_one_at_a_time_and_the_cycle_is_counted_after_the_last() {
    let (gate, snap) = (gate(), grounded(Instant::now(), None));
    let mut core = planned(&snap, &gate);
    let calls = [take_off("T1", "alfa"), take_off("T2", "bravo")];
    let effects = answer(&mut core, &gate, (&snap, &snap), &calls);
    assert_eq!(sends(&effects), [("T1".to_owned(), "alfa".to_owned())]);
    let effects = core.step(Input::Sent(Ok(11)), &snap, &gate);
    assert_eq!(sends(&effects), [("T2".to_owned(), "bravo".to_owned())]);
    assert!(
        cycles_logged(&effects).is_empty(),
        "counted before the last send"
    );
    let effects = core.step(Input::Sent(Ok(12)), &snap, &gate);
    assert!(sends(&effects).is_empty());
    assert_eq!(
        cycles_logged(&effects),
        [vec![
            "T1 alfa arm_takeoff()".to_owned(),
            "T2 bravo arm_takeoff()".to_owned()
        ]]
    );
    assert!(effects.contains(&Effect::CycleCounted));
    assert_eq!(
        statuses(&core),
        [
            TaskStatus::Running,
            TaskStatus::Running,
            TaskStatus::NotStarted
        ]
    );
    assert_eq!(core.book.plan.as_ref().map(|p| p.cycles), Some(1));
}

#[test]
fn a_call_the_gate_refuses_by_the_time_it_is_to_go_is_not_sent() {
    let gate = gate();
    let t0 = Instant::now();
    let snap = grounded(t0, None);
    let mut core = planned(&snap, &gate);
    let calls = [take_off("T1", "alfa"), take_off("T2", "bravo")];
    // By the reply's step, alfa has not been heard for long: its status is stale.
    let mut later = grounded(t0 + Duration::from_secs(5), Some("alfa"));
    later
        .swarm
        .apply_status(test_status("alfa", DroneMode::Idle), t0);
    let effects = answer(&mut core, &gate, (&snap, &later), &calls);
    assert_eq!(sends(&effects), [("T2".to_owned(), "bravo".to_owned())]);
    assert!(
        effects.iter().any(|e| matches!(
            e,
            Effect::Note(Record::Event { text }) if text.starts_with("T1 alfa arm_takeoff(): not sent")
        )),
        "{effects:?}"
    );
    let effects = core.step(Input::Sent(Ok(3)), &later, &gate);
    assert_eq!(
        cycles_logged(&effects),
        [vec!["T2 bravo arm_takeoff()".to_owned()]]
    );
}

#[test]
fn a_call_sent_early_is_booked_and_its_drone_left_out_of_the_whole_reply() {
    let (gate, snap) = (gate(), grounded(Instant::now(), None));
    let mut core = planned(&snap, &gate);
    let effects = core.step(
        Input::EarlyCall {
            call: take_off("T1", "alfa"),
            checked: checked(&gate, &snap, "alfa"),
            after: Duration::from_millis(1500),
        },
        &snap,
        &gate,
    );
    assert_eq!(sends(&effects), [("T1".to_owned(), "alfa".to_owned())]);
    let effects = core.step(Input::Sent(Ok(7)), &snap, &gate);
    assert!(effects.iter().any(|e| matches!(
        e,
        Effect::Note(Record::Event { text }) if text.contains("sent 1.5 s into the call")
    )));
    // The whole reply names alfa's take-off again and charlie's: only charlie's goes.
    let calls = [take_off("T1", "alfa"), take_off("T3", "charlie")];
    let effects = answer(&mut core, &gate, (&snap, &snap), &calls);
    assert_eq!(sends(&effects), [("T3".to_owned(), "charlie".to_owned())]);
    let effects = core.step(Input::Sent(Ok(8)), &snap, &gate);
    assert_eq!(
        cycles_logged(&effects),
        [vec![
            "T1 alfa arm_takeoff()".to_owned(),
            "T3 charlie arm_takeoff()".to_owned()
        ]]
    );
    assert_eq!(
        statuses(&core),
        [
            TaskStatus::Running,
            TaskStatus::NotStarted,
            TaskStatus::Running
        ]
    );
}

#[test]
fn a_failed_send_ends_the_cycle_there_and_a_reply_for_ended_work_sends_nothing() {
    let (gate, snap) = (gate(), grounded(Instant::now(), None));
    let mut core = planned(&snap, &gate);
    let calls = [take_off("T1", "alfa"), take_off("T2", "bravo")];
    answer(&mut core, &gate, (&snap, &snap), &calls);
    let failure = || MissionError::Overridden {
        drone: "alfa".into(),
        action: "arm_takeoff".into(),
    };
    let effects = core.step(Input::Sent(Err(failure())), &snap, &gate);
    assert!(
        sends(&effects).is_empty(),
        "bravo's call went after the failure"
    );
    assert_eq!(
        effects,
        [Effect::Tell(MissionUpdate::Error(failure().to_string()))]
    );
    assert_eq!(core.book.plan.as_ref().map(|p| p.cycles), Some(0));
    // The next cycle's call is overtaken by a direct command before its reply comes.
    core.calls.set_cycle_due(true);
    start_due_cycle(&mut core, &snap, &gate);
    core.step(Input::Overridden, &snap, &gate);
    let effects = answer(&mut core, &gate, (&snap, &snap), &calls);
    assert!(sends(&effects).is_empty());
    assert!(effects.iter().any(|e| matches!(
        e,
        Effect::Note(Record::Event { text }) if text.starts_with("a reply for work that ended meanwhile was dropped")
    )));
}

#[test]
fn the_monolithic_claim_stands_only_when_every_call_was_sent() {
    let gate = gate();
    let t0 = Instant::now();
    let snap = grounded(t0, None);
    let mut core = core(Mode::Mnl);
    core.step(Input::Pilot("all drones take off".into()), &snap, &gate);
    for refused in [true, false] {
        start_due_cycle(&mut core, &snap, &gate);
        let calls = [take_off("T1", "alfa"), take_off("T2", "bravo")];
        let mut reply = choice(&gate, &snap, &calls);
        reply.claim = true;
        // The first time, bravo is not heard by the step that sends: its call is refused.
        let step_snap = if refused {
            let mut s = grounded(t0 + Duration::from_secs(5), Some("bravo"));
            s.swarm
                .apply_status(test_status("bravo", DroneMode::Idle), t0);
            s.swarm.apply_status(
                test_status("alfa", DroneMode::Idle),
                t0 + Duration::from_secs(5),
            );
            s
        } else {
            snap.clone()
        };
        let mut effects = core.step(Input::CycleReply(Ok(reply)), &step_snap, &gate);
        while !sends(&effects).is_empty() {
            effects = core.step(Input::Sent(Ok(1)), &step_snap, &gate);
        }
        assert_eq!(core.book.mnl.claimed_done, !refused, "refused: {refused}");
        core.calls.set_cycle_due(true);
    }
}

#[test]
fn a_failed_early_send_is_told_and_the_whole_reply_still_goes() {
    let (gate, snap) = (gate(), grounded(Instant::now(), None));
    let mut core = planned(&snap, &gate);
    core.step(
        Input::EarlyCall {
            call: take_off("T1", "alfa"),
            checked: checked(&gate, &snap, "alfa"),
            after: Duration::from_millis(900),
        },
        &snap,
        &gate,
    );
    let failure = MissionError::Send {
        drone: "alfa".into(),
        action: "arm_takeoff".into(),
        reason: "the link is down".into(),
    };
    let told = failure.to_string();
    let effects = core.step(Input::Sent(Err(failure)), &snap, &gate);
    assert_eq!(effects, [Effect::Tell(MissionUpdate::Error(told))]);
    // alfa was not served: the whole reply sends its call, then bravo's.
    let calls = [take_off("T1", "alfa"), take_off("T2", "bravo")];
    let effects = answer(&mut core, &gate, (&snap, &snap), &calls);
    assert_eq!(sends(&effects), [("T1".to_owned(), "alfa".to_owned())]);
    let effects = core.step(Input::Sent(Ok(4)), &snap, &gate);
    assert_eq!(sends(&effects), [("T2".to_owned(), "bravo".to_owned())]);
    let effects = core.step(Input::Sent(Ok(5)), &snap, &gate);
    assert_eq!(cycles_logged(&effects).len(), 1);
}

#[test]
fn an_early_call_the_gate_refuses_when_it_is_to_go_keeps_the_monolithic_claim_from_standing() {
    let gate = gate();
    let t0 = Instant::now();
    let snap = grounded(t0, None);
    let mut core = core(Mode::Mnl);
    core.step(
        Input::Pilot("alfa and bravo, take off".into()),
        &snap,
        &gate,
    );
    start_due_cycle(&mut core, &snap, &gate);
    // alfa's call passed as the reply was written, but alfa is not heard by the step that
    // would send it.
    let mut stale = grounded(t0 + Duration::from_secs(5), Some("alfa"));
    stale
        .swarm
        .apply_status(test_status("alfa", DroneMode::Idle), t0);
    let effects = core.step(
        Input::EarlyCall {
            call: take_off("T1", "alfa"),
            checked: checked(&gate, &snap, "alfa"),
            after: Duration::from_millis(700),
        },
        &stale,
        &gate,
    );
    assert!(sends(&effects).is_empty());
    let mut reply = choice(&gate, &snap, &[take_off("T2", "bravo")]);
    reply.claim = true;
    let effects = core.step(Input::CycleReply(Ok(reply)), &snap, &gate);
    assert_eq!(sends(&effects), [("T2".to_owned(), "bravo".to_owned())]);
    core.step(Input::Sent(Ok(2)), &snap, &gate);
    assert!(
        !core.book.mnl.claimed_done,
        "a claim over a refused call stood"
    );
    assert_eq!(core.book.mnl.cycles, 1);
}

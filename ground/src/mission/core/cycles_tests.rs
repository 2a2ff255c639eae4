//! A plan carried out over several Supervisor cycles, on hand-built snapshots: in each cycle the
//! calls that can start, the Supervisor's reply judged against them, the sends booked, and the
//! drones' outcomes polled, until the plan is complete. No process, no clock, no model.

use super::start::startable;
use super::tests::{empty, gate, goto, heard, progress, rules};
use super::*;
use crate::mission::log::Record;
use crate::safety::CheckedAction;
use std::time::{Duration, Instant};
use tacos_prompts::render::TaskStatus;
use tacos_prompts::{ActionName, Call};
use tacos_shared::action::Action;
use tacos_shared::messages::ActionState;
use tacos_shared::{DroneId, DroneMode};

fn take_off(task: &str, drone: &str) -> Call {
    Call::named(task, drone, ActionName::ArmTakeoff, "none")
}

fn names<'a>(calls: impl IntoIterator<Item = &'a Call>) -> Vec<String> {
    calls
        .into_iter()
        .map(|c| format!("{} {}", c.task, c.drone))
        .collect()
}

fn lines(book: &PlanBook) -> Vec<(Call, TaskStatus)> {
    book.tasks()
        .map(|t| (t.call.clone(), t.status.clone()))
        .collect()
}

fn offered(book: &PlanBook, snap: &Snapshot, gate: &crate::safety::SafetyGate) -> Vec<Call> {
    let plan = book.plan.as_ref().expect("a plan in force");
    startable(plan, &Start::new(snap, gate, book))
}

/// Books the accepted calls as sent, numbering them from `seq`, as the engine does after each
/// send; returns what was sent.
fn send(book: &mut PlanBook, accepted: Vec<(Call, CheckedAction)>, seq: &mut u64) -> Vec<Action> {
    let plan = book.plan.as_mut().expect("a plan in force");
    plan.cycles += 1;
    let mut sent = Vec::new();
    for (call, checked) in accepted {
        *seq += 1;
        sent.push(checked.action().clone());
        let drone = DroneId::new(&call.drone).expect("a drone");
        plan.issued(call, drone, *seq);
    }
    sent
}

fn statuses(book: &PlanBook) -> Vec<(String, TaskStatus)> {
    book.tasks()
        .map(|t| (t.call.task.clone(), t.status.clone()))
        .collect()
}

#[test]
fn a_plan_whose_steps_wait_on_each_other_runs_over_several_cycles_and_completes() {
    let gate = gate();
    let t0 = Instant::now();
    let mut book = PlanBook::default();
    let plan = vec![
        take_off("T1", "alfa"),
        goto("T2", "alfa", "car_2"),
        take_off("T3", "bravo"),
    ];
    adopt(&mut book, "alfa to car_2, bravo up".into(), plan.clone());
    let mut seq = 0;

    // Cycle 1, both on the ground: the take-offs can start, alfa's goto cannot yet.
    let mut snap = empty(t0);
    heard(&mut snap, "alfa", DroneMode::Idle, None);
    heard(&mut snap, "bravo", DroneMode::Idle, None);
    let startable_now = offered(&book, &snap, &gate);
    assert_eq!(names(&startable_now), ["T1 alfa", "T3 bravo"]);
    // The Supervisor answers with the whole plan: alfa's goto is its second call, left for
    // later; nothing is refused.
    let judged = judge_cycle(
        &plan,
        Some(&startable_now),
        &[],
        &snap,
        &gate,
        &lines(&book),
    );
    assert_eq!(
        names(judged.accepted.iter().map(|(c, _)| c)),
        ["T1 alfa", "T3 bravo"]
    );
    assert_eq!(judged.later.len(), 1, "{:?}", judged.later);
    assert!(judged.later[0].contains("T2"), "{:?}", judged.later);
    assert!(judged.rejections.is_empty() && judged.gate_refusals.is_empty());
    let sent = send(&mut book, judged.accepted, &mut seq);
    assert_eq!(sent, [Action::ArmTakeoff, Action::ArmTakeoff]);

    // Cycle 2, both climbing: nothing changed, nothing can start, and the plan is not stuck.
    snap.now = t0 + Duration::from_secs(2);
    let climbing = ActionState::Running { progress: 0.5 };
    let alfa_up = progress(1, Action::ArmTakeoff, climbing.clone());
    heard(&mut snap, "alfa", DroneMode::Flying, alfa_up);
    heard(
        &mut snap,
        "bravo",
        DroneMode::Flying,
        progress(2, Action::ArmTakeoff, climbing),
    );
    let (effects, changed) = poll(&mut book, &snap, &rules(&gate));
    assert!(!changed && effects.is_empty(), "{effects:?}");
    assert!(offered(&book, &snap, &gate).is_empty());

    // Cycle 3: alfa is up: its take-off is done, and its goto can start; bravo still climbs.
    snap.now = t0 + Duration::from_secs(6);
    let alfa_done = progress(1, Action::ArmTakeoff, ActionState::Done);
    heard(&mut snap, "alfa", DroneMode::Flying, alfa_done);
    let (effects, changed) = poll(&mut book, &snap, &rules(&gate));
    assert!(changed);
    assert!(!effects.iter().any(|e| matches!(e, Effect::PlanCycles(_))));
    assert_eq!(
        statuses(&book),
        [
            ("T1".into(), TaskStatus::Done),
            ("T2".into(), TaskStatus::NotStarted),
            ("T3".into(), TaskStatus::Running)
        ]
    );
    let startable_now = offered(&book, &snap, &gate);
    assert_eq!(names(&startable_now), ["T2 alfa"]);
    // The Supervisor answers with the done take-off before the goto: alfa's first call is the
    // one judged, and it is refused (it cannot start); the repaired reply's goto passes.
    let reply = [take_off("T1", "alfa"), goto("T2", "alfa", "car_2")];
    let judged = judge_cycle(
        &reply,
        Some(&startable_now),
        &[],
        &snap,
        &gate,
        &lines(&book),
    );
    assert!(judged.accepted.is_empty(), "{:?}", judged.accepted);
    assert_eq!(judged.rejections.len(), 1, "{:?}", judged.rejections);
    let judged = judge_cycle(
        &reply[1..],
        Some(&startable_now),
        &[],
        &snap,
        &gate,
        &lines(&book),
    );
    let sent = send(&mut book, judged.accepted, &mut seq);
    let [Action::Goto { target }] = sent[..] else {
        panic!("{sent:?}")
    };
    // The Supervisor's memory of the plan, for its next cycle.
    let plan = book.plan.as_ref().expect("a plan");
    let tasks: Vec<_> = (plan.tasks.iter())
        .map(crate::mission::resume::PlanTask::progress)
        .collect();
    assert_eq!(
        tacos_prompts::render::plan_memory(&tasks),
        "- T1: done\n- T2: running\n- T3: running\n- every task issued\n"
    );

    // Both arrive: the plan is complete after its two cycles.
    snap.now = t0 + Duration::from_secs(30);
    heard(
        &mut snap,
        "alfa",
        DroneMode::Flying,
        progress(3, Action::Goto { target }, ActionState::Done),
    );
    heard(
        &mut snap,
        "bravo",
        DroneMode::Flying,
        progress(2, Action::ArmTakeoff, ActionState::Done),
    );
    let (effects, changed) = poll(&mut book, &snap, &rules(&gate));
    assert!(changed);
    assert_eq!(book.plan, None);
    assert!(effects.contains(&Effect::PlanCycles(2)), "{effects:?}");
    assert!(effects.contains(&Effect::Note(Record::PlanComplete { cycles: 2 })));
}

//! What a Supervisor's (or the monolithic model's) reply comes to: each drone's first call, those
//! among the calls that can start, checked live against the step's snapshot and the safety gate;
//! and the rejections the model is told. One call per drone, one drone per task.

use super::checks::check_live;
use super::snapshot::Snapshot;
use crate::safety::{CheckedAction, SafetyGate};
use tacos_prompts::Call;
use tacos_prompts::render::TaskStatus;

/// A cycle's reply as judged.
#[derive(Debug)]
pub(crate) struct CycleJudgement {
    /// The calls to send, each with the gate's check.
    pub(crate) accepted: Vec<(Call, CheckedAction)>,
    /// A drone's later steps in the same reply, left for a later cycle.
    pub(crate) later: Vec<String>,
    /// Why the other calls were not taken, for the repair round.
    pub(crate) rejections: Vec<String>,
    /// The safety gate's refusals.
    pub(crate) gate_refusals: Vec<String>,
}

/// Judges a cycle's `actions`: each drone's first call (`first_call_per_drone`), but none for a
/// drone `served` while the reply was being written or for a task that went to one of them;
/// when `only` is given (the plan's startable calls) only those; then `check_live` on `snap`.
pub(crate) fn judge_cycle(
    actions: &[Call],
    only: Option<&[Call]>,
    served: &[Call],
    snap: &Snapshot,
    gate: &SafetyGate,
    tasks: &[(Call, TaskStatus)],
) -> CycleJudgement {
    let (firsts, later) = first_call_per_drone(actions);
    let mut handed_elsewhere = Vec::new();
    let firsts: Vec<Call> = firsts
        .into_iter()
        .filter(|c| !served.iter().any(|s| s.drone == c.drone))
        .filter(|c| match served.iter().find(|s| s.task == c.task) {
            Some(s) => {
                handed_elsewhere.push(format!(
                    "{c}: task {} already goes to {} this cycle",
                    c.task, s.drone
                ));
                false
            }
            None => true,
        })
        .collect();
    let (calls, mut rejections) = match only {
        Some(startable) => match_startable(&firsts, startable),
        None => (firsts, Vec::new()),
    };
    rejections.extend(handed_elsewhere);
    let (accepted, live, gate_refusals) = check_live(&calls, gate, snap, tasks);
    rejections.extend(live);
    CycleJudgement {
        accepted,
        later,
        rejections,
        gate_refusals,
    }
}

/// What a call asks of which drone, whatever its task id: a replan that repeats a running call
/// keeps it running instead of starting it again.
pub(crate) fn same_work(call: &Call) -> (String, String) {
    let text = call.to_string();
    let without_task = text
        .split_once(' ')
        .map(|x| x.1.to_owned())
        .unwrap_or_default();
    (call.drone.clone(), without_task)
}

/// Each drone's first call in a reply; the calls after it for the same drone are its next
/// steps (one action per drone per cycle), which a later cycle issues if they still apply. A
/// small model lists a drone's whole route at once, often under one task id: sending that back
/// costs a model call of minutes and changes nothing. Returns the first calls and the later
/// steps that are other work (a repeat of the first call is just dropped).
pub(crate) fn first_call_per_drone(calls: &[Call]) -> (Vec<Call>, Vec<String>) {
    let mut firsts: Vec<Call> = Vec::new();
    let mut later = Vec::new();
    for call in calls {
        match firsts.iter().find(|c| c.drone == call.drone) {
            None => firsts.push(call.clone()),
            Some(first) if same_work(first) == same_work(call) => {}
            Some(_) => later.push(call.to_string()),
        }
    }
    (firsts, later)
}

/// Keeps the proposed calls that are one of the startable calls (task, drone, action and target
/// as the plan has them; the point of a goto comes from the plan), and says why the others are not.
pub(crate) fn match_startable(proposed: &[Call], startable: &[Call]) -> (Vec<Call>, Vec<String>) {
    let mut calls = Vec::new();
    let mut rejections = Vec::new();
    for call in proposed {
        let found = startable.iter().find(|c| {
            c.task == call.task
                && c.drone == call.drone
                && c.action == call.action
                && c.target_name() == call.target_name()
        });
        match found {
            Some(c) => calls.push(c.clone()),
            None => {
                let options: Vec<String> = startable.iter().map(|c| c.to_string()).collect();
                rejections.push(format!(
                    "{call}: not a task that can start now (startable: {})",
                    options.join("; ")
                ));
            }
        }
    }
    (calls, rejections)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_prompts::ActionName;

    #[test]
    fn a_reply_gives_each_drone_its_first_call_and_names_the_later_steps() {
        let call = |task: &str, drone: &str, target: &str| Call {
            task: task.into(),
            drone: drone.into(),
            action: ActionName::Goto,
            target: target.into(),
            xyz: None,
        };
        // The 135M model's monolithic reply at 12 drones: one task id, alfa's whole route.
        let reply = vec![
            call("A1", "alfa", "car_1"),
            call("A1", "alfa", "car_2"),
            call("A2", "bravo", "car_4"),
            call("A3", "alfa", "car_1"),
            call("A1", "alfa", "car_3"),
        ];
        let (firsts, later) = first_call_per_drone(&reply);
        assert_eq!(firsts, vec![reply[0].clone(), reply[2].clone()]);
        // The repeat of alfa's first call (under another id) is no later step.
        assert_eq!(later, ["A1 alfa goto(car_2)", "A1 alfa goto(car_3)"]);
    }
}

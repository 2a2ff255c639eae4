//! The checks of a model's calls before they are sent: the static ones (the plan names real
//! drones, places and points) and the live ones (against the swarm now, through the safety gate).

use super::snapshot::Snapshot;
use crate::mission::resolve::{claimed_points, nearest_first, position_of, resolve};
use crate::safety::{CheckedAction, SafetyGate};
use tacos_prompts::Call;
use tacos_prompts::render::TaskStatus;
use tacos_shared::action::Action;
use tacos_shared::messages::TargetObservation;
use tacos_shared::{DroneId, DroneMode};

/// Checks a planned call that does not depend on the live state: the drone exists, the call
/// names something real, and a point is a place a drone may be.
pub(crate) fn check_static(
    call: &Call,
    scenario: &tacos_shared::scenario::Scenario,
    visible: &[TargetObservation],
) -> Result<(), String> {
    if !scenario.drones.iter().any(|d| d.id.as_str() == call.drone) {
        return Err(format!("there is no drone {:?}", call.drone));
    }
    let action = resolve(call, scenario, visible, &[], None)?;
    if let Action::Goto { target } = action {
        crate::safety::goto_point_fault(scenario, &target)?;
    }
    Ok(())
}

/// Checks calls against the live swarm: resolvable, through the safety gate, to drones that are
/// not busy, one drone per task id, and not repeating a task that is running or done. The calls
/// come one per drone (`first_call_per_drone`). Returns the accepted calls, the checks'
/// refusals and the gate's.
pub(crate) fn check_live(
    calls: &[Call],
    gate: &SafetyGate,
    snap: &Snapshot,
    tasks: &[(Call, TaskStatus)],
) -> (Vec<(Call, CheckedAction)>, Vec<String>, Vec<String>) {
    let mut accepted: Vec<(Call, CheckedAction)> = Vec::new();
    let mut rejections = Vec::new();
    let mut gate_refusals = Vec::new();
    let view = &snap.swarm;
    let now = snap.now;
    let visible = &snap.targets[..];
    let order = nearest_first(calls, gate.scenario(), visible, |d| position_of(view, d));
    for call in order {
        if let Some((other, _)) = accepted.iter().find(|(c, _)| c.task == call.task) {
            rejections.push(format!(
                "{call}: task {} already goes to {} this cycle",
                call.task, other.drone
            ));
            continue;
        }
        if let Some((_, status)) = tasks.iter().find(|(c, s)| {
            c.task == call.task && matches!(s, TaskStatus::Running | TaskStatus::Done)
        }) {
            let state = if *status == TaskStatus::Done {
                "done"
            } else {
                "running"
            };
            rejections.push(format!("{call}: task {} is already {state}", call.task));
            continue;
        }
        // Busy as the drone reports it, or with a task sent and not yet seen to finish.
        let busy = DroneId::new(&call.drone)
            .ok()
            .and_then(|id| view.get(&id).cloned())
            .is_some_and(|e| e.busy() && e.effective_mode(now) != DroneMode::Unavailable)
            || tasks
                .iter()
                .any(|(c, s)| *s == TaskStatus::Running && c.drone == call.drone);
        if busy {
            rejections.push(format!(
                "{call}: {} is still busy with its current action",
                call.drone
            ));
            continue;
        }
        // Clear of where the other drones are or go, this cycle's accepted gotos included.
        let mut claimed = claimed_points(view, &call.drone, now);
        claimed.extend(accepted.iter().filter_map(|(_, c)| match c.action() {
            Action::Goto { target } => Some(*target),
            _ => None,
        }));
        let action = match resolve(
            call,
            gate.scenario(),
            visible,
            &claimed,
            position_of(view, &call.drone),
        ) {
            Ok(a) => a,
            Err(why) => {
                rejections.push(format!("{call}: {why}"));
                continue;
            }
        };
        match gate.check(view, &call.drone, &action, now) {
            Ok(checked) => accepted.push((call.clone(), checked)),
            Err(r) => gate_refusals.push(format!("{call}: {r}")),
        }
    }
    (accepted, rejections, gate_refusals)
}

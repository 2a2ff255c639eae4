//! Whether a call can start now, and which of the plan's calls can: on one snapshot, with the
//! safety gate's own check.

use super::book::{ActivePlan, PlanBook};
use super::snapshot::Snapshot;
use crate::mission::resolve::{claimed_points, position_of, resolve};
use crate::safety::SafetyGate;
use tacos_prompts::Call;
use tacos_prompts::render::TaskStatus;
use tacos_shared::{DroneId, DroneMode};

/// What decides whether a call can start now: the step's snapshot, the gate, and the drones
/// with an action under way.
pub(crate) struct Start<'a> {
    pub(crate) snap: &'a Snapshot,
    pub(crate) gate: &'a SafetyGate,
    pub(crate) pending: Vec<DroneId>,
}

impl<'a> Start<'a> {
    pub(crate) fn new(snap: &'a Snapshot, gate: &'a SafetyGate, book: &PlanBook) -> Start<'a> {
        Start {
            snap,
            gate,
            pending: book.pending_drones(),
        }
    }

    /// Why `call` cannot start now on its drone; `None` when it can.
    pub(crate) fn blocker(&self, call: &Call) -> Option<String> {
        let view = &self.snap.swarm;
        let now = self.snap.now;
        let drone = &call.drone;
        let Some(entry) = DroneId::new(drone).ok().and_then(|id| view.get(&id)) else {
            return Some(format!("{drone} is not in the swarm"));
        };
        if entry.effective_mode(now) == DroneMode::Unavailable {
            return Some(format!("{drone} is unavailable"));
        }
        // A drone that follows another ground station takes none of our actions, as after a
        // restart until the old one has been silent for the drone's hold time.
        if let Some(other) = entry
            .status
            .as_ref()
            .and_then(|s| s.ground)
            .filter(|g| *g != self.snap.ground)
        {
            return Some(format!(
                "{drone} follows another ground station ({other}) until it falls silent"
            ));
        }
        if entry.busy() || self.pending.contains(&entry.id) {
            return Some(format!("{drone} is busy with another action"));
        }
        let claimed = claimed_points(view, drone, now);
        let action = match resolve(
            call,
            self.gate.scenario(),
            &self.snap.targets,
            &claimed,
            position_of(view, drone),
        ) {
            Ok(action) => action,
            Err(why) => return Some(why),
        };
        self.gate
            .check(view, drone, &action, now)
            .err()
            .map(|r| r.to_string())
    }
}

/// The plan's calls that could start now: tasks not started, on their own drone; failed tasks,
/// on any drone of the swarm; each only if `Start::blocker` has nothing against it.
pub(crate) fn startable(plan: &ActivePlan, start: &Start<'_>) -> Vec<Call> {
    let swarm = start.snap.swarm_ids(start.gate.scenario());
    let mut out = Vec::new();
    // No order is imposed here: the plan's temporal dependencies are the Supervisor's to
    // infer (the paper's division of labour); the drone's mode rules what is possible.
    for task in &plan.tasks {
        let drones: Vec<String> = match &task.status {
            TaskStatus::NotStarted => vec![task.call.drone.clone()],
            TaskStatus::Failed(_) => swarm.clone(),
            _ => continue,
        };
        for drone in drones {
            let call = Call {
                drone,
                ..task.call.clone()
            };
            if start.blocker(&call).is_none() {
                out.push(call);
            }
        }
    }
    out
}

/// Why each of the plan's unfinished tasks cannot start now, as the pilot reads it.
pub(crate) fn blockers(plan: &ActivePlan, start: &Start<'_>) -> Vec<String> {
    plan.tasks
        .iter()
        .filter(|t| t.status != TaskStatus::Done)
        .map(|t| match start.blocker(&t.call) {
            Some(why) => format!("{} ({why})", t.call),
            None => t.call.to_string(),
        })
        .collect()
}

//! The mission's state as the prompts show it: the swarm's lines, the world, the drones and
//! places a reply may name, and the pending plan.

use super::Mission;
use crate::mission::untrusted;
use tacos_prompts::Call;
use tacos_prompts::render::{self, DroneLine, TaskStatus};
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionState, TargetObservation};
use tacos_shared::{DroneId, DroneMode};

impl Mission {
    /// The drones resting on the ground now (idle, disarmed).
    pub(super) fn grounded_ids(&self) -> Vec<String> {
        let view = self.link.view();
        let now = self.link.clock().instant();
        view.drones()
            .filter(|e| e.effective_mode(now) == DroneMode::Idle)
            .map(|e| e.id.to_string())
            .collect()
    }

    /// The targets seen now that the scenario has: a name from the network reaches a prompt
    /// only when it is one of the map's (`untrusted`).
    pub(super) fn visible_targets(&self) -> Vec<TargetObservation> {
        let seen = self.targets.borrow();
        let known = untrusted::known_targets(&seen, self.gate.scenario());
        let unknown = seen.len() - known.len();
        if unknown > 0 {
            tracing::debug!(
                unknown,
                "observations of targets the map does not have left out"
            );
        }
        known
    }

    pub(super) fn drone_lines(&self) -> Vec<DroneLine> {
        let view = self.link.view();
        let now = self.link.clock().instant();
        self.gate
            .scenario()
            .drones
            .iter()
            .filter_map(|slot| view.get(&slot.id))
            .map(|e| {
                let status = e.status.as_ref();
                let (action, state) = match status.and_then(|s| s.action.as_ref()) {
                    Some(p) => (
                        Some(
                            format!("{} {}", p.task_id.clone().unwrap_or_default(), p.action)
                                .trim()
                                .to_owned(),
                        ),
                        Some(match &p.state {
                            ActionState::Running { progress } => {
                                format!("running {:.0}%", progress * 100.0)
                            }
                            ActionState::Done => "done".into(),
                            ActionState::Failed(why) => format!("failed: {why}"),
                        }),
                    ),
                    None => (None, None),
                };
                DroneLine {
                    id: e.id.to_string(),
                    mode: e.effective_mode(now),
                    position: status.map(|s| s.position).unwrap_or_default(),
                    speed: status.map_or(0.0, |s| s.velocity.norm()),
                    action,
                    state,
                }
            })
            .collect()
    }

    pub(super) fn world_text(&self) -> String {
        render::world(
            &self.gate.scenario().world,
            &self.visible_targets(),
            &self.events,
        )
    }

    /// The drones of this swarm: those the ground has heard from, in scenario order.
    pub(super) fn swarm_ids(&self) -> Vec<String> {
        let view = self.link.view();
        self.gate
            .scenario()
            .drones
            .iter()
            .filter(|d| view.get(&d.id).is_some())
            .map(|d| d.id.to_string())
            .collect()
    }

    /// The swarm's drones a plan may use now: all but the unavailable ones (lost link, failed),
    /// in the scenario's order.
    pub(super) fn available_ids(&self) -> Vec<String> {
        // Before the view is locked: `swarm_ids` locks it too.
        let ids = self.swarm_ids();
        let view = self.link.view();
        let now = self.link.clock().instant();
        ids.into_iter()
            .filter(|d| {
                DroneId::new(d)
                    .ok()
                    .and_then(|id| view.get(&id))
                    .is_some_and(|e| e.effective_mode(now) != DroneMode::Unavailable)
            })
            .collect()
    }

    pub(super) fn enums(&self) -> (Vec<String>, Vec<String>) {
        let s = self.gate.scenario();
        let drones = self.swarm_ids();
        let places = s
            .world
            .landmarks
            .iter()
            .map(|l| l.name.clone())
            .chain(self.trackable())
            .collect();
        (drones, places)
    }

    /// The targets a drone may be asked to follow: the scenario's targets that are not hidden.
    pub(super) fn trackable(&self) -> Vec<String> {
        self.gate
            .scenario()
            .targets
            .iter()
            .filter(|t| t.hidden_at.is_none())
            .map(|t| t.name.clone())
            .collect()
    }

    /// The targets that drones follow now (tracking, by their status).
    pub(super) fn followed_targets(&self) -> Vec<String> {
        let view = self.link.view();
        let now = self.link.clock().instant();
        view.drones()
            .filter(|e| e.effective_mode(now) == DroneMode::Tracking)
            .filter_map(|e| match &e.status.as_ref()?.action.as_ref()?.action {
                Action::StartTracking { target } => Some(target.clone()),
                _ => None,
            })
            .collect()
    }

    pub(super) fn plan_lines(&self) -> Vec<(Call, TaskStatus)> {
        self.book
            .plan
            .iter()
            .flat_map(|p| p.tasks.iter())
            .map(|t| (t.call.clone(), t.status.clone()))
            .collect()
    }
}

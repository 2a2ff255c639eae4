//! The swarm as the layers' prompts and schemas show it, read from one [`Snapshot`]: the
//! drones' lines, which drones a plan may use, which rest on the ground, the targets followed,
//! the names a reply may use, the world's text, and what the monolithic model may call now.
//! One snapshot per prompt, so every line of a prompt and its schema sees the same swarm.

use super::book::PlanBook;
use super::outcomes::effect_holds;
use super::snapshot::Snapshot;
use tacos_prompts::offer::Callable;
use tacos_prompts::render::{self, DroneLine, TaskStatus};
use tacos_prompts::{ActionName, Call};
use tacos_shared::action::Action;
use tacos_shared::messages::ActionState;
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, DroneMode};

impl Snapshot {
    /// The drones resting on the ground (idle, disarmed).
    pub(crate) fn grounded_ids(&self) -> Vec<String> {
        self.swarm
            .drones()
            .filter(|e| e.effective_mode(self.now) == DroneMode::Idle)
            .map(|e| e.id.to_string())
            .collect()
    }

    /// The swarm's drones a plan may use: all but the unavailable ones (lost link, failed), in
    /// the scenario's order.
    pub(crate) fn available_ids(&self, scenario: &Scenario) -> Vec<String> {
        self.swarm_ids(scenario)
            .into_iter()
            .filter(|d| self.mode_of(d).is_some_and(|m| m != DroneMode::Unavailable))
            .collect()
    }

    /// The mode of `drone` now, if the view has heard of it.
    pub(crate) fn mode_of(&self, drone: &str) -> Option<DroneMode> {
        let entry = DroneId::new(drone)
            .ok()
            .and_then(|id| self.swarm.get(&id))?;
        Some(entry.effective_mode(self.now))
    }

    /// The targets drones follow (tracking, by their status).
    pub(crate) fn followed_targets(&self) -> Vec<String> {
        self.swarm
            .drones()
            .filter(|e| e.effective_mode(self.now) == DroneMode::Tracking)
            .filter_map(|e| match &e.status.as_ref()?.action.as_ref()?.action {
                Action::StartTracking { target } => Some(target.clone()),
                _ => None,
            })
            .collect()
    }

    /// Each drone of the swarm as a prompt shows it, in the scenario's order.
    pub(crate) fn drone_lines(&self, scenario: &Scenario) -> Vec<DroneLine> {
        scenario
            .drones
            .iter()
            .filter_map(|slot| self.swarm.get(&slot.id))
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
                    mode: e.effective_mode(self.now),
                    position: status.map(|s| s.position).unwrap_or_default(),
                    speed: status.map_or(0.0, |s| s.velocity.norm()),
                    action,
                    state,
                }
            })
            .collect()
    }

    /// The world as the prompts show it: the map, the targets seen, the world's `events`.
    pub(crate) fn world_text(&self, scenario: &Scenario, events: &[String]) -> render::WorldText {
        render::world(&scenario.world, &self.targets, events)
    }

    /// The names a reply may use: the swarm's drones, and the places (landmarks and the
    /// targets a drone may follow).
    pub(crate) fn enums(&self, scenario: &Scenario) -> (Vec<String>, Vec<String>) {
        let places = (scenario.world.landmarks.iter())
            .map(|l| l.name.clone())
            .chain(trackable(scenario))
            .collect();
        (self.swarm_ids(scenario), places)
    }

    /// What the monolithic model may call now: for each drone that can take an action, a fresh
    /// task id (from `A<next_task + 1>`) and the actions its mode allows whose effect does not
    /// already hold. Points and targets are checked per call afterwards, by `check_live` and
    /// the safety gate.
    pub(crate) fn callable(&self, scenario: &Scenario, book: &PlanBook) -> Vec<Callable> {
        let pending = book.pending_drones();
        let mut out = Vec::new();
        for drone in self.swarm_ids(scenario) {
            let Some(entry) = DroneId::new(&drone).ok().and_then(|id| self.swarm.get(&id)) else {
                continue;
            };
            if !entry.ready(self.now) || pending.contains(&entry.id) {
                continue;
            }
            let mode = entry.effective_mode(self.now);
            let actions: Vec<ActionName> = ActionName::ALL
                .into_iter()
                .filter(|a| {
                    !effect_holds(*a, mode)
                        && tacos_shared::action::mode_forbids(&mode_probe(*a), mode).is_none()
                })
                .collect();
            if actions.is_empty() {
                continue;
            }
            out.push(Callable {
                task: format!("A{}", book.mnl.next_task + 1 + out.len() as u32),
                drone,
                actions,
            });
        }
        out
    }
}

/// The targets a drone may be asked to follow: the scenario's targets that are not hidden.
pub(crate) fn trackable(scenario: &Scenario) -> Vec<String> {
    (scenario.targets.iter())
        .filter(|t| t.hidden_at.is_none())
        .map(|t| t.name.clone())
        .collect()
}

/// The plan's tasks with their status, as the prompts and checks read them.
pub(crate) fn plan_lines(book: &PlanBook) -> Vec<(Call, TaskStatus)> {
    (book.plan.iter())
        .flat_map(|p| p.tasks.iter())
        .map(|t| (t.call.clone(), t.status.clone()))
        .collect()
}

/// An action of this kind, for asking whether a mode allows it (the argument does not matter
/// to the mode rules; the real argument is checked by the safety gate).
fn mode_probe(name: ActionName) -> Action {
    match name {
        ActionName::ArmTakeoff => Action::ArmTakeoff,
        ActionName::Goto => Action::Goto {
            target: tacos_shared::Vec3::default(),
        },
        ActionName::StartTracking => Action::StartTracking {
            target: String::new(),
        },
        ActionName::StopTracking => Action::StopTracking,
        ActionName::Land => Action::Land,
        ActionName::Hold => Action::Hold,
    }
}

//! The safety gate: every action is checked here before it leaves the ground, whoever proposed
//! it (the pilot's direct commands, the demo, a model). The drone checks again on board.

use crate::swarm::SwarmView;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::time::Instant;
use tacos_shared::action::{Action, mode_forbids};
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, DroneMode, Vec3};

/// One reason an action may not be sent.
#[derive(Debug, Clone, PartialEq)]
pub enum Rejection {
    UnknownDrone {
        drone: String,
        known: Vec<String>,
    },
    Unavailable(DroneId),
    ModeForbids {
        drone: DroneId,
        mode: DroneMode,
        action: &'static str,
        why: &'static str,
    },
    BadPoint {
        drone: DroneId,
        why: String,
    },
    UnknownTarget {
        target: String,
        known: Vec<String>,
    },
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Rejection::UnknownDrone { drone, known } => {
                write!(
                    f,
                    "there is no drone {drone:?} (known: {})",
                    known.join(", ")
                )
            }
            Rejection::Unavailable(d) => write!(
                f,
                "{d} is unavailable (gone, stale, without autopilot link, or flown by PX4 out of offboard)"
            ),
            Rejection::ModeForbids {
                drone,
                mode,
                action,
                why,
            } => write!(f, "{drone} is {mode}: {action} not allowed ({why})"),
            Rejection::BadPoint { drone, why } => write!(f, "goto for {drone}: {why}"),
            Rejection::UnknownTarget { target, known } => {
                write!(
                    f,
                    "there is no target {target:?} (known: {})",
                    known.join(", ")
                )
            }
        }
    }
}

/// What the gate knew of a drone when it judged an action: all it reads of the live swarm.
/// Logged with each send (`Record::ActionSent`), so an audit can run the gate again on what
/// was sent ([`SafetyGate::recheck`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct DroneSeen {
    /// The mode of the drone's latest status (`Unavailable` when none came).
    pub mode: DroneMode,
    /// The status was recent and the drone's liveliness token present.
    pub fresh: bool,
    pub autopilot_link: bool,
}

/// Actions the gate never refuses for an old status: what a pilot sends a drone in trouble.
/// A stale status is what trouble looks like from the ground (a drone out of radio range, a
/// frozen onboard), and asking such a drone to land or hold cannot make anything worse; the
/// drone judges them again on board.
pub fn is_emergency(action: &Action) -> bool {
    matches!(action, Action::Land | Action::Hold)
}

/// An action that passed the gate. Only the gate makes one ([`SafetyGate::check`], or
/// [`SafetyGate::recheck`] on a drone's state as recorded), and only a checked
/// action can be sent (`GroundLink::send`), so nothing reaches a drone around the gate.
#[derive(Debug, Clone, PartialEq)]
pub struct CheckedAction {
    drone: DroneId,
    action: Action,
    seen: DroneSeen,
}

impl CheckedAction {
    pub fn drone(&self) -> &DroneId {
        &self.drone
    }
    pub fn action(&self) -> &Action {
        &self.action
    }
    /// The drone's state the action was checked against.
    pub fn seen(&self) -> DroneSeen {
        self.seen
    }
}

/// The gate's view of the world: the scenario and the names of trackable targets.
#[derive(Clone)]
pub struct SafetyGate {
    scenario: Scenario,
    targets: Vec<String>,
}

impl SafetyGate {
    pub fn new(scenario: Scenario) -> Self {
        let targets = scenario.targets.iter().map(|t| t.name.clone()).collect();
        SafetyGate { scenario, targets }
    }

    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }

    /// Checks one action for one drone against the live swarm view.
    pub fn check(
        &self,
        view: &SwarmView,
        drone: &str,
        action: &Action,
        now: Instant,
    ) -> Result<CheckedAction, Rejection> {
        let known = || view.drones().map(|d| d.id.to_string()).collect::<Vec<_>>();
        let unknown = || Rejection::UnknownDrone {
            drone: drone.to_owned(),
            known: known(),
        };
        let id = DroneId::new(drone).map_err(|_| unknown())?;
        let entry = view.get(&id).ok_or_else(unknown)?;
        let seen = DroneSeen {
            mode: entry
                .status
                .as_ref()
                .map_or(DroneMode::Unavailable, |s| s.mode),
            fresh: entry.effective_mode(now) != DroneMode::Unavailable,
            autopilot_link: entry.status.as_ref().is_some_and(|s| s.autopilot_link),
        };
        self.checked(id, seen, action)
    }

    /// The gate run again, away from the swarm, on what it saw of a drone: the audit of a
    /// mission log, and a replayed mission trace (`mission::core::trace`), which gets its
    /// checked actions back this way. The same rules as [`check`](Self::check); the drone must
    /// be one of the scenario's.
    pub fn recheck(
        &self,
        drone: &str,
        seen: DroneSeen,
        action: &Action,
    ) -> Result<CheckedAction, Rejection> {
        let known = || {
            self.scenario
                .drones
                .iter()
                .map(|d| d.id.to_string())
                .collect::<Vec<_>>()
        };
        let id = DroneId::new(drone)
            .ok()
            .filter(|id| self.scenario.drones.iter().any(|d| d.id == *id))
            .ok_or_else(|| Rejection::UnknownDrone {
                drone: drone.to_owned(),
                known: known(),
            })?;
        self.checked(id, seen, action)
    }

    /// `action` for `id` as checked, if the rules let it through on the drone's state as seen.
    fn checked(
        &self,
        id: DroneId,
        seen: DroneSeen,
        action: &Action,
    ) -> Result<CheckedAction, Rejection> {
        self.judge(&id, seen, action)?;
        Ok(CheckedAction {
            drone: id,
            action: action.clone(),
            seen,
        })
    }

    /// The rules, on the drone's state as seen.
    fn judge(&self, id: &DroneId, seen: DroneSeen, action: &Action) -> Result<(), Rejection> {
        let mode = seen.mode;
        let stale = !seen.fresh && !is_emergency(action);
        if mode == DroneMode::Unavailable || !seen.autopilot_link || stale {
            return Err(Rejection::Unavailable(id.clone()));
        }
        if let Some(why) = mode_forbids(action, mode) {
            return Err(Rejection::ModeForbids {
                drone: id.clone(),
                mode,
                action: action.name(),
                why,
            });
        }
        match action {
            Action::Goto { target } => {
                goto_point_fault(&self.scenario, target).map_err(|why| Rejection::BadPoint {
                    drone: id.clone(),
                    why,
                })?;
            }
            Action::StartTracking { target } if !self.targets.contains(target) => {
                return Err(Rejection::UnknownTarget {
                    target: target.clone(),
                    known: self.targets.clone(),
                });
            }
            _ => {}
        }
        Ok(())
    }
}

/// Why a goto to `target` can never be flown on this map, whatever the drone's state: outside
/// the flight area, inside an obstacle (with the drone's radius), or too low (a goto is not a
/// landing). The gate's rule, also applied when a plan is made (`mission::core::checks`).
pub fn goto_point_fault(scenario: &Scenario, target: &Vec3) -> Result<(), String> {
    let limits = &scenario.limits;
    scenario
        .world
        .check_point(target, limits.drone_radius)
        .map_err(|e| e.to_string())?;
    if target.z < limits.drone_radius * 2.0 {
        return Err(format!(
            "altitude {:.1} m is too low for a goto: use land",
            target.z
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_shared::Vec3;

    fn view_with(id: &str, mode: DroneMode, now: Instant) -> SwarmView {
        let mut view = SwarmView::default();
        view.apply_status(crate::swarm::test_status(id, mode), now);
        view
    }

    #[test]
    fn gate_rejects_what_must_not_fly() {
        let gate = SafetyGate::new(Scenario::builtin("city").expect("city"));
        let now = Instant::now();
        let flying = view_with("alfa", DroneMode::Flying, now);
        let idle = view_with("alfa", DroneMode::Idle, now);
        let goto = |x, y, z| Action::Goto {
            target: Vec3::new(x, y, z),
        };

        assert!(
            gate.check(&flying, "alfa", &goto(-40.0, -100.0, 10.0), now)
                .is_ok()
        );
        assert!(matches!(
            gate.check(&flying, "zulu", &Action::Land, now),
            Err(Rejection::UnknownDrone { .. })
        ));
        assert!(matches!(
            gate.check(&flying, "Bad/Id", &Action::Land, now),
            Err(Rejection::UnknownDrone { .. })
        ));
        assert!(matches!(
            gate.check(&idle, "alfa", &goto(-40.0, -100.0, 10.0), now),
            Err(Rejection::ModeForbids { .. })
        ));
        // Into a skyscraper, out of the area, underground.
        assert!(matches!(
            gate.check(&flying, "alfa", &goto(18.0, 18.0, 20.0), now),
            Err(Rejection::BadPoint { .. })
        ));
        assert!(matches!(
            gate.check(&flying, "alfa", &goto(500.0, 0.0, 10.0), now),
            Err(Rejection::BadPoint { .. })
        ));
        assert!(matches!(
            gate.check(&flying, "alfa", &goto(0.0, -100.0, -5.0), now),
            Err(Rejection::BadPoint { .. })
        ));
        assert!(matches!(
            gate.check(
                &flying,
                "alfa",
                &Action::StartTracking {
                    target: "ghost".into()
                },
                now
            ),
            Err(Rejection::UnknownTarget { .. })
        ));
        assert!(
            gate.check(
                &flying,
                "alfa",
                &Action::StartTracking {
                    target: "van".into()
                },
                now
            )
            .is_ok()
        );
        // Just above the ground (inside the box, clear of every obstacle) is too low for a
        // goto; a point that is not a number is no point.
        let low = gate.scenario().limits.drone_radius * 1.5;
        assert!(
            matches!(
                gate.check(&flying, "alfa", &goto(-40.0, -100.0, low), now),
                Err(Rejection::BadPoint { why, .. }) if why.contains("too low")
            ),
            "{:?}",
            gate.check(&flying, "alfa", &goto(-40.0, -100.0, low), now)
        );
        assert!(matches!(
            gate.check(&flying, "alfa", &goto(f64::NAN, -100.0, 10.0), now),
            Err(Rejection::BadPoint { .. })
        ));
        // A drone whose status is stale is unavailable, but may always be told to land or
        // hold (judged by its last reported mode).
        let later = now + std::time::Duration::from_secs(3);
        assert!(matches!(
            gate.check(&flying, "alfa", &goto(-40.0, -100.0, 10.0), later),
            Err(Rejection::Unavailable(_))
        ));
        assert!(matches!(
            gate.check(&flying, "alfa", &Action::ArmTakeoff, later),
            Err(Rejection::Unavailable(_))
        ));
        for emergency in [Action::Land, Action::Hold] {
            let checked = gate.check(&flying, "alfa", &emergency, later);
            assert!(
                checked.as_ref().is_ok_and(|c| !c.seen().fresh),
                "{emergency}: {checked:?}"
            );
        }
    }

    /// The audit's gate: the same verdicts from what the live gate saw, away from the swarm.
    #[test]
    fn the_gate_run_again_on_what_it_saw_gives_the_same_verdict() {
        let gate = SafetyGate::new(Scenario::builtin("city").expect("city"));
        let now = Instant::now();
        let goto = |x, y, z| Action::Goto {
            target: Vec3::new(x, y, z),
        };
        let actions = [
            goto(-40.0, -100.0, 10.0),
            goto(18.0, 18.0, 20.0),
            Action::Land,
            Action::ArmTakeoff,
            Action::StartTracking {
                target: "ghost".into(),
            },
        ];
        for mode in [DroneMode::Idle, DroneMode::Flying] {
            let view = view_with("alfa", mode, now);
            for action in &actions {
                let live = gate.check(&view, "alfa", action, now);
                let seen = DroneSeen {
                    mode,
                    fresh: true,
                    autopilot_link: true,
                };
                let again = gate.recheck("alfa", seen, action);
                assert_eq!(live.as_ref().err(), again.as_ref().err(), "{mode} {action}");
                if let Ok(c) = live {
                    assert_eq!(c.seen(), seen);
                }
            }
        }
        let flying = DroneSeen {
            mode: DroneMode::Flying,
            fresh: true,
            autopilot_link: true,
        };
        assert!(matches!(
            gate.recheck("zulu", flying, &Action::Land),
            Err(Rejection::UnknownDrone { .. })
        ));
        let unlinked = DroneSeen {
            autopilot_link: false,
            ..flying
        };
        assert!(matches!(
            gate.recheck("alfa", unlinked, &Action::Land),
            Err(Rejection::Unavailable(_))
        ));
    }
}

//! The paper's action set A (plus `hold`), and the command that carries one to a drone.

use crate::geometry::Vec3;
use crate::mode::DroneMode;
use serde::{Deserialize, Serialize};
use std::fmt;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Action {
    /// Arm and climb to the drone's configured take-off altitude.
    ArmTakeoff,
    /// Fly to a point in the world frame (ENU metres).
    Goto { target: Vec3 },
    /// Follow a named target.
    StartTracking { target: String },
    /// Stop following and hold where the drone is.
    StopTracking,
    /// Land where the drone is and disarm.
    Land,
    /// Stop and hold the current position.
    Hold,
}

/// Why an action cannot start in a given mode, or `None` when it may.
pub fn mode_forbids(action: &Action, mode: DroneMode) -> Option<&'static str> {
    use DroneMode::*;
    match (action, mode) {
        (_, Unavailable) => Some("the drone is unavailable"),
        (Action::ArmTakeoff, Flying | Tracking) => Some("the drone is already airborne"),
        (Action::Goto { .. } | Action::StartTracking { .. }, Idle) => {
            Some("the drone is on the ground: take off first")
        }
        (Action::StopTracking, Idle) => Some("the drone is on the ground"),
        (Action::Land | Action::Hold, Idle) => None,
        _ => None,
    }
}

impl Action {
    /// The API name used in prompts and on the command line.
    pub fn name(&self) -> &'static str {
        match self {
            Action::ArmTakeoff => "arm_takeoff",
            Action::Goto { .. } => "goto",
            Action::StartTracking { .. } => "start_tracking",
            Action::StopTracking => "stop_tracking",
            Action::Land => "land",
            Action::Hold => "hold",
        }
    }

    /// Parses the command-line form: `arm_takeoff`, `goto X Y Z`, `start_tracking NAME`,
    /// `stop_tracking`, `land`, `hold`.
    pub fn parse_words(words: &[&str]) -> Result<Action, String> {
        let (name, args) = words.split_first().ok_or("no action given")?;
        let expect_args = |n: usize| {
            if args.len() == n {
                Ok(())
            } else {
                Err(format!("{name} takes {n} argument(s), got {}", args.len()))
            }
        };
        match *name {
            "arm_takeoff" | "takeoff" => expect_args(0).map(|_| Action::ArmTakeoff),
            "goto" => {
                expect_args(3)?;
                let mut xyz = [0.0; 3];
                for (slot, raw) in xyz.iter_mut().zip(args) {
                    *slot = raw
                        .parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| format!("goto: {raw:?} is not a finite number"))?;
                }
                Ok(Action::Goto {
                    target: Vec3::new(xyz[0], xyz[1], xyz[2]),
                })
            }
            "start_tracking" => {
                expect_args(1)?;
                Ok(Action::StartTracking {
                    target: args[0].to_owned(),
                })
            }
            "stop_tracking" => expect_args(0).map(|_| Action::StopTracking),
            "land" => expect_args(0).map(|_| Action::Land),
            "hold" => expect_args(0).map(|_| Action::Hold),
            other => Err(format!(
                "unknown action {other:?} (arm_takeoff, goto X Y Z, start_tracking TARGET, stop_tracking, land, hold)"
            )),
        }
    }
}

impl fmt::Display for Action {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Action::Goto { target } => {
                write!(f, "goto({:.1}, {:.1}, {:.1})", target.x, target.y, target.z)
            }
            Action::StartTracking { target } => write!(f, "start_tracking({target})"),
            other => write!(f, "{}()", other.name()),
        }
    }
}

/// An action sent from the ground to one drone. `ground` names the ground station that sent it
/// (its epoch, as in its heartbeat); `seq` grows per ground station so a drone can tell a new
/// command from a repeated or replayed one; `task_id` ties it to a subtask of the plan, when
/// there is one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionCommand {
    pub ground: u64,
    pub seq: u64,
    /// When the ground station sent it, in seconds of its clock (as its heartbeats'
    /// `GroundHeartbeat::stamp`): a drone measures how late an action arrives against the
    /// beats of the same ground, so the two clocks need not agree.
    pub sent_at: f64,
    pub task_id: Option<String>,
    pub action: Action,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_command_line_actions() {
        assert_eq!(
            Action::parse_words(&["arm_takeoff"]),
            Ok(Action::ArmTakeoff)
        );
        assert_eq!(
            Action::parse_words(&["goto", "1", "-2.5", "10"]),
            Ok(Action::Goto {
                target: Vec3::new(1.0, -2.5, 10.0)
            })
        );
        assert!(Action::parse_words(&["goto", "1", "2"]).is_err());
        assert!(Action::parse_words(&["goto", "1", "2", "NaN"]).is_err());
        assert!(Action::parse_words(&["fly"]).is_err());
        assert!(Action::parse_words(&[]).is_err());
    }

    #[test]
    fn modes_gate_actions() {
        let goto = Action::Goto {
            target: Vec3::zeros(),
        };
        assert!(mode_forbids(&goto, DroneMode::Idle).is_some());
        assert!(mode_forbids(&goto, DroneMode::Flying).is_none());
        assert!(mode_forbids(&Action::ArmTakeoff, DroneMode::Idle).is_none());
        assert!(mode_forbids(&Action::ArmTakeoff, DroneMode::Flying).is_some());
        assert!(mode_forbids(&Action::Land, DroneMode::Unavailable).is_some());
    }
}

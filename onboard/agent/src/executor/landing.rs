//! Landing under offboard control: the planner brings the drone down to the hand-over height,
//! apart from its neighbours; then it sinks onto the floor at [`TOUCHDOWN_SPEED`] until PX4's
//! land detector says it is down, and is disarmed. PX4's own landing (NAV_LAND) is the fallback:
//! for a drone not in OFFBOARD, above an obstacle, or not detected as landed in time.
//!
//! Measured on PX4 SITL (SIH): AUTO.LAND keeps apart from nobody and its last 0.3 m drifted
//! tenths of a metre; three drones of the lab map (1 m apart) came within 0.52 m there.

use super::{Executor, Task};
use crate::motion::Steering;
use crate::planner::Goal;
use tacos_shared::Vec3;
use tacos_shared::ipc::CommandKind;
use tacos_shared::messages::{ActionState, FailureReason};

/// The descent asked for in the last centimetres, m/s. PX4's land detector takes ground contact
/// only while the setpoint descends at ≥ 1.1 × 0.9 × MPC_LAND_SPEED (0.69 m/s at its default
/// 0.7 m/s); PX4's own landing touches down at MPC_LAND_SPEED too.
pub const TOUCHDOWN_SPEED: f64 = 0.8;
/// How far below the vehicle's measured height the sinking point may run ahead. The point is
/// never stopped at a fixed depth: a vehicle tracking it would brake there, and PX4 SIH's ground
/// holds only a vehicle whose net force points down, so one braking at the floor sank through it
/// (1.5 m below the floor, seen in CI, after which the next take-off was 1.5 m short). Held by
/// the floor, the vehicle stays this far above the point: pressed into the ground, its thrust
/// drops, which the land detector also wants.
const SINK_LEAD: f64 = 0.5;
/// Time allowed for PX4's land detector after the touchdown (measured 3.5 s: ground contact,
/// maybe landed, landed), before PX4's own landing is asked for instead.
const DETECTION_ALLOWANCE_S: f64 = 10.0;

#[derive(Debug, Clone, PartialEq)]
pub(super) enum LandPhase {
    /// Descending through the planner to `handoff`, until the time given at the latest.
    Descend { handoff: Vec3, until: f64 },
    /// Sinking from `from` since `since` (see [`TOUCHDOWN_SPEED`]); PX4's landing is asked for
    /// if the vehicle is not down by `until`. `disarm_asked` once it was seen landed.
    Touchdown {
        from: Vec3,
        since: f64,
        until: f64,
        disarm_asked: bool,
    },
    /// PX4's own landing was asked for (and `accepted`).
    Autopilot { accepted: bool },
}

impl Executor {
    /// How high above the floor the planner's descent ends and the sinking starts.
    fn handoff_height(&self) -> f64 {
        (2.0 * self.cfg.limits.drone_radius).max(0.3)
    }

    fn floor(&self) -> f64 {
        self.cfg.world.bounds.min.z
    }

    fn touchdown_from(&self, from: Vec3, now: f64) -> LandPhase {
        let height = (from.z - self.floor()).max(0.0);
        LandPhase::Touchdown {
            from,
            since: now,
            until: now + height / TOUCHDOWN_SPEED + DETECTION_ALLOWANCE_S,
            disarm_asked: false,
        }
    }

    /// Lands: under offboard control when the drone is airborne in OFFBOARD and the floor below
    /// it is free; otherwise PX4's landing.
    pub(super) fn start_landing(&mut self, now: f64) {
        let Some(vehicle) = self.vehicle else { return };
        let deadline = now + 60.0 + vehicle.position.z / 0.5;
        let p = vehicle.position;
        let handoff = Vec3::new(p.x, p.y, self.floor() + self.handoff_height());
        let offboard = self.airborne()
            && self.in_offboard()
            && self
                .cfg
                .world
                .check_point(&handoff, self.cfg.limits.drone_radius)
                .is_ok();
        let phase = if !offboard {
            self.request(CommandKind::Land, 0.0);
            LandPhase::Autopilot { accepted: false }
        } else if p.z > handoff.z + 0.2 {
            // Room for the descent at a third of PX4's default 1.5 m/s down.
            LandPhase::Descend {
                handoff,
                until: now + 10.0 + (p.z - handoff.z) / 0.5,
            }
        } else {
            self.touchdown_from(p, now)
        };
        self.task = Task::Land { phase, deadline };
    }

    pub(super) fn landing_steering(&self, phase: &LandPhase, now: f64) -> Option<Steering> {
        match *phase {
            LandPhase::Descend { handoff, .. } => Some(Steering::Toward(Goal::fixed(handoff))),
            LandPhase::Touchdown { from, since, .. } => {
                let measured = self.vehicle.map_or(from.z, |v| v.position.z);
                let z =
                    (from.z - TOUCHDOWN_SPEED * (now - since).max(0.0)).max(measured - SINK_LEAD);
                Some(Steering::Sink {
                    point: Vec3::new(from.x, from.y, z),
                    speed: TOUCHDOWN_SPEED,
                })
            }
            LandPhase::Autopilot { .. } => None,
        }
    }

    /// PX4's landing instead of ours, from where the drone is.
    fn hand_over_to_autopilot(&mut self, deadline: f64) {
        self.task = Task::Land {
            phase: LandPhase::Autopilot { accepted: false },
            deadline,
        };
        self.request(CommandKind::Land, 0.0);
    }

    fn landed(&mut self) {
        self.hold_point = None;
        self.task = Task::Idle;
        self.finish(ActionState::Done);
    }

    pub(super) fn advance_landing(&mut self, phase: LandPhase, deadline: f64, now: f64) {
        let Some(vehicle) = self.vehicle else { return };
        let takeoff_altitude = self.cfg.limits.takeoff_altitude.max(0.1);
        let height = (vehicle.position.z - self.floor()).max(0.0);
        match phase {
            LandPhase::Descend { handoff, until } => {
                let there =
                    (vehicle.position.z - handoff.z).abs() <= 0.1 && vehicle.velocity.norm() <= 0.3;
                if !vehicle.armed {
                    self.landed();
                } else if self.left_offboard(&vehicle, now) {
                    self.hand_over_to_autopilot(deadline);
                } else if there || now > until {
                    let phase = self.touchdown_from(vehicle.position, now);
                    self.task = Task::Land { phase, deadline };
                } else {
                    let progress = 1.0 - height / takeoff_altitude;
                    self.set_running((progress.clamp(0.0, 1.0) * 0.5) as f32);
                }
            }
            LandPhase::Touchdown {
                from,
                since,
                until,
                disarm_asked,
            } => {
                if !vehicle.armed {
                    self.landed();
                } else if self.left_offboard(&vehicle, now) || now > until {
                    self.hand_over_to_autopilot(deadline);
                } else if vehicle.landed && !disarm_asked {
                    // PX4 would disarm by itself after COM_DISARM_LAND, unless that is off.
                    self.request(CommandKind::Disarm, 0.0);
                    self.task = Task::Land {
                        phase: LandPhase::Touchdown {
                            from,
                            since,
                            until,
                            disarm_asked: true,
                        },
                        deadline,
                    };
                } else {
                    let progress = 1.0 - height / takeoff_altitude;
                    self.set_running((0.5 + progress.clamp(0.0, 1.0) * 0.45) as f32);
                }
            }
            LandPhase::Autopilot { accepted } => {
                if accepted && !vehicle.armed {
                    self.landed();
                } else if now > deadline {
                    self.fail(FailureReason::TimedOut);
                } else if accepted {
                    let progress = 1.0 - height / takeoff_altitude;
                    self.set_running((progress.clamp(0.0, 1.0) * 0.95) as f32);
                }
            }
        }
    }

    /// PX4 took the landing command.
    pub(super) fn landing_accepted(&mut self) {
        if let Task::Land {
            phase: LandPhase::Autopilot { accepted },
            ..
        } = &mut self.task
        {
            *accepted = true;
        }
    }
}

//! Taking off under offboard control: PX4 is switched to OFFBOARD on the pad while the still
//! reference streams, armed there, and the planner flies the climb, apart from the neighbours.
//!
//! PX4's own take-off (NAV_TAKEOFF, then AUTO.LOITER) was flown until measured on PX4 SITL:
//! neither keeps apart from the drones beside it, the climb to 1 m ended 0.2–0.4 m up and sank,
//! and the drones of the lab map (pads 1 m apart) came within 0.52 m of each other there. PX4
//! arms in OFFBOARD once setpoints stream (`../shared/px4-sitl/README.md`).

use super::{Executor, Task, disarmed_in_flight};
use crate::motion::Steering;
use crate::planner::Goal;
use tacos_shared::Vec3;
use tacos_shared::ipc::CommandKind;
use tacos_shared::messages::{ActionState, FailureReason};

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum TakeoffStep {
    /// The still reference streams at the pad; PX4 is asked for OFFBOARD.
    Offboarding,
    /// In OFFBOARD on the pad: arming.
    Arming,
    /// The arm was accepted: the planner climbs to the take-off altitude above the pad.
    /// `armed_seen` once the vehicle's state shows it armed (PX4's heartbeat lags the ack).
    Climbing { armed_seen: bool },
}

impl Executor {
    /// Starts a take-off from where the vehicle stands.
    pub(super) fn start_takeoff(&mut self, pad: Vec3, now: f64) {
        let limits = self.cfg.limits;
        let deadline = now + 30.0 + limits.takeoff_altitude / 0.5;
        let step = if self.in_offboard() {
            TakeoffStep::Arming
        } else {
            TakeoffStep::Offboarding
        };
        self.hold_point = Some(pad);
        self.task = Task::Takeoff {
            step,
            pad,
            deadline,
        };
        match step {
            TakeoffStep::Arming => self.request(CommandKind::Arm, 0.0),
            _ => self.request(CommandKind::Offboard, 0.0),
        }
    }

    /// A take-off command was accepted: the next step.
    pub(super) fn takeoff_accepted(&mut self, kind: CommandKind) {
        let Task::Takeoff { step, .. } = &mut self.task else {
            return;
        };
        match (*step, kind) {
            (TakeoffStep::Offboarding, CommandKind::Offboard) => {
                *step = TakeoffStep::Arming;
                self.request(CommandKind::Arm, 0.0);
            }
            (TakeoffStep::Arming, CommandKind::Arm) => {
                *step = TakeoffStep::Climbing { armed_seen: false }
            }
            _ => {}
        }
    }

    /// The climb's goal: the take-off altitude above the pad.
    fn climb_goal(&self, pad: Vec3) -> Vec3 {
        Vec3::new(pad.x, pad.y, pad.z + self.cfg.limits.takeoff_altitude)
    }

    /// Still at the pad until armed; then straight up to the take-off point while the autopilot
    /// reports the vehicle on the ground or it is below half the take-off altitude, and the
    /// planner's climb from there.
    ///
    /// Why not the planner from the start: on PX4 SIH the vehicle stands on its pad for a few
    /// seconds after arming while its estimate already climbs (0.4 m with the vehicle on the
    /// ground, PX4's flight logs), and the planner's sideways corrections of that time wound up
    /// PX4's position control: the lab's drones lurched 0.3–0.5 m sideways as they lifted off,
    /// where their separation breaches were. A fixed point above the pad gives nothing to wind
    /// up; PX4's own take-off ramp lifts the vehicle towards it. PX4's land detector is not
    /// enough to hand over: it reported the vehicle airborne 1.5 s after arming, when only the
    /// estimate had risen (0.2 m), and the planner's 0.4 m setpoints then left it on the ground
    /// for 12 s more.
    pub(super) fn takeoff_steering(&self, step: TakeoffStep, pad: Vec3) -> Steering {
        match step {
            TakeoffStep::Climbing { .. }
                if self.vehicle.is_none_or(|v| {
                    v.landed || v.position.z - pad.z < self.cfg.limits.takeoff_altitude / 2.0
                }) =>
            {
                Steering::Still(self.climb_goal(pad))
            }
            TakeoffStep::Climbing { .. } => Steering::Toward(Goal::fixed(self.climb_goal(pad))),
            _ => Steering::Still(pad),
        }
    }

    pub(super) fn advance_takeoff(
        &mut self,
        step: TakeoffStep,
        pad: Vec3,
        deadline: f64,
        now: f64,
    ) {
        let Some(vehicle) = self.vehicle else { return };
        if now > deadline {
            return self.fail(FailureReason::TimedOut);
        }
        let altitude = self.cfg.limits.takeoff_altitude;
        self.set_running((((vehicle.position.z - pad.z) / altitude).clamp(0.0, 1.0) * 0.9) as f32);
        let TakeoffStep::Climbing { armed_seen } = step else {
            return;
        };
        if !vehicle.armed {
            if armed_seen {
                // PX4 disarms a vehicle that has not left the ground within COM_DISARM_PRFLT.
                self.fail(disarmed_in_flight());
            }
            return;
        }
        if !armed_seen {
            self.task = Task::Takeoff {
                step: TakeoffStep::Climbing { armed_seen: true },
                pad,
                deadline,
            };
        }
        if !self.in_offboard() {
            if vehicle.landed {
                // Armed on the pad in another mode (an arm that had to go through AUTO.LOITER):
                // the climb needs OFFBOARD, which PX4 grants armed on the ground too.
                return self.ensure_offboard();
            }
            if self.left_offboard(&vehicle, now) {
                self.hold_point = Some(vehicle.position);
                return self.fail(FailureReason::Rejected(format!(
                    "the autopilot left offboard for {} during the take-off",
                    vehicle.px4
                )));
            }
        }
        let goal = self.climb_goal(pad);
        let tolerance = (0.1 * altitude).max(0.1);
        if vehicle.position.z >= goal.z - tolerance {
            self.hold_point = Some(goal);
            self.task = Task::Hold;
            self.finish(ActionState::Done);
        }
    }
}

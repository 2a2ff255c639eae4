//! The COMMAND_LONGs a [`Vehicle`] executes, answered as PX4's commander answers them:
//! - `MAV_CMD_COMPONENT_ARM_DISARM`: ARM is TEMPORARILY_REJECTED ("Arming denied: Resolve system
//!   health failures first") until the vehicle is ready and can arm in its mode; disarming in the
//!   air is TEMPORARILY_REJECTED ("Disarming denied: not landed") unless forced (param2 = 21196).
//! - `MAV_CMD_NAV_TAKEOFF`: param7 is the altitude **above mean sea level**. Below the current
//!   altitude it is clamped to it ("Already higher than takeoff altitude": a vehicle on the ground
//!   stays there); NaN means `MIS_TAKEOFF_ALT` (2.5 m) above here. Accepted while disarmed too:
//!   the vehicle climbs once armed.
//! - `MAV_CMD_NAV_LAND`: AUTO.LAND descends; once landed it disarms after `COM_DISARM_LAND`.
//! - `MAV_CMD_DO_SET_MODE`: any mode while disarmed; armed, OFFBOARD needs a setpoint stream
//!   and manual modes a remote control ("Switching to Offboard is currently not available").
//!   (The first of PX4's two acks is the link's; see `link`.)

use super::{Vehicle, text};
use crate::vehicle::FORCE_DISARM_MAGIC;
use mavlink::dialects::common::{MavCmd, MavResult, MavSeverity};
use tacos_shared::Vec3;
use tacos_shared::px4_mode::{self, Px4Mode};

impl Vehicle {
    /// A COMMAND_LONG addressed to this vehicle; the result goes back in COMMAND_ACK. What PX4
    /// would say about it goes to the status texts.
    pub fn handle_command(&mut self, command: MavCmd, params: [f32; 7]) -> MavResult {
        if !self.alive {
            return MavResult::MAV_RESULT_FAILED;
        }
        match command {
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => {
                let force = params[1] == FORCE_DISARM_MAGIC;
                if params[0] > 0.5 {
                    self.arm()
                } else {
                    self.disarm(force)
                }
            }
            MavCmd::MAV_CMD_NAV_TAKEOFF => self.takeoff(params[6]),
            MavCmd::MAV_CMD_NAV_LAND => {
                self.start_landing();
                self.select_mode(Px4Mode::Land);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_DO_SET_MODE => self.set_mode(params[0], params[1], params[2]),
            _ => MavResult::MAV_RESULT_UNSUPPORTED,
        }
    }

    fn arm(&mut self) -> MavResult {
        if self.armed {
            return MavResult::MAV_RESULT_ACCEPTED;
        }
        if !self.ready() {
            self.say(MavSeverity::MAV_SEVERITY_CRITICAL, text::HEADING_INVALID);
        }
        if !self.can_arm() {
            self.say(MavSeverity::MAV_SEVERITY_CRITICAL, text::ARMING_DENIED);
            return MavResult::MAV_RESULT_TEMPORARILY_REJECTED;
        }
        self.armed = true;
        self.flown_since_arming = !self.landed;
        self.armed_on_ground_since = self.time;
        self.home = self.body.position;
        if self.landed && self.mode == Px4Mode::Hold {
            self.hold_at = self.body.position;
        }
        self.say(MavSeverity::MAV_SEVERITY_INFO, text::ARMED);
        MavResult::MAV_RESULT_ACCEPTED
    }

    fn disarm(&mut self, force: bool) -> MavResult {
        if !self.armed {
            return MavResult::MAV_RESULT_ACCEPTED;
        }
        if !self.landed && !force {
            self.say(MavSeverity::MAV_SEVERITY_CRITICAL, text::DISARMING_DENIED);
            return MavResult::MAV_RESULT_TEMPORARILY_REJECTED;
        }
        self.on_disarmed(text::DISARMED);
        MavResult::MAV_RESULT_ACCEPTED
    }

    /// NAV_TAKEOFF to `param7` metres AMSL (NaN: `default_takeoff_height` above here).
    fn takeoff(&mut self, param7: f32) -> MavResult {
        let here = self.amsl();
        let target = if param7.is_finite() {
            f64::from(param7)
        } else {
            let height = self.params.default_takeoff_height;
            self.say(
                MavSeverity::MAV_SEVERITY_INFO,
                format!("Using default takeoff altitude: {height:.1} m"),
            );
            here + height
        };
        let target = if target < here {
            self.say(MavSeverity::MAV_SEVERITY_CRITICAL, text::ALREADY_HIGHER);
            here
        } else {
            target
        };
        let p = self.body.position;
        self.takeoff_to = Vec3::new(p.x, p.y, self.params.ground_amsl - target);
        self.select_mode(Px4Mode::Takeoff);
        MavResult::MAV_RESULT_ACCEPTED
    }

    fn set_mode(&mut self, base_mode: f32, main: f32, sub: f32) -> MavResult {
        let as_u8 = |x: f32| {
            if x.is_finite() && (0.0..=255.0).contains(&x) {
                Some(x as u8)
            } else {
                None
            }
        };
        let (Some(base), Some(main), Some(sub)) = (as_u8(base_mode), as_u8(main), as_u8(sub))
        else {
            return MavResult::MAV_RESULT_DENIED;
        };
        if base & px4_mode::BASE_MODE_CUSTOM_ENABLED == 0 {
            return MavResult::MAV_RESULT_UNSUPPORTED;
        }
        // PX4 ignores the sub mode outside AUTO.
        let sub = if main == px4_mode::MAIN_AUTO { sub } else { 0 };
        let custom = (u32::from(main) << 16) | (u32::from(sub) << 24);
        let wanted = Px4Mode::from_custom_mode(custom);
        if wanted == self.mode {
            self.select_mode(wanted);
            return MavResult::MAV_RESULT_ACCEPTED;
        }
        // Any mode change is allowed while disarmed (`UserModeIntention::change`).
        if self.armed && !self.can_run(wanted) {
            self.say(
                MavSeverity::MAV_SEVERITY_CRITICAL,
                format!("Switching to {wanted} is currently not available"),
            );
            return MavResult::MAV_RESULT_TEMPORARILY_REJECTED;
        }
        match wanted {
            Px4Mode::Hold => {
                self.enter_hold();
                self.select_mode(Px4Mode::Hold);
            }
            Px4Mode::Land => {
                self.start_landing();
                self.select_mode(Px4Mode::Land);
            }
            Px4Mode::Takeoff => return self.takeoff(f32::NAN),
            other => self.select_mode(other),
        }
        MavResult::MAV_RESULT_ACCEPTED
    }

    /// Whether an armed vehicle can fly `mode` now.
    fn can_run(&self, mode: Px4Mode) -> bool {
        match mode {
            Px4Mode::Hold | Px4Mode::Land | Px4Mode::Takeoff => true,
            Px4Mode::Offboard => self.offboard_stream_ok(),
            // Manual modes need a remote control, which a simulated vehicle does not have; the
            // other auto modes need a mission or a return the simulator does not model.
            _ => false,
        }
    }
}

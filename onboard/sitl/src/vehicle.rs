//! One simulated PX4 vehicle: arming, flight modes, the offboard rules, the land detector and the
//! auto-disarm timers, driving a [`PointMass`]. Pure: time only advances through [`Vehicle::step`],
//! and everything is in the vehicle's own local NED frame (origin at its home, ground at z = 0).
//!
//! The PX4 behaviour reproduced (parameter names are PX4's):
//! - `MAV_CMD_COMPONENT_ARM_DISARM`: disarming in the air is DENIED unless forced (param2 = 21196).
//! - `MAV_CMD_NAV_TAKEOFF`: TEMPORARILY_REJECTED while disarmed; AUTO.TAKEOFF climbs, then AUTO.LOITER.
//! - `MAV_CMD_NAV_LAND`: AUTO.LAND descends; once landed it disarms after `COM_DISARM_LAND` (2 s).
//! - Armed on the ground without ever taking off: disarms after `COM_DISARM_PRFLT` (10 s).
//! - OFFBOARD is only entered when setpoints have been streaming (> 2 Hz) for at least 1 s, and is
//!   left for AUTO.LOITER when they stop for `COM_OF_LOSS_T` (1 s).

use crate::motion::{MotionLimits, PointMass, Reference};
use mavlink::dialects::common::{MavCmd, MavResult};
use tacos_shared::Vec3;
use tacos_shared::px4_mode::{self, Px4Mode};
use tacos_shared::scenario::FlightLimits;

/// PX4's magic param2 that forces a disarm in the air.
pub const FORCE_DISARM_MAGIC: f32 = 21196.0;
/// `COM_OF_LOSS_T`: offboard setpoints older than this → leave offboard.
pub const OFFBOARD_LOSS_TIMEOUT: f64 = 1.0;
/// Setpoints further apart than this do not count as a stream (the stream must exceed 2 Hz).
pub const OFFBOARD_MAX_GAP: f64 = 0.5;
/// How long setpoints must have been streaming before OFFBOARD is accepted.
pub const OFFBOARD_MIN_STREAM: f64 = 1.0;
/// `COM_DISARM_LAND`.
pub const DISARM_AFTER_LANDING: f64 = 2.0;
/// `COM_DISARM_PRFLT`.
pub const DISARM_PREFLIGHT: f64 = 10.0;
/// Takeoff is complete within this many metres of the takeoff altitude.
pub const TAKEOFF_ACCEPTANCE: f64 = 0.1;
/// `MPC_LAND_SPEED`, capped by the vehicle's vertical speed limit.
pub const LAND_SPEED: f64 = 0.7;
/// Within this height above the ground, a vehicle that is not climbing has touched down.
pub const GROUND_CONTACT: f64 = 0.02;
/// A powered touchdown faster than this (m/s down, about twice `LAND_SPEED`) is a crash into
/// the ground, not a landing.
pub const HARD_TOUCHDOWN_SPEED: f64 = 1.5;

const GRAVITY: f64 = 9.81;
/// A falling vehicle's terminal speed (m/s).
const TERMINAL_SPEED: f64 = 25.0;

/// A vehicle's tuning, from the scenario's limits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VehicleParams {
    pub limits: MotionLimits,
    /// Used when a takeoff names no altitude (param7 NaN), like PX4's `MIS_TAKEOFF_ALT`.
    pub takeoff_altitude: f64,
    pub land_speed: f64,
}

impl VehicleParams {
    pub fn from_limits(limits: &FlightLimits) -> Self {
        let motion = MotionLimits::from_scenario(limits.max_speed, limits.max_accel);
        VehicleParams {
            limits: motion,
            takeoff_altitude: limits.takeoff_altitude,
            land_speed: LAND_SPEED.min(motion.max_vertical_speed),
        }
    }
}

/// `MAV_LANDED_STATE` as PX4 reports it in EXTENDED_SYS_STATE.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LandedState {
    OnGround,
    Takeoff,
    InAir,
    Landing,
}

#[derive(Debug, Clone)]
pub struct Vehicle {
    params: VehicleParams,
    /// Seconds since the vehicle booted (sim time).
    time: f64,
    body: PointMass,
    armed: bool,
    mode: Px4Mode,
    landed: bool,
    alive: bool,
    /// Left the ground since it was last armed (selects which auto-disarm timer applies).
    flown_since_arming: bool,
    /// When the vehicle last became both armed and landed.
    armed_on_ground_since: f64,
    /// Where AUTO.LOITER holds.
    hold_at: Vec3,
    /// Where AUTO.TAKEOFF climbs to.
    takeoff_to: Vec3,
    /// Horizontal spot AUTO.LAND descends over.
    land_at: Vec3,
    setpoint: Option<Reference>,
    last_setpoint: Option<f64>,
    stream_since: Option<f64>,
    /// Set by a powered touchdown faster than `HARD_TOUCHDOWN_SPEED`; read (and cleared) by
    /// `take_ground_strike`.
    struck_ground: bool,
}

impl Vehicle {
    /// A vehicle on the ground at its home, disarmed, in AUTO.LOITER (what PX4 boots into
    /// without a remote control).
    pub fn new(params: VehicleParams) -> Self {
        Vehicle {
            params,
            time: 0.0,
            body: PointMass::at_rest(Vec3::zeros()),
            armed: false,
            mode: Px4Mode::Hold,
            landed: true,
            alive: true,
            flown_since_arming: false,
            armed_on_ground_since: 0.0,
            hold_at: Vec3::zeros(),
            takeoff_to: Vec3::zeros(),
            land_at: Vec3::zeros(),
            setpoint: None,
            last_setpoint: None,
            stream_since: None,
            struck_ground: false,
        }
    }

    /// True once after the vehicle flew into the ground under power (see
    /// `HARD_TOUCHDOWN_SPEED`). A vehicle that lost power and fell is not counted: its fall is
    /// the fault that was injected, not something the flight software did.
    pub fn take_ground_strike(&mut self) -> bool {
        std::mem::take(&mut self.struck_ground)
    }

    pub fn time(&self) -> f64 {
        self.time
    }

    pub fn position(&self) -> Vec3 {
        self.body.position
    }

    pub fn velocity(&self) -> Vec3 {
        self.body.velocity
    }

    pub fn armed(&self) -> bool {
        self.armed
    }

    pub fn mode(&self) -> Px4Mode {
        self.mode
    }

    /// HEARTBEAT.custom_mode.
    pub fn custom_mode(&self) -> u32 {
        self.mode.custom_mode()
    }

    pub fn landed(&self) -> bool {
        self.landed
    }

    pub fn alive(&self) -> bool {
        self.alive
    }

    pub fn params(&self) -> &VehicleParams {
        &self.params
    }

    pub fn landed_state(&self) -> LandedState {
        match (self.landed, self.mode) {
            (true, _) => LandedState::OnGround,
            (false, Px4Mode::Takeoff) => LandedState::Takeoff,
            (false, Px4Mode::Land) => LandedState::Landing,
            (false, _) => LandedState::InAir,
        }
    }

    /// A COMMAND_LONG addressed to this vehicle; the result goes back in COMMAND_ACK.
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
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_DO_SET_MODE => self.set_mode(params[0], params[1], params[2]),
            _ => MavResult::MAV_RESULT_UNSUPPORTED,
        }
    }

    /// A SET_POSITION_TARGET_LOCAL_NED addressed to this vehicle (already translated; see
    /// `link`). PX4 takes setpoints in any mode and flies them only in OFFBOARD.
    pub fn handle_setpoint(&mut self, reference: Reference) {
        if !self.alive {
            return;
        }
        let continuing = self
            .last_setpoint
            .is_some_and(|t| self.time - t <= OFFBOARD_MAX_GAP);
        if !continuing {
            self.stream_since = Some(self.time);
        }
        self.last_setpoint = Some(self.time);
        self.setpoint = Some(reference);
    }

    /// Power loss: motors off for good; the body falls.
    pub fn kill(&mut self) {
        self.alive = false;
        self.armed = false;
    }

    /// Advances the vehicle by `dt` seconds.
    pub fn step(&mut self, dt: f64) {
        if dt.is_nan() || dt <= 0.0 {
            return;
        }
        self.time += dt;
        if self.alive
            && self.mode == Px4Mode::Offboard
            && !self.setpoints_fresh(OFFBOARD_LOSS_TIMEOUT)
        {
            self.enter_hold();
        }
        if !self.armed {
            if !self.landed {
                self.fall(dt);
            }
            return;
        }

        let reference = self.reference();
        let limits = self.params.limits;
        let a = self.body.command(&reference, &limits);
        // On the ground, only a climb command lifts the vehicle; it does not slide about.
        if !(self.landed && a.z >= 0.0) {
            self.body.integrate(a, dt, &limits);
            if self.body.position.z < 0.0 && self.landed {
                self.landed = false;
                self.flown_since_arming = true;
            }
            self.check_ground_contact();
        }

        if self.mode == Px4Mode::Takeoff
            && !self.landed
            && (self.body.position.z - self.takeoff_to.z).abs() <= TAKEOFF_ACCEPTANCE
        {
            self.mode = Px4Mode::Hold;
            self.hold_at = self.takeoff_to;
        }
        self.auto_disarm();
    }

    // ---- commands ------------------------------------------------------------------------------

    fn arm(&mut self) -> MavResult {
        if !self.armed {
            self.armed = true;
            self.flown_since_arming = !self.landed;
            self.armed_on_ground_since = self.time;
            if self.landed && self.mode == Px4Mode::Hold {
                self.hold_at = self.body.position;
            }
        }
        MavResult::MAV_RESULT_ACCEPTED
    }

    fn disarm(&mut self, force: bool) -> MavResult {
        if self.armed && !self.landed && !force {
            return MavResult::MAV_RESULT_DENIED;
        }
        self.armed = false;
        MavResult::MAV_RESULT_ACCEPTED
    }

    fn takeoff(&mut self, altitude: f32) -> MavResult {
        if !self.armed {
            return MavResult::MAV_RESULT_TEMPORARILY_REJECTED;
        }
        let altitude = if altitude.is_finite() {
            f64::from(altitude)
        } else {
            self.params.takeoff_altitude
        };
        if altitude <= TAKEOFF_ACCEPTANCE {
            return MavResult::MAV_RESULT_DENIED;
        }
        self.begin_takeoff(altitude);
        MavResult::MAV_RESULT_ACCEPTED
    }

    fn begin_takeoff(&mut self, altitude: f64) {
        let p = self.body.position;
        self.takeoff_to = Vec3::new(p.x, p.y, -altitude);
        self.mode = Px4Mode::Takeoff;
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
        let custom = (u32::from(main) << 16) | (u32::from(sub) << 24);
        match Px4Mode::from_custom_mode(custom) {
            Px4Mode::Offboard => {
                if self.mode != Px4Mode::Offboard && !self.offboard_stream_ok() {
                    return MavResult::MAV_RESULT_TEMPORARILY_REJECTED;
                }
                self.mode = Px4Mode::Offboard;
            }
            Px4Mode::Hold => {
                if self.mode != Px4Mode::Hold {
                    self.enter_hold();
                }
            }
            Px4Mode::Land => {
                if self.mode != Px4Mode::Land {
                    self.start_landing();
                }
            }
            Px4Mode::Takeoff => {
                if self.mode != Px4Mode::Takeoff {
                    self.begin_takeoff(self.params.takeoff_altitude);
                }
            }
            // Manual modes need a remote control, which a simulated vehicle does not have; the
            // other auto modes need a mission or a home position the simulator does not model.
            _ => return MavResult::MAV_RESULT_TEMPORARILY_REJECTED,
        }
        MavResult::MAV_RESULT_ACCEPTED
    }

    fn enter_hold(&mut self) {
        self.mode = Px4Mode::Hold;
        self.hold_at = self.body.position;
    }

    fn start_landing(&mut self) {
        self.mode = Px4Mode::Land;
        self.land_at = self.body.position;
    }

    fn setpoints_fresh(&self, max_age: f64) -> bool {
        self.last_setpoint.is_some_and(|t| self.time - t <= max_age)
    }

    fn offboard_stream_ok(&self) -> bool {
        self.setpoints_fresh(OFFBOARD_MAX_GAP)
            && self
                .stream_since
                .is_some_and(|since| self.time - since >= OFFBOARD_MIN_STREAM - 1e-9)
    }

    // ---- flight ----------------------------------------------------------------------------------

    /// What the position controller tracks in the current mode.
    fn reference(&self) -> Reference {
        match self.mode {
            Px4Mode::Takeoff => Reference::hold(self.takeoff_to),
            Px4Mode::Land => {
                let height = -self.body.position.z;
                // Slow down for the last metre, like PX4's MPC_LAND_ALT2.
                let speed = self.params.land_speed * height.clamp(0.4, 1.0);
                Reference {
                    position: [Some(self.land_at.x), Some(self.land_at.y), None],
                    velocity: [None, None, Some(speed)],
                    acceleration: [None; 3],
                }
            }
            Px4Mode::Offboard => self
                .setpoint
                .unwrap_or_else(|| Reference::hold(self.hold_at)),
            _ => Reference::hold(self.hold_at),
        }
    }

    fn check_ground_contact(&mut self) {
        let p = self.body.position;
        if !self.landed && p.z > -GROUND_CONTACT && self.body.velocity.z >= 0.0 {
            self.struck_ground |= self.body.velocity.z > HARD_TOUCHDOWN_SPEED;
            self.body.position.z = 0.0;
            self.body.velocity = Vec3::zeros();
            self.landed = true;
            self.armed_on_ground_since = self.time;
            if self.mode == Px4Mode::Hold {
                self.hold_at = self.body.position;
            }
        }
    }

    fn auto_disarm(&mut self) {
        if !(self.armed && self.landed) {
            return;
        }
        let after = if self.flown_since_arming {
            DISARM_AFTER_LANDING
        } else {
            DISARM_PREFLIGHT
        };
        if self.time - self.armed_on_ground_since >= after {
            self.armed = false;
        }
    }

    /// Motors off in the air: gravity, some drag on the horizontal, until the ground.
    fn fall(&mut self, dt: f64) {
        let v = self.body.velocity;
        let horizontal = Vec3::new(v.x, v.y, 0.0);
        let slow = (self.params.limits.max_accel * dt).min(horizontal.norm());
        let horizontal = if horizontal.norm() > 0.0 {
            horizontal * (1.0 - slow / horizontal.norm())
        } else {
            horizontal
        };
        let vz = (v.z + GRAVITY * dt).min(TERMINAL_SPEED);
        let new_v = Vec3::new(horizontal.x, horizontal.y, vz);
        self.body.position += (v + new_v) * (0.5 * dt);
        self.body.velocity = new_v;
        if self.body.position.z >= 0.0 {
            self.body.position.z = 0.0;
            self.body.velocity = Vec3::zeros();
            self.landed = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: f64 = 0.01;

    fn params() -> VehicleParams {
        VehicleParams {
            limits: MotionLimits {
                max_speed: 4.0,
                max_vertical_speed: 2.0,
                max_accel: 3.0,
            },
            takeoff_altitude: 5.0,
            land_speed: 0.7,
        }
    }

    fn arm(v: &mut Vehicle) -> MavResult {
        v.handle_command(
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
    }

    fn takeoff(v: &mut Vehicle, altitude: f32) -> MavResult {
        v.handle_command(
            MavCmd::MAV_CMD_NAV_TAKEOFF,
            [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, altitude],
        )
    }

    fn set_mode(v: &mut Vehicle, main: u8, sub: u8) -> MavResult {
        v.handle_command(
            MavCmd::MAV_CMD_DO_SET_MODE,
            [1.0, f32::from(main), f32::from(sub), 0.0, 0.0, 0.0, 0.0],
        )
    }

    fn offboard(v: &mut Vehicle) -> MavResult {
        set_mode(v, px4_mode::MAIN_OFFBOARD, 0)
    }

    /// Steps for `seconds`, checking the envelope on every step the vehicle is flying.
    fn run(v: &mut Vehicle, seconds: f64) {
        let steps = (seconds / DT).round() as usize;
        for _ in 0..steps {
            step_checked(v);
        }
    }

    fn step_checked(v: &mut Vehicle) {
        let before = (v.velocity(), v.landed());
        v.step(DT);
        let limits = v.params().limits;
        assert!(
            v.velocity().norm() <= limits.max_speed + 1e-9,
            "speed {}",
            v.velocity().norm()
        );
        assert!(v.velocity().z.abs() <= limits.max_vertical_speed + 1e-9);
        // Touchdown is a contact, not a commanded acceleration.
        if !before.1 && !v.landed() {
            let accel = (v.velocity() - before.0).norm() / DT;
            assert!(accel <= limits.max_accel + 1e-6, "accel {accel}");
        }
        assert!(v.position().z <= 0.0, "below the ground");
    }

    fn airborne(altitude: f32) -> Vehicle {
        let mut v = Vehicle::new(params());
        assert_eq!(arm(&mut v), MavResult::MAV_RESULT_ACCEPTED);
        assert_eq!(takeoff(&mut v, altitude), MavResult::MAV_RESULT_ACCEPTED);
        run(&mut v, 15.0);
        v
    }

    /// Airborne at `altitude` and switched to offboard, setpoints streaming at where it hovers
    /// (returned with it).
    fn offboard_at(altitude: f32) -> (Vehicle, Vec3) {
        let mut v = airborne(altitude);
        let here = v.position();
        stream(&mut v, here, 1.2);
        assert_eq!(offboard(&mut v), MavResult::MAV_RESULT_ACCEPTED);
        (v, here)
    }

    fn stream(v: &mut Vehicle, target: Vec3, seconds: f64) {
        let steps = (seconds / DT).round() as usize;
        for i in 0..steps {
            if i % 5 == 0 {
                v.handle_setpoint(Reference::hold(target));
            }
            step_checked(v);
        }
    }

    #[test]
    fn boots_disarmed_on_the_ground_in_hold() {
        let v = Vehicle::new(params());
        assert!(!v.armed() && v.landed());
        assert_eq!(v.mode(), Px4Mode::Hold);
        assert_eq!(v.landed_state(), LandedState::OnGround);
    }

    #[test]
    fn arm_takeoff_hold_reaches_altitude() {
        let mut v = Vehicle::new(params());
        assert_eq!(arm(&mut v), MavResult::MAV_RESULT_ACCEPTED);
        assert!(v.armed());
        assert_eq!(takeoff(&mut v, 8.0), MavResult::MAV_RESULT_ACCEPTED);
        assert_eq!(v.mode(), Px4Mode::Takeoff);
        run(&mut v, 1.0);
        assert_eq!(v.landed_state(), LandedState::Takeoff);
        assert!(v.position().z < -0.5, "climbing: {}", v.position().z);
        run(&mut v, 14.0);
        assert_eq!(v.mode(), Px4Mode::Hold, "takeoff ends in AUTO.LOITER");
        assert_eq!(v.landed_state(), LandedState::InAir);
        assert!((v.position().z + 8.0).abs() < 0.15, "at {}", v.position().z);
        assert!(v.position().xy().norm() < 1e-6, "straight up");
        run(&mut v, 5.0);
        assert!(
            (v.position().z + 8.0).abs() < 0.15 && v.armed(),
            "and it stays there"
        );
    }

    #[test]
    fn takeoff_without_altitude_uses_the_default() {
        let v = airborne(f32::NAN);
        assert!((v.position().z + 5.0).abs() < 0.15);
    }

    #[test]
    fn takeoff_while_disarmed_is_temporarily_rejected() {
        let mut v = Vehicle::new(params());
        assert_eq!(
            takeoff(&mut v, 5.0),
            MavResult::MAV_RESULT_TEMPORARILY_REJECTED
        );
        run(&mut v, 2.0);
        assert!(v.landed() && v.position().z == 0.0);
        assert_eq!(v.mode(), Px4Mode::Hold);
    }

    #[test]
    fn disarm_in_the_air_needs_force() {
        let mut v = airborne(5.0);
        let disarm = |v: &mut Vehicle, p2: f32| {
            v.handle_command(
                MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
                [0.0, p2, 0.0, 0.0, 0.0, 0.0, 0.0],
            )
        };
        assert_eq!(disarm(&mut v, 0.0), MavResult::MAV_RESULT_DENIED);
        assert!(v.armed());
        assert_eq!(
            disarm(&mut v, FORCE_DISARM_MAGIC),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert!(!v.armed());
        for _ in 0..500 {
            v.step(DT);
        }
        assert!(v.landed() && v.position().z == 0.0, "it fell");
    }

    #[test]
    fn offboard_needs_a_second_of_setpoints() {
        let mut v = airborne(5.0);
        assert_eq!(
            offboard(&mut v),
            MavResult::MAV_RESULT_TEMPORARILY_REJECTED,
            "no stream at all"
        );
        let here = v.position();
        stream(&mut v, here, 0.5);
        assert_eq!(
            offboard(&mut v),
            MavResult::MAV_RESULT_TEMPORARILY_REJECTED,
            "only 0.5 s of stream"
        );
        stream(&mut v, here, 0.6);
        assert_eq!(offboard(&mut v), MavResult::MAV_RESULT_ACCEPTED);
        assert_eq!(v.mode(), Px4Mode::Offboard);
    }

    #[test]
    fn a_slow_stream_does_not_count() {
        let mut v = airborne(5.0);
        let here = v.position();
        // 1 Hz for 3 s: each setpoint restarts the stream.
        for _ in 0..3 {
            v.handle_setpoint(Reference::hold(here));
            run(&mut v, 1.0);
        }
        v.handle_setpoint(Reference::hold(here));
        assert_eq!(offboard(&mut v), MavResult::MAV_RESULT_TEMPORARILY_REJECTED);
    }

    #[test]
    fn offboard_flies_the_setpoints_then_holds_when_they_stop() {
        let (mut v, _) = offboard_at(5.0);
        let goal = Vec3::new(12.0, -6.0, -7.0);
        stream(&mut v, goal, 15.0);
        assert_eq!(v.mode(), Px4Mode::Offboard);
        assert!((v.position() - goal).norm() < 0.1, "at {:?}", v.position());

        // Setpoints stop (the last one 0.05 s before the stream ended): still offboard just
        // before COM_OF_LOSS_T, hold just after.
        run(&mut v, 0.9);
        assert_eq!(v.mode(), Px4Mode::Offboard);
        run(&mut v, 0.1);
        assert_eq!(v.mode(), Px4Mode::Hold);
        let held = v.position();
        run(&mut v, 5.0);
        assert!(
            (v.position() - held).norm() < 0.05,
            "holds where hold began"
        );
    }

    #[test]
    fn hold_while_moving_brakes_and_returns_within_limits() {
        let (mut v, _) = offboard_at(5.0);
        // Full speed, then a hold command mid-flight.
        let far = Vec3::new(200.0, 0.0, -5.0);
        stream(&mut v, far, 5.0);
        assert!(v.velocity().norm() > 3.9, "at full speed");
        assert_eq!(
            set_mode(&mut v, px4_mode::MAIN_AUTO, px4_mode::AUTO_LOITER),
            MavResult::MAV_RESULT_ACCEPTED
        );
        let held = v.position();
        stream(&mut v, far, 10.0);
        assert_eq!(
            v.mode(),
            Px4Mode::Hold,
            "setpoints do not move a holding vehicle"
        );
        assert!((v.position() - held).norm() < 0.1);
    }

    #[test]
    fn velocity_setpoints_are_honoured() {
        let mut v = airborne(5.0);
        let vel = Reference::velocity(Vec3::new(0.0, 2.0, 0.0));
        for _ in 0..120 {
            v.handle_setpoint(vel);
            step_checked(&mut v);
        }
        assert_eq!(offboard(&mut v), MavResult::MAV_RESULT_ACCEPTED);
        for _ in 0..300 {
            v.handle_setpoint(vel);
            step_checked(&mut v);
        }
        assert!(
            (v.velocity() - Vec3::new(0.0, 2.0, 0.0)).norm() < 0.01,
            "{:?}",
            v.velocity()
        );
    }

    #[test]
    fn land_descends_touches_down_and_disarms() {
        let mut v = airborne(5.0);
        assert_eq!(
            v.handle_command(MavCmd::MAV_CMD_NAV_LAND, [0.0; 7]),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(v.mode(), Px4Mode::Land);
        run(&mut v, 1.0);
        assert_eq!(v.landed_state(), LandedState::Landing);
        let mut touchdown = None;
        for _ in 0..3000 {
            step_checked(&mut v);
            if touchdown.is_none() && v.landed() {
                touchdown = Some(v.time());
            }
            if !v.armed() {
                break;
            }
        }
        let touchdown = touchdown.expect("it touched down");
        assert!(!v.armed(), "auto-disarmed");
        let waited = v.time() - touchdown;
        assert!(
            (DISARM_AFTER_LANDING - 0.02..DISARM_AFTER_LANDING + 0.05).contains(&waited),
            "{waited}"
        );
        assert_eq!(v.landed_state(), LandedState::OnGround);
        assert_eq!(v.position().z, 0.0);
    }

    #[test]
    fn flying_into_the_ground_is_a_strike_and_a_landing_or_a_fall_is_not() {
        // Offboard setpoints 20 m below the ground: the vehicle descends at full vertical speed
        // and hits it.
        let (mut v, here) = offboard_at(5.0);
        let mut strikes = 0;
        for i in 0..1000 {
            if i % 5 == 0 {
                v.handle_setpoint(Reference::hold(Vec3::new(here.x, here.y, 20.0)));
            }
            step_checked(&mut v);
            strikes += usize::from(v.take_ground_strike());
        }
        assert!(v.landed());
        assert_eq!(strikes, 1, "one strike, reported once");

        // Setpoints that come down to the ground itself slow to a gentle touchdown.
        let (mut v, here) = offboard_at(5.0);
        stream(&mut v, Vec3::new(here.x, here.y, 0.0), 20.0);
        assert!(v.landed() && !v.take_ground_strike());

        let mut v = airborne(5.0);
        v.handle_command(MavCmd::MAV_CMD_NAV_LAND, [0.0; 7]);
        run(&mut v, 30.0);
        assert!(v.landed() && !v.take_ground_strike(), "a landing");

        let mut v = airborne(5.0);
        v.kill();
        for _ in 0..1000 {
            v.step(DT);
        }
        assert!(
            v.landed() && !v.take_ground_strike(),
            "a fall without power"
        );
    }

    #[test]
    fn armed_on_the_ground_disarms_after_the_preflight_timeout() {
        let mut v = Vehicle::new(params());
        arm(&mut v);
        run(&mut v, DISARM_PREFLIGHT - 0.1);
        assert!(v.armed());
        run(&mut v, 0.2);
        assert!(!v.armed());
    }

    #[test]
    fn unknown_commands_are_unsupported_and_manual_modes_rejected() {
        let mut v = Vehicle::new(params());
        assert_eq!(
            v.handle_command(MavCmd::MAV_CMD_DO_REPOSITION, [0.0; 7]),
            MavResult::MAV_RESULT_UNSUPPORTED
        );
        assert_eq!(
            set_mode(&mut v, px4_mode::MAIN_POSCTL, 0),
            MavResult::MAV_RESULT_TEMPORARILY_REJECTED
        );
        let no_custom = [
            0.0,
            f32::from(px4_mode::MAIN_AUTO),
            f32::from(px4_mode::AUTO_LAND),
            0.0,
            0.0,
            0.0,
            0.0,
        ];
        assert_eq!(
            v.handle_command(MavCmd::MAV_CMD_DO_SET_MODE, no_custom),
            MavResult::MAV_RESULT_UNSUPPORTED
        );
    }

    #[test]
    fn a_dead_vehicle_falls_and_stays_down() {
        let mut v = airborne(5.0);
        v.kill();
        for _ in 0..500 {
            v.step(DT);
        }
        assert!(!v.alive() && !v.armed() && v.landed());
        assert_eq!(arm(&mut v), MavResult::MAV_RESULT_FAILED);
        assert!(!v.armed());
    }
}

//! One simulated PX4 vehicle: readiness, arming, flight modes, the offboard rules, the land
//! detector and the auto-disarm timers, driving a [`PointMass`]. Pure: time only advances
//! through [`Vehicle::step`], and everything is in the vehicle's own local NED frame (origin at
//! its spawn point on the ground, z = 0; that point is `ground_amsl` metres above sea level).
//!
//! The PX4 behaviour reproduced (measured on PX4 main SITL with SIH; parameter names are PX4's)
//! is listed on [`commands`] for the commands and here for the rest:
//! - Readiness: for `readiness_delay` seconds after boot the health checks fail ("Preflight Fail:
//!   heading estimate invalid", repeated); then "Ready for takeoff!" once.
//! - HEARTBEAT.system_status ([`Vehicle::system_status`]): UNINIT while it cannot arm in the
//!   current mode, STANDBY when it can, ACTIVE when armed, CRITICAL in the offboard-loss failsafe.
//! - Boots in AUTO.LOITER. After a disarm it returns to the last mode chosen by command that
//!   does not prevent arming (PX4's `UserModeIntention`): after an offboard flight, OFFBOARD,
//!   where it cannot arm again until setpoints stream or it is switched to AUTO.LOITER.
//! - The offboard-loss failsafe, armed only: when setpoints stop for `COM_OF_LOSS_T` (default
//!   1 s) in OFFBOARD, the vehicle does what `COM_OBL_RC_ACT` says ([`OffboardLossAction`]):
//!   5 holds where it is (AUTO.LOITER), 4 lands where it is (AUTO.LAND), 0–3 return (AUTO.RTL:
//!   0–2 are manual modes that need a remote control, which a simulated vehicle never has; PX4
//!   with no RC returns for its default 0, see `deploy/README.md`).
//!   When the stream is back, a vehicle holding in this failsafe flies OFFBOARD again, as PX4
//!   SITL did under a restarted writer (the other actions not measured, not modelled).
//!   The return is approximated: it flies at its current altitude straight to above home (no
//!   climb to PX4's `RTL_RETURN_ALT`), then lands there. 6 (Terminate) and 7 (Disarm) stop the
//!   motors. PX4's default is 0, so a vehicle nobody set up returns; the writer sets 5.
//! - Parameters ([`crate::params`]) and the geofence ([`crate::fence`]) are read and written
//!   over MAVLink as on PX4; of the parameters only the two above change the flight, and the
//!   geofence is held, not enforced (nor are `GF_ACTION` and `GF_MAX_VER_DIST`).
//! - Take-off climbs at `MPC_TKO_SPEED` (1.5 m/s) and ends within `NAV_MC_ALT_RAD` (0.8 m) of its
//!   altitude, in AUTO.LOITER at that altitude. Vertical speeds 3 m/s up, 1.5 m/s down.
//! - Landed: disarms after `COM_DISARM_LAND` (2 s), or `COM_DISARM_PRFLT` + `COM_SPOOLUP_TIME`
//!   (11 s) after an arming that never left the ground. Home moves at every arming and touchdown.
//! - The land detector: in OFFBOARD, ground contact counts only while the setpoint commands a
//!   descent (see `flight`).

pub mod commands;
mod flight;
#[cfg(test)]
mod tests;

use crate::fence::Geofence;
use crate::geo::DEFAULT_ORIGIN_AMSL_M;
use crate::motion::{MotionLimits, PointMass, Reference};
use crate::params::{OffboardLossAction, Px4Params};
use mavlink::dialects::common::{MavSeverity, MavState};
use tacos_shared::Vec3;
use tacos_shared::px4_mode::Px4Mode;
use tacos_shared::scenario::FlightLimits;

/// PX4's magic param2 that forces a disarm in the air.
pub const FORCE_DISARM_MAGIC: f32 = 21196.0;
/// `COM_OF_LOSS_T`'s default: offboard setpoints older than this → the offboard-loss failsafe.
pub const OFFBOARD_LOSS_TIMEOUT: f64 = 1.0;
/// AUTO.RTL: the return, flown at this height above home at the least (m).
pub const RETURN_MIN_HEIGHT: f64 = 1.0;
/// `NAV_ACC_RAD`-like: within this horizontal distance of home the return descends (m).
pub const RETURN_ACCEPTANCE: f64 = 1.0;
/// PX4's AUTO.RTL.
pub const RETURN: Px4Mode = Px4Mode::Other {
    main: tacos_shared::px4_mode::MAIN_AUTO,
    sub: tacos_shared::px4_mode::AUTO_RTL,
};
/// Setpoints further apart than this do not count as a stream (the stream must exceed 2 Hz).
pub const OFFBOARD_MAX_GAP: f64 = 0.5;
/// How long setpoints must have been streaming before an armed vehicle accepts OFFBOARD. PX4
/// only wants the last one within `COM_OF_LOSS_T`; the stand-in is stricter on purpose.
pub const OFFBOARD_MIN_STREAM: f64 = 1.0;
/// `COM_DISARM_LAND`.
pub const DISARM_AFTER_LANDING: f64 = 2.0;
/// `COM_DISARM_PRFLT` (10 s) + `COM_SPOOLUP_TIME` (1 s).
pub const DISARM_PREFLIGHT: f64 = 11.0;
/// `NAV_MC_ALT_RAD`: take-off is complete within this many metres of its altitude.
pub const TAKEOFF_ACCEPTANCE: f64 = 0.8;
/// `MPC_TKO_SPEED`: the climb rate of a take-off (m/s).
pub const TAKEOFF_SPEED: f64 = 1.5;
/// `MIS_TAKEOFF_ALT`: the take-off height when NAV_TAKEOFF gives no altitude (param7 NaN).
pub const MIS_TAKEOFF_ALT: f64 = 2.5;
/// `MPC_LAND_SPEED`, capped by the vehicle's vertical speed limit.
pub const LAND_SPEED: f64 = 0.7;
/// How long after boot the stand-in is not ready to arm, by default (PX4 SITL takes several
/// seconds; kept short so tests stay fast).
pub const DEFAULT_READINESS_DELAY: f64 = 2.0;
/// How often "Preflight Fail: heading estimate invalid" repeats while not ready.
pub const PREFLIGHT_TEXT_PERIOD: f64 = 1.0;
/// Within this height above the ground, a vehicle that is not climbing has touched down.
pub const GROUND_CONTACT: f64 = 0.02;
/// A powered touchdown faster than this (m/s down, well above `LAND_SPEED`) is a crash into
/// the ground, not a landing.
pub const HARD_TOUCHDOWN_SPEED: f64 = 1.0;
/// Status texts kept for the link; older ones are dropped when nobody collects them.
const MAX_PENDING_TEXTS: usize = 32;

const GRAVITY: f64 = 9.81;
/// A falling vehicle's terminal speed (m/s).
const TERMINAL_SPEED: f64 = 25.0;

/// What PX4 says in STATUSTEXT (without the trailing tab PX4 puts on texts that also exist as
/// events).
pub mod text {
    pub const HEADING_INVALID: &str = "Preflight Fail: heading estimate invalid";
    pub const ARMING_DENIED: &str = "Arming denied: Resolve system health failures first";
    pub const READY: &str = "Ready for takeoff!";
    pub const ALREADY_HIGHER: &str = "Already higher than takeoff altitude";
    pub const DISARMING_DENIED: &str = "Disarming denied: not landed";
    pub const ARMED: &str = "Armed by external command";
    pub const DISARMED: &str = "Disarmed by external command";
    pub const DISARMED_LANDING: &str = "Disarmed by landing";
    pub const DISARMED_PREFLIGHT: &str = "Disarmed by auto preflight disarming";
    pub const TAKEOFF_DETECTED: &str = "Takeoff detected";
    pub const LANDING_DETECTED: &str = "Landing detected";
}

/// A vehicle's tuning, from the scenario's limits, and where it stands.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VehicleParams {
    pub limits: MotionLimits,
    /// Height of a take-off that names no altitude (param7 NaN), PX4's `MIS_TAKEOFF_ALT`.
    pub default_takeoff_height: f64,
    pub land_speed: f64,
    /// Metres above mean sea level of the local origin (the spawn point, on the ground).
    pub ground_amsl: f64,
    /// Seconds after boot before the vehicle can arm.
    pub readiness_delay: f64,
}

impl VehicleParams {
    pub fn from_limits(limits: &FlightLimits) -> Self {
        let motion = MotionLimits::from_scenario(limits.max_speed, limits.max_accel);
        VehicleParams {
            limits: motion,
            default_takeoff_height: MIS_TAKEOFF_ALT,
            land_speed: LAND_SPEED.min(motion.max_descent_speed),
            ground_amsl: DEFAULT_ORIGIN_AMSL_M,
            readiness_delay: DEFAULT_READINESS_DELAY,
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

/// One STATUSTEXT.
#[derive(Debug, Clone, PartialEq)]
pub struct StatusText {
    pub severity: MavSeverity,
    pub text: String,
}

#[derive(Debug, Clone)]
pub struct Vehicle {
    params: VehicleParams,
    /// Seconds since the vehicle booted (sim time).
    time: f64,
    body: PointMass,
    armed: bool,
    mode: Px4Mode,
    /// The mode a disarm returns to (PX4's `_nav_state_after_disarming`).
    mode_after_disarm: Px4Mode,
    /// In the offboard-loss failsafe (holding although OFFBOARD was asked for).
    failsafe: bool,
    landed: bool,
    alive: bool,
    /// Left the ground since it was last armed (selects which auto-disarm timer applies).
    flown_since_arming: bool,
    /// When the vehicle last became both armed and landed.
    armed_on_ground_since: f64,
    /// Home in the local frame: set at every arming and every touchdown.
    home: Vec3,
    /// Where AUTO.LOITER holds.
    hold_at: Vec3,
    /// Where AUTO.TAKEOFF climbs to.
    takeoff_to: Vec3,
    /// Horizontal spot AUTO.LAND descends over.
    land_at: Vec3,
    setpoint: Option<Reference>,
    last_setpoint: Option<f64>,
    stream_since: Option<f64>,
    announced_ready: bool,
    next_preflight_text: f64,
    texts: Vec<StatusText>,
    /// Set by a powered touchdown faster than `HARD_TOUCHDOWN_SPEED`; read (and cleared) by
    /// `take_ground_strike`.
    struck_ground: bool,
    /// PX4's parameters (the few modelled).
    px4: Px4Params,
    geofence: Geofence,
    /// AUTO.RTL: the altitude (local z) it flies back at, and whether it is descending yet.
    return_z: f64,
    return_landing: bool,
}

impl Vehicle {
    /// A vehicle on the ground at its spawn point, disarmed, in AUTO.LOITER (what this PX4
    /// build boots into), not ready yet.
    pub fn new(params: VehicleParams) -> Self {
        Vehicle {
            params,
            time: 0.0,
            body: PointMass::at_rest(Vec3::zeros()),
            armed: false,
            mode: Px4Mode::Hold,
            mode_after_disarm: Px4Mode::Hold,
            failsafe: false,
            landed: true,
            alive: true,
            flown_since_arming: false,
            armed_on_ground_since: 0.0,
            home: Vec3::zeros(),
            hold_at: Vec3::zeros(),
            takeoff_to: Vec3::zeros(),
            land_at: Vec3::zeros(),
            setpoint: None,
            last_setpoint: None,
            stream_since: None,
            announced_ready: false,
            next_preflight_text: 0.0,
            texts: Vec::new(),
            struck_ground: false,
            px4: Px4Params::default(),
            geofence: Geofence::default(),
            return_z: 0.0,
            return_landing: false,
        }
    }

    /// PX4's parameters.
    pub fn px4_params(&self) -> &Px4Params {
        &self.px4
    }

    pub fn px4_params_mut(&mut self) -> &mut Px4Params {
        &mut self.px4
    }

    /// The geofence as uploaded (held, not enforced).
    pub fn geofence(&self) -> &Geofence {
        &self.geofence
    }

    pub fn geofence_mut(&mut self) -> &mut Geofence {
        &mut self.geofence
    }

    /// True once after the vehicle flew into the ground under power (see
    /// `HARD_TOUCHDOWN_SPEED`). A vehicle that lost power and fell is not counted: its fall is
    /// the fault that was injected, not something the flight software did.
    pub fn take_ground_strike(&mut self) -> bool {
        std::mem::take(&mut self.struck_ground)
    }

    /// The STATUSTEXTs said since the last call, oldest first.
    pub fn take_status_texts(&mut self) -> Vec<StatusText> {
        std::mem::take(&mut self.texts)
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

    /// Metres above mean sea level.
    pub fn amsl(&self) -> f64 {
        self.params.ground_amsl - self.body.position.z
    }

    /// Home in the local frame.
    pub fn home(&self) -> Vec3 {
        self.home
    }

    /// Home's altitude, metres above mean sea level.
    pub fn home_amsl(&self) -> f64 {
        self.params.ground_amsl - self.home.z
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

    /// The health checks pass (the readiness delay after boot is over).
    pub fn ready(&self) -> bool {
        self.alive && self.time + 1e-9 >= self.params.readiness_delay
    }

    /// Whether an ARM would be accepted now, in the current mode (PX4's `canArm(nav_state)`).
    pub fn can_arm(&self) -> bool {
        self.ready()
            && match self.mode {
                Px4Mode::Hold | Px4Mode::Takeoff => true,
                Px4Mode::Offboard => self.setpoints_fresh(self.px4.offboard_loss_timeout()),
                // Manual modes want a remote control; Land and the rest prevent arming or need
                // what the stand-in does not model.
                _ => false,
            }
    }

    /// HEARTBEAT.system_status as PX4 sets it.
    pub fn system_status(&self) -> MavState {
        if self.armed {
            if self.failsafe {
                MavState::MAV_STATE_CRITICAL
            } else {
                MavState::MAV_STATE_ACTIVE
            }
        } else if self.can_arm() {
            MavState::MAV_STATE_STANDBY
        } else {
            MavState::MAV_STATE_UNINIT
        }
    }

    pub fn landed_state(&self) -> LandedState {
        match (self.landed, self.mode) {
            (true, _) => LandedState::OnGround,
            (false, Px4Mode::Takeoff) => LandedState::Takeoff,
            (false, Px4Mode::Land) => LandedState::Landing,
            (false, RETURN) if self.return_landing => LandedState::Landing,
            (false, _) => LandedState::InAir,
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
        self.report_readiness();
        if self.alive
            && self.armed
            && self.mode == Px4Mode::Offboard
            && !self.setpoints_fresh(self.px4.offboard_loss_timeout())
        {
            self.offboard_lost();
        } else if self.failsafe && self.mode == Px4Mode::Hold && self.offboard_stream_ok() {
            // PX4's failsafe ends with its cause: the stream back, it flies the OFFBOARD asked
            // for again (PX4 SITL, a writer restarted under a vehicle holding in this failsafe).
            self.select_mode(Px4Mode::Offboard);
        }
        if !self.armed {
            if !self.landed {
                self.fall(dt);
            }
            return;
        }

        let reference = self.reference();
        let limits = self.params.limits;
        let control = if self.mode == Px4Mode::Takeoff {
            limits.with_climb_at_most(TAKEOFF_SPEED)
        } else {
            limits
        };
        let a = self.body.command(&reference, &control);
        // On the ground, only a climb command lifts the vehicle; it does not slide about.
        if !(self.landed && a.z >= 0.0) {
            self.body.integrate(a, dt, &limits);
            if self.body.position.z < 0.0 && self.landed {
                self.landed = false;
                self.flown_since_arming = true;
                self.say(MavSeverity::MAV_SEVERITY_INFO, text::TAKEOFF_DETECTED);
            }
            self.check_ground_contact();
        }

        if self.mode == RETURN && !self.return_landing {
            let p = self.body.position;
            let off = Vec3::new(p.x - self.home.x, p.y - self.home.y, 0.0);
            if off.norm() <= RETURN_ACCEPTANCE {
                // Above home: the landing phase of the return.
                self.return_landing = true;
                self.land_at = Vec3::new(self.home.x, self.home.y, p.z);
            }
        }
        if self.mode == Px4Mode::Takeoff
            && !self.landed
            && (self.body.position.z - self.takeoff_to.z).abs() <= TAKEOFF_ACCEPTANCE
        {
            // Commander's switch to AUTO.LOITER, holding at the take-off altitude.
            self.select_mode(Px4Mode::Hold);
            self.hold_at = self.takeoff_to;
        }
        self.auto_disarm();
    }

    // ---- status ----------------------------------------------------------------------------------

    fn say(&mut self, severity: MavSeverity, text: impl Into<String>) {
        if self.texts.len() >= MAX_PENDING_TEXTS {
            self.texts.remove(0);
        }
        self.texts.push(StatusText {
            severity,
            text: text.into(),
        });
    }

    fn report_readiness(&mut self) {
        if !self.alive {
            return;
        }
        if self.ready() {
            if !self.announced_ready {
                self.announced_ready = true;
                self.say(MavSeverity::MAV_SEVERITY_INFO, text::READY);
            }
        } else if self.time + 1e-9 >= self.next_preflight_text {
            self.next_preflight_text = self.time + PREFLIGHT_TEXT_PERIOD;
            self.say(MavSeverity::MAV_SEVERITY_CRITICAL, text::HEADING_INVALID);
        }
    }

    // ---- modes -----------------------------------------------------------------------------------

    /// A mode chosen by command (PX4's user intention): it ends a failsafe, and becomes the
    /// mode after disarming unless it prevents arming.
    fn select_mode(&mut self, mode: Px4Mode) {
        self.mode = mode;
        self.failsafe = false;
        if !prevents_arming(mode) {
            self.mode_after_disarm = mode;
        }
    }

    fn enter_hold(&mut self) {
        self.mode = Px4Mode::Hold;
        self.hold_at = self.body.position;
    }

    fn start_landing(&mut self) {
        self.mode = Px4Mode::Land;
        self.land_at = self.body.position;
    }

    /// AUTO.RTL (approximated): straight to above home at the current altitude (at least
    /// `RETURN_MIN_HEIGHT` above home), then land there.
    fn start_return(&mut self) {
        self.mode = RETURN;
        self.return_z = self.body.position.z.min(self.home.z - RETURN_MIN_HEIGHT);
        self.return_landing = false;
    }

    /// The offboard-loss failsafe (`COM_OBL_RC_ACT`). The mode asked for stays OFFBOARD: it is
    /// where a disarm returns to, and a mode command ends the failsafe.
    fn offboard_lost(&mut self) {
        match self.px4.offboard_loss_action() {
            OffboardLossAction::Hold => self.enter_hold(),
            OffboardLossAction::Land => self.start_landing(),
            OffboardLossAction::Return => self.start_return(),
            OffboardLossAction::MotorsOff => {
                // Terminate or disarm in the air: the motors stop and it falls.
                self.armed = false;
                self.failsafe = false;
                self.mode = self.mode_after_disarm;
                return;
            }
        }
        self.failsafe = true;
    }

    fn on_disarmed(&mut self, reason: &'static str) {
        self.armed = false;
        self.failsafe = false;
        self.say(MavSeverity::MAV_SEVERITY_INFO, reason);
        self.mode = self.mode_after_disarm;
        if self.mode == Px4Mode::Hold {
            self.hold_at = self.body.position;
        }
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
}

/// Modes PX4 never arms in, so a disarm does not return to them (`mode_req_prevent_arming`).
fn prevents_arming(mode: Px4Mode) -> bool {
    use tacos_shared::px4_mode::{AUTO_RTL, MAIN_AUTO};
    /// PX4's AUTO.PRECLAND sub mode.
    const AUTO_PRECLAND: u8 = 9;
    match mode {
        Px4Mode::Land => true,
        Px4Mode::Other { main, sub } => {
            main == MAIN_AUTO && (sub == AUTO_RTL || sub == AUTO_PRECLAND)
        }
        _ => false,
    }
}

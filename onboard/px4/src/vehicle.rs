//! The vehicle as seen over MAVLink: which system is the autopilot (pinned by its system id),
//! whether its heartbeats still arrive (link loss), its arming, mode and readiness, position
//! (and how old it is), AMSL altitude, heading and landed state; and the [`VehicleStateSample`]
//! built from all that. Pure: the clock is passed in.

use crate::procedure::AutopilotFacts;
use crate::reference::VehicleView;
use crate::setup::GeoFix;
use std::time::{Duration, Instant};
use tacos_shared::Vec3;
use tacos_shared::frames::{Home, ned_vector_to_enu};
use tacos_shared::ipc::{NEVER_MS, VehicleStateSample};
use tacos_shared::px4_mode::{self, Px4Mode};

/// An AMSL altitude older than this is not used for a take-off.
pub const ALTITUDE_FRESH: Duration = Duration::from_secs(2);
/// HEARTBEAT.system_status values.
pub mod mav_state {
    pub const UNINIT: u8 = 0;
    pub const STANDBY: u8 = 3;
    pub const ACTIVE: u8 = 4;
}

/// No autopilot heartbeat for this long = link lost.
pub const LINK_TIMEOUT: Duration = Duration::from_secs(3);
/// Without EXTENDED_SYS_STATE, a vehicle lower than this above its home counts as landed.
pub const LANDED_ALTITUDE_M: f64 = 0.3;
/// `heartbeat_age_ms` before the first heartbeat.
pub const NEVER: u64 = NEVER_MS;
/// MAV_LANDED_STATE values.
pub mod landed_state {
    pub const UNDEFINED: u8 = 0;
    pub const ON_GROUND: u8 = 1;
}

/// The autopilot's MAVLink address.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Autopilot {
    pub sysid: u8,
    pub compid: u8,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkChange {
    /// Heartbeats arrive (first contact, or back after a loss).
    Up,
    /// No heartbeat for [`LINK_TIMEOUT`].
    Lost,
}

/// What a heartbeat from an autopilot-like component meant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeartbeatVerdict {
    /// From the autopilot we talk to (its system id is the configured one).
    Ours,
    /// From another system: ignored.
    Foreign,
}

fn age_ms(now: Instant, at: Option<Instant>) -> u64 {
    at.map_or(NEVER, |t| {
        u64::try_from(now.saturating_duration_since(t).as_millis()).unwrap_or(NEVER)
    })
}

#[derive(Debug, Clone)]
pub struct VehicleTracker {
    home: Home,
    epoch: Instant,
    /// The configured system id of our autopilot (component 1).
    autopilot_sysid: u8,
    /// Known once its first heartbeat arrived.
    autopilot: Option<Autopilot>,
    last_heartbeat: Option<Instant>,
    base_mode: u8,
    custom_mode: u32,
    system_status: u8,
    link_reported: bool,
    /// World ENU position and velocity, and when they arrived.
    position: Option<(Vec3, Vec3)>,
    position_at: Option<Instant>,
    /// Altitude above mean sea level (GLOBAL_POSITION_INT), and when it arrived.
    amsl: Option<(f64, Instant)>,
    /// NED heading (radians from north, clockwise), when reported.
    heading: Option<f64>,
    /// The last geodetic fix (lat, lon in degrees × 10⁷) with the world position at that time.
    geo: Option<GeoFix>,
    /// The heading when PX4 entered OFFBOARD: held while it stays there.
    offboard_heading: Option<f64>,
    landed_state: Option<u8>,
}

impl VehicleTracker {
    /// `epoch` is time zero of `VehicleStateSample::stamp_ns`; only heartbeats from
    /// (`autopilot_sysid`, component 1) count as the autopilot's.
    pub fn new(home: Home, epoch: Instant, autopilot_sysid: u8) -> Self {
        VehicleTracker {
            home,
            epoch,
            autopilot_sysid,
            autopilot: None,
            last_heartbeat: None,
            base_mode: 0,
            custom_mode: 0,
            system_status: mav_state::UNINIT,
            link_reported: false,
            position: None,
            position_at: None,
            amsl: None,
            heading: None,
            geo: None,
            offboard_heading: None,
            landed_state: None,
        }
    }

    /// A HEARTBEAT from an autopilot (the caller checked MAV_AUTOPILOT is not INVALID). Only the
    /// configured system's component 1 is ours: another vehicle on a shared link never is.
    pub fn on_heartbeat(
        &mut self,
        now: Instant,
        sysid: u8,
        compid: u8,
        base_mode: u8,
        custom_mode: u32,
        system_status: u8,
    ) -> HeartbeatVerdict {
        if compid != crate::mav::AUTOPILOT_COMPONENT || sysid != self.autopilot_sysid {
            return HeartbeatVerdict::Foreign;
        }
        self.autopilot = Some(Autopilot { sysid, compid });
        self.last_heartbeat = Some(now);
        self.base_mode = base_mode;
        let was_offboard = self.mode() == Px4Mode::Offboard;
        self.custom_mode = custom_mode;
        self.system_status = system_status;
        match (was_offboard, self.mode() == Px4Mode::Offboard) {
            (false, true) => self.offboard_heading = self.heading,
            (_, false) => self.offboard_heading = None,
            (true, true) => {}
        }
        HeartbeatVerdict::Ours
    }

    /// GLOBAL_POSITION_INT: latitude and longitude (degrees × 10⁷; both 0 before a fix),
    /// altitude AMSL (mm) and heading (cdeg, `u16::MAX` = unknown). The geodetic fix is paired
    /// with the world position known now (none before the first LOCAL_POSITION_NED).
    pub fn on_global_position(
        &mut self,
        (lat_e7, lon_e7): (i32, i32),
        alt_mm: i32,
        hdg_cdeg: u16,
        now: Instant,
    ) {
        self.amsl = Some((f64::from(alt_mm) / 1000.0, now));
        if hdg_cdeg != u16::MAX {
            self.heading = Some(f64::from(hdg_cdeg).to_radians() / 100.0);
        }
        if let (Some((here, _)), false) = (self.position, lat_e7 == 0 && lon_e7 == 0) {
            self.geo = Some(GeoFix {
                here,
                lat_e7,
                lon_e7,
            });
        }
    }

    /// Where the vehicle is on Earth and in the world, once both are known.
    pub fn geo_fix(&self) -> Option<GeoFix> {
        self.geo
    }

    /// The heading to stream when the planner gives none: the one PX4 had when it entered
    /// OFFBOARD (so the heading is held, not left to drift), else the current one.
    pub fn held_heading(&self) -> Option<f64> {
        self.offboard_heading.or(self.heading)
    }

    /// What the command procedures need to know now.
    pub fn facts(&self, now: Instant) -> AutopilotFacts {
        AutopilotFacts {
            link_ok: self.link_ok(now),
            ready: self.ready(),
            armed: self.armed(),
            mode: self.mode(),
            amsl_m: self
                .amsl
                .filter(|(_, at)| now.saturating_duration_since(*at) <= ALTITUDE_FRESH)
                .map(|(alt, _)| alt),
        }
    }

    /// PX4 can arm now (its pre-flight checks pass) or is armed.
    pub fn ready(&self) -> bool {
        self.armed() || matches!(self.system_status, mav_state::STANDBY | mav_state::ACTIVE)
    }

    /// Whether a message from (`sysid`, `compid`) comes from our autopilot.
    pub fn is_autopilot(&self, sysid: u8, compid: u8) -> bool {
        self.autopilot
            .is_some_and(|ap| ap.sysid == sysid && ap.compid == compid)
    }

    /// LOCAL_POSITION_NED, in the vehicle's NED frame.
    pub fn on_local_position(&mut self, ned_position: Vec3, ned_velocity: Vec3, now: Instant) {
        self.position = Some((
            self.home.ned_to_enu(&ned_position),
            ned_vector_to_enu(&ned_velocity),
        ));
        self.position_at = Some(now);
    }

    /// EXTENDED_SYS_STATE.landed_state.
    pub fn on_extended_sys_state(&mut self, landed_state: u8) {
        self.landed_state = Some(landed_state);
    }

    pub fn autopilot(&self) -> Option<Autopilot> {
        self.autopilot
    }

    pub fn link_ok(&self, now: Instant) -> bool {
        self.last_heartbeat
            .is_some_and(|t| now.saturating_duration_since(t) < LINK_TIMEOUT)
    }

    /// Reports each change of the link state once.
    pub fn update_link(&mut self, now: Instant) -> Option<LinkChange> {
        let ok = self.link_ok(now);
        if ok == self.link_reported {
            return None;
        }
        self.link_reported = ok;
        Some(if ok { LinkChange::Up } else { LinkChange::Lost })
    }

    pub fn mode(&self) -> Px4Mode {
        Px4Mode::from_custom_mode(self.custom_mode)
    }

    pub fn armed(&self) -> bool {
        self.base_mode & px4_mode::BASE_MODE_ARMED != 0
    }

    /// What the reference keeper needs: the position (once known) and whether PX4 is in OFFBOARD.
    pub fn view(&self) -> Option<VehicleView> {
        self.position.map(|(position, _)| VehicleView {
            position,
            in_offboard: self.mode() == Px4Mode::Offboard,
        })
    }

    fn landed(&self) -> bool {
        match self.landed_state {
            Some(s) if s != landed_state::UNDEFINED => s == landed_state::ON_GROUND,
            // Nothing heard yet: a vehicle that has not reported is taken to be on its pad.
            _ => self
                .position
                .is_none_or(|(p, _)| p.z - self.home.enu.z < LANDED_ALTITUDE_M),
        }
    }

    /// The state for the planner. Before the first LOCAL_POSITION_NED the position is the home.
    pub fn sample(&self, now: Instant) -> VehicleStateSample {
        let (position, velocity) = self.position.unwrap_or((self.home.enu, Vec3::zeros()));
        VehicleStateSample {
            stamp_ns: u64::try_from(now.saturating_duration_since(self.epoch).as_nanos())
                .unwrap_or(u64::MAX),
            link_ok: u32::from(self.link_ok(now)),
            armed: u32::from(self.armed()),
            custom_mode: self.custom_mode,
            landed: u32::from(self.landed()),
            position: position.into(),
            velocity: velocity.into(),
            heartbeat_age_ms: age_ms(now, self.last_heartbeat),
            position_age_ms: age_ms(now, self.position_at),
            ready: u32::from(self.ready()),
            _reserved: 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(t0: Instant, ms: u64) -> Instant {
        t0 + Duration::from_millis(ms)
    }

    #[test]
    fn link_is_lost_after_three_silent_seconds_and_comes_back() {
        let t0 = Instant::now();
        let mut v = VehicleTracker::new(Home::new(Vec3::zeros()), t0, 1);
        assert!(!v.link_ok(t0));
        assert_eq!(v.update_link(t0), None, "never up, so nothing to report");
        assert_eq!(v.sample(t0).heartbeat_age_ms, NEVER);
        assert_eq!(
            v.on_heartbeat(at(t0, 100), 1, 1, 0, 0, 3),
            HeartbeatVerdict::Ours
        );
        assert_eq!(v.update_link(at(t0, 100)), Some(LinkChange::Up));
        assert_eq!(v.update_link(at(t0, 200)), None);
        assert_eq!(v.sample(at(t0, 3099)).link_ok, 1);
        assert_eq!(v.sample(at(t0, 3099)).heartbeat_age_ms, 2999);
        assert_eq!(v.update_link(at(t0, 3100)), Some(LinkChange::Lost));
        assert_eq!(v.update_link(at(t0, 3200)), None, "reported once");
        assert_eq!(v.sample(at(t0, 3100)).link_ok, 0);
        v.on_heartbeat(at(t0, 5000), 1, 1, 0, 0, 3);
        assert_eq!(v.update_link(at(t0, 5000)), Some(LinkChange::Up));
    }

    #[test]
    fn only_the_configured_autopilot_counts() {
        let t0 = Instant::now();
        let mut v = VehicleTracker::new(Home::new(Vec3::zeros()), t0, 7);
        assert_eq!(
            v.on_heartbeat(t0, 7, 191, 0, 0, 3),
            HeartbeatVerdict::Foreign,
            "not an autopilot component"
        );
        assert_eq!(
            v.on_heartbeat(t0, 8, 1, 0, 0, 3),
            HeartbeatVerdict::Foreign,
            "another vehicle on the same link, even if it speaks first"
        );
        assert_eq!(v.autopilot(), None);
        assert_eq!(v.on_heartbeat(t0, 7, 1, 0, 0, 3), HeartbeatVerdict::Ours);
        assert_eq!(v.on_heartbeat(t0, 8, 1, 0, 0, 3), HeartbeatVerdict::Foreign);
        assert_eq!(
            v.autopilot(),
            Some(Autopilot {
                sysid: 7,
                compid: 1
            })
        );
        assert!(v.is_autopilot(7, 1) && !v.is_autopilot(8, 1) && !v.is_autopilot(7, 2));
    }

    #[test]
    fn readiness_altitude_heading_and_position_age() {
        let t0 = Instant::now();
        let mut v = VehicleTracker::new(Home::new(Vec3::zeros()), t0, 1);
        let hold = Px4Mode::Hold.custom_mode();
        v.on_heartbeat(t0, 1, 1, 0, hold, mav_state::UNINIT);
        assert!(!v.ready() && !v.facts(t0).ready);
        assert_eq!(v.facts(t0).amsl_m, None);
        assert_eq!(v.sample(t0).position_age_ms, NEVER, "no position yet");
        v.on_heartbeat(at(t0, 1000), 1, 1, 0, hold, mav_state::STANDBY);
        assert!(v.ready());
        v.on_global_position((0, 0), 489_370, 9_000, at(t0, 1000));
        assert_eq!(v.facts(at(t0, 1000)).amsl_m, Some(489.37));
        assert_eq!(
            v.facts(at(t0, 1000) + ALTITUDE_FRESH + Duration::from_millis(1))
                .amsl_m,
            None,
            "stale"
        );
        v.on_local_position(Vec3::zeros(), Vec3::zeros(), at(t0, 1000));
        assert_eq!(v.sample(at(t0, 1750)).position_age_ms, 750);
        // The heading at offboard entry is held while in offboard.
        let east = std::f64::consts::FRAC_PI_2;
        assert!((v.held_heading().unwrap_or(0.0) - east).abs() < 1e-9);
        v.on_heartbeat(
            at(t0, 2000),
            1,
            1,
            128,
            Px4Mode::Offboard.custom_mode(),
            mav_state::ACTIVE,
        );
        v.on_global_position((473_977_420, 85_455_940), 489_370, 18_000, at(t0, 2100));
        assert_eq!(
            v.geo_fix().map(|g| (g.lat_e7, g.lon_e7)),
            Some((473_977_420, 85_455_940)),
            "a fix once a position is known"
        );
        assert!(
            (v.held_heading().unwrap_or(0.0) - east).abs() < 1e-9,
            "held"
        );
        v.on_heartbeat(at(t0, 3000), 1, 1, 128, hold, mav_state::ACTIVE);
        assert!(
            (v.held_heading().unwrap_or(0.0) - std::f64::consts::PI).abs() < 1e-9,
            "follows again"
        );
    }

    #[test]
    fn state_is_in_world_enu_with_mode_arming_and_landed() {
        let t0 = Instant::now();
        let home = Home::new(Vec3::new(100.0, 50.0, 1.0));
        let mut v = VehicleTracker::new(home, t0, 1);
        let s = v.sample(t0);
        assert_eq!(
            (s.position, s.landed),
            ([100.0, 50.0, 1.0], 1),
            "home until a position arrives"
        );
        v.on_heartbeat(
            t0,
            1,
            1,
            px4_mode::BASE_MODE_ARMED | 1,
            Px4Mode::Offboard.custom_mode(),
            mav_state::ACTIVE,
        );
        // 10 m north, 5 m east, 8 m up of home; climbing at 1 m/s.
        v.on_local_position(Vec3::new(10.0, 5.0, -8.0), Vec3::new(0.0, 0.0, -1.0), t0);
        let s = v.sample(at(t0, 250));
        assert_eq!(s.position, [105.0, 60.0, 9.0]);
        assert_eq!(s.velocity, [0.0, 0.0, 1.0]);
        assert_eq!(
            (s.armed, s.mode(), s.landed, s.stamp_ns),
            (1, Px4Mode::Offboard, 0, 250_000_000)
        );
        assert_eq!(
            v.view().map(|w| (w.position, w.in_offboard)),
            Some((Vec3::new(105.0, 60.0, 9.0), true))
        );
        // Low above home: landed by altitude …
        v.on_local_position(Vec3::new(10.0, 5.0, -0.1), Vec3::zeros(), t0);
        assert_eq!(v.sample(t0).landed, 1);
        // … unless PX4 says otherwise.
        v.on_extended_sys_state(2);
        assert_eq!(v.sample(t0).landed, 0);
        v.on_local_position(Vec3::new(10.0, 5.0, -30.0), Vec3::zeros(), t0);
        v.on_extended_sys_state(landed_state::ON_GROUND);
        assert_eq!(v.sample(t0).landed, 1);
        v.on_extended_sys_state(landed_state::UNDEFINED);
        assert_eq!(v.sample(t0).landed, 0, "undefined falls back to altitude");
    }
}

//! The vehicle as seen over MAVLink: which system is the autopilot, whether its heartbeats still
//! arrive (link loss), its arming and mode, position and landed state; and the
//! [`VehicleStateSample`] built from all that. Pure: the clock is passed in.

use crate::reference::VehicleView;
use std::time::{Duration, Instant};
use tacos_shared::Vec3;
use tacos_shared::frames::{Home, ned_vector_to_enu};
use tacos_shared::ipc::VehicleStateSample;
use tacos_shared::px4_mode::{self, Px4Mode};

/// No autopilot heartbeat for this long = link lost.
pub const LINK_TIMEOUT: Duration = Duration::from_secs(3);
/// Without EXTENDED_SYS_STATE, a vehicle lower than this above its home counts as landed.
pub const LANDED_ALTITUDE_M: f64 = 0.3;
/// `heartbeat_age_ms` before the first heartbeat.
pub const NEVER: u64 = u64::MAX;
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
    /// From the autopilot we talk to (learnt now if it is the first).
    Ours,
    /// From another system: ignored.
    Foreign,
}

#[derive(Debug, Clone)]
pub struct VehicleTracker {
    home: Home,
    epoch: Instant,
    autopilot: Option<Autopilot>,
    last_heartbeat: Option<Instant>,
    base_mode: u8,
    custom_mode: u32,
    link_reported: bool,
    /// World ENU position and velocity.
    position: Option<(Vec3, Vec3)>,
    landed_state: Option<u8>,
}

impl VehicleTracker {
    /// `epoch` is time zero of `VehicleStateSample::stamp_ns`.
    pub fn new(home: Home, epoch: Instant) -> Self {
        VehicleTracker {
            home,
            epoch,
            autopilot: None,
            last_heartbeat: None,
            base_mode: 0,
            custom_mode: 0,
            link_reported: false,
            position: None,
            landed_state: None,
        }
    }

    /// A HEARTBEAT from an autopilot (the caller checked MAV_AUTOPILOT is not INVALID). The first
    /// one from component 1 fixes the autopilot's system id.
    pub fn on_heartbeat(
        &mut self,
        now: Instant,
        sysid: u8,
        compid: u8,
        base_mode: u8,
        custom_mode: u32,
    ) -> HeartbeatVerdict {
        if compid != crate::mav::AUTOPILOT_COMPONENT {
            return HeartbeatVerdict::Foreign;
        }
        match self.autopilot {
            Some(ap) if ap.sysid != sysid => return HeartbeatVerdict::Foreign,
            Some(_) => {}
            None => self.autopilot = Some(Autopilot { sysid, compid }),
        }
        self.last_heartbeat = Some(now);
        self.base_mode = base_mode;
        self.custom_mode = custom_mode;
        HeartbeatVerdict::Ours
    }

    /// Whether a message from (`sysid`, `compid`) comes from our autopilot.
    pub fn is_autopilot(&self, sysid: u8, compid: u8) -> bool {
        self.autopilot
            .is_some_and(|ap| ap.sysid == sysid && ap.compid == compid)
    }

    /// LOCAL_POSITION_NED, in the vehicle's NED frame.
    pub fn on_local_position(&mut self, ned_position: Vec3, ned_velocity: Vec3) {
        self.position = Some((
            self.home.ned_to_enu(&ned_position),
            ned_vector_to_enu(&ned_velocity),
        ));
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
        let age = self.last_heartbeat.map_or(NEVER, |t| {
            u64::try_from(now.saturating_duration_since(t).as_millis()).unwrap_or(NEVER)
        });
        VehicleStateSample {
            stamp_ns: u64::try_from(now.saturating_duration_since(self.epoch).as_nanos())
                .unwrap_or(u64::MAX),
            link_ok: u32::from(self.link_ok(now)),
            armed: u32::from(self.armed()),
            custom_mode: self.custom_mode,
            landed: u32::from(self.landed()),
            position: position.into(),
            velocity: velocity.into(),
            heartbeat_age_ms: age,
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
        let mut v = VehicleTracker::new(Home::new(Vec3::zeros()), t0);
        assert!(!v.link_ok(t0));
        assert_eq!(v.update_link(t0), None, "never up, so nothing to report");
        assert_eq!(v.sample(t0).heartbeat_age_ms, NEVER);
        assert_eq!(
            v.on_heartbeat(at(t0, 100), 1, 1, 0, 0),
            HeartbeatVerdict::Ours
        );
        assert_eq!(v.update_link(at(t0, 100)), Some(LinkChange::Up));
        assert_eq!(v.update_link(at(t0, 200)), None);
        assert_eq!(v.sample(at(t0, 3099)).link_ok, 1);
        assert_eq!(v.sample(at(t0, 3099)).heartbeat_age_ms, 2999);
        assert_eq!(v.update_link(at(t0, 3100)), Some(LinkChange::Lost));
        assert_eq!(v.update_link(at(t0, 3200)), None, "reported once");
        assert_eq!(v.sample(at(t0, 3100)).link_ok, 0);
        v.on_heartbeat(at(t0, 5000), 1, 1, 0, 0);
        assert_eq!(v.update_link(at(t0, 5000)), Some(LinkChange::Up));
    }

    #[test]
    fn only_the_first_autopilot_counts() {
        let t0 = Instant::now();
        let mut v = VehicleTracker::new(Home::new(Vec3::zeros()), t0);
        assert_eq!(
            v.on_heartbeat(t0, 7, 191, 0, 0),
            HeartbeatVerdict::Foreign,
            "not an autopilot component"
        );
        assert_eq!(v.autopilot(), None);
        assert_eq!(v.on_heartbeat(t0, 7, 1, 0, 0), HeartbeatVerdict::Ours);
        assert_eq!(v.on_heartbeat(t0, 8, 1, 0, 0), HeartbeatVerdict::Foreign);
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
    fn state_is_in_world_enu_with_mode_arming_and_landed() {
        let t0 = Instant::now();
        let home = Home::new(Vec3::new(100.0, 50.0, 1.0));
        let mut v = VehicleTracker::new(home, t0);
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
        );
        // 10 m north, 5 m east, 8 m up of home; climbing at 1 m/s.
        v.on_local_position(Vec3::new(10.0, 5.0, -8.0), Vec3::new(0.0, 0.0, -1.0));
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
        v.on_local_position(Vec3::new(10.0, 5.0, -0.1), Vec3::zeros());
        assert_eq!(v.sample(t0).landed, 1);
        // … unless PX4 says otherwise.
        v.on_extended_sys_state(2);
        assert_eq!(v.sample(t0).landed, 0);
        v.on_local_position(Vec3::new(10.0, 5.0, -30.0), Vec3::zeros());
        v.on_extended_sys_state(landed_state::ON_GROUND);
        assert_eq!(v.sample(t0).landed, 1);
        v.on_extended_sys_state(landed_state::UNDEFINED);
        assert_eq!(v.sample(t0).landed, 0, "undefined falls back to altitude");
    }
}

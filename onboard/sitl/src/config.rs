//! What one simulator run is made of: the scenario, how many vehicles, their ports, the speed,
//! and how PX4-like the vehicles are set up.

use crate::error::SitlError;
use crate::geo::GeoOrigin;
use crate::streams::LinkProfile;
use crate::vehicle::DEFAULT_READINESS_DELAY;
use tacos_bus::BusArgs;
use tacos_shared::scenario::{DroneSlot, Scenario};

/// PX4 SITL instance i sends to 14540+i (where the offboard API / the writer listens).
pub const DEFAULT_MAVLINK_BASE_PORT: u16 = 14540;
/// PX4 SITL instance i binds 14580+i locally.
pub const DEFAULT_SITL_BASE_PORT: u16 = 14580;

/// The longest readiness delay accepted (s).
pub const MAX_READINESS_DELAY: f64 = 600.0;

/// How the simulated PX4s are set up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Px4Options {
    /// Where world ENU (0, 0, 0) is on the Earth; altitudes are reported AMSL from it.
    pub origin: GeoOrigin,
    /// Seconds after start before a vehicle's health checks pass and it can arm.
    pub readiness_delay_s: f64,
    /// The default stream rates of every vehicle's link.
    pub link_profile: LinkProfile,
}

impl Default for Px4Options {
    fn default() -> Self {
        Px4Options {
            origin: GeoOrigin::default(),
            readiness_delay_s: DEFAULT_READINESS_DELAY,
            link_profile: LinkProfile::default(),
        }
    }
}

impl Px4Options {
    pub fn validate(&self) -> Result<(), SitlError> {
        if !self.origin.is_valid() {
            return Err(SitlError::Config(format!(
                "the geodetic origin {:?} is not a place on the Earth (|lat| <= 85, |lon| <= 180, \
                 |amsl| <= 100 km)",
                self.origin
            )));
        }
        if !(self.readiness_delay_s.is_finite()
            && (0.0..=MAX_READINESS_DELAY).contains(&self.readiness_delay_s))
        {
            return Err(SitlError::Config(format!(
                "--readiness-delay must be in [0, {MAX_READINESS_DELAY}] s, got {}",
                self.readiness_delay_s
            )));
        }
        Ok(())
    }
}

/// Real PX4 SITL vehicles to observe instead of simulating: drone slot i is PX4 instance
/// (first) + i, read on its GCS link at 127.0.0.1:(`gcs_base_port` + i) with system id
/// `first_sysid` + i.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ObservePx4 {
    pub gcs_base_port: u16,
    pub first_sysid: u8,
}

/// Everything [`crate::run`] needs; built by the binary from its flags, or by a test directly.
#[derive(Debug, Clone)]
pub struct SitlConfig {
    pub scenario: Scenario,
    /// Vehicles to simulate: slots `0..drones` of the scenario (slot i = vehicle i).
    pub drones: usize,
    /// Vehicle i sends its MAVLink to `127.0.0.1:(mavlink_base_port + i)` until it hears from a peer.
    pub mavlink_base_port: u16,
    /// Vehicle i binds `127.0.0.1:(sitl_base_port + i)`.
    pub sitl_base_port: u16,
    /// Sim seconds per wall second while no model call is in flight (see [`SitlConfig::rate`]).
    pub speed: f64,
    pub px4: Px4Options,
    /// With `Some`, no vehicle is simulated: the world observes these real ones.
    pub observe: Option<ObservePx4>,
    pub bus: BusArgs,
}

impl SitlConfig {
    /// A configuration with PX4's default ports and real-time speed.
    pub fn new(scenario: Scenario, drones: usize, bus: BusArgs) -> Self {
        SitlConfig {
            scenario,
            drones,
            mavlink_base_port: DEFAULT_MAVLINK_BASE_PORT,
            sitl_base_port: DEFAULT_SITL_BASE_PORT,
            speed: 1.0,
            px4: Px4Options::default(),
            observe: None,
            bus,
        }
    }

    /// Sim seconds per wall second: `speed`, but real time while the ground has a model call in
    /// flight, so that the models meet the world at the pace a real flight would give them.
    pub fn rate(&self, model_call_in_flight: bool) -> f64 {
        if model_call_in_flight {
            1.0
        } else {
            self.speed
        }
    }

    /// Checks the numbers and returns the drone slots to simulate.
    pub fn validate(&self) -> Result<&[DroneSlot], SitlError> {
        if !(self.speed.is_finite() && self.speed > 0.0 && self.speed <= 100.0) {
            return Err(SitlError::Config(format!(
                "--speed must be in (0, 100], got {}",
                self.speed
            )));
        }
        self.px4.validate()?;
        // MAVLink system ids are 1..=255 and vehicle i is system i + 1.
        if !(1..=255).contains(&self.drones) {
            return Err(SitlError::Config(format!(
                "--drones must be in 1..=255, got {}",
                self.drones
            )));
        }
        let slots = self
            .scenario
            .first_drones(self.drones)
            .map_err(SitlError::Config)?;
        let last = self.drones - 1;
        for (base, flag) in [
            (self.mavlink_base_port, "--mavlink-base-port"),
            (self.sitl_base_port, "--sitl-base-port"),
        ] {
            if base == 0 || usize::from(base) + last > usize::from(u16::MAX) {
                return Err(SitlError::Config(format!(
                    "{flag} {base} + {last} is not a valid port"
                )));
            }
        }
        let (a, b) = (
            usize::from(self.mavlink_base_port),
            usize::from(self.sitl_base_port),
        );
        if a.max(b) - a.min(b) <= last {
            return Err(SitlError::Config(format!(
                "the MAVLink port ranges {a}..={} and {b}..={} overlap",
                a + last,
                b + last
            )));
        }
        Ok(slots)
    }

    pub fn mavlink_port(&self, vehicle: usize) -> u16 {
        port_at(self.mavlink_base_port, vehicle)
    }

    pub fn sitl_port(&self, vehicle: usize) -> u16 {
        port_at(self.sitl_base_port, vehicle)
    }
}

/// `base + i`, saturating (validated beforehand by [`SitlConfig::validate`]).
fn port_at(base: u16, i: usize) -> u16 {
    u16::try_from(i)
        .ok()
        .and_then(|i| base.checked_add(i))
        .unwrap_or(u16::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_shared::SwarmId;

    fn config(drones: usize) -> SitlConfig {
        let scenario = Scenario::builtin("lab").expect("lab is valid");
        let bus = BusArgs::loopback(SwarmId::new("t").expect("valid"), None, vec![]);
        SitlConfig::new(scenario, drones, bus)
    }

    #[test]
    fn defaults_are_px4s_ports() {
        let c = config(3);
        assert_eq!(c.validate().map(|s| s.len()).ok(), Some(3));
        assert_eq!((c.mavlink_port(2), c.sitl_port(2)), (14542, 14582));
    }

    #[test]
    fn bad_settings_are_refused() {
        assert!(config(4).validate().is_err(), "lab has three slots");
        assert!(config(0).validate().is_err());
        let mut c = config(3);
        c.sitl_base_port = 14542;
        assert!(c.validate().is_err(), "overlapping ranges");
        let mut c = config(3);
        c.speed = 0.0;
        assert!(c.validate().is_err());
        let mut c = config(3);
        c.sitl_base_port = u16::MAX;
        assert!(c.validate().is_err());
        let mut c = config(3);
        c.px4.readiness_delay_s = -1.0;
        assert!(c.validate().is_err());
        let mut c = config(3);
        c.px4.origin.lat_deg = f64::NAN;
        assert!(c.validate().is_err());
    }

    #[test]
    fn px4_defaults_are_sihs() {
        let c = config(1);
        assert_eq!(c.px4.origin.amsl_m, 489.4);
        assert_eq!(c.px4.readiness_delay_s, 2.0);
        assert_eq!(c.px4.link_profile, LinkProfile::Onboard);
    }

    #[test]
    fn a_model_call_in_flight_holds_real_time() {
        let mut c = config(3);
        c.speed = 4.0;
        assert_eq!(c.rate(false), 4.0);
        assert_eq!(c.rate(true), 1.0);
    }
}

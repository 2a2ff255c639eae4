//! World ENU ↔ PX4 local NED.
//!
//! The world frame is ENU with a shared origin; each PX4 vehicle flies in NED with its origin at
//! its own home (where it was powered up). Only `tacos-px4` (and the simulator standing in for
//! PX4) convert; everything else speaks ENU.

use crate::geometry::Vec3;
use std::f64::consts::FRAC_PI_2;

/// A vehicle's home: its NED origin, given in world ENU.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Home {
    pub enu: Vec3,
}

impl Home {
    pub fn new(enu: Vec3) -> Self {
        Home { enu }
    }

    /// World ENU position → this vehicle's local NED position.
    pub fn enu_to_ned(&self, p: &Vec3) -> Vec3 {
        enu_vector_to_ned(&(p - self.enu))
    }

    /// This vehicle's local NED position → world ENU position.
    pub fn ned_to_enu(&self, p: &Vec3) -> Vec3 {
        ned_vector_to_enu(p) + self.enu
    }
}

/// Where the world frame's origin is on Earth, for autopilots that need a geodetic position
/// (PX4 SITL's SIH spawns each vehicle at a latitude, longitude and altitude). SIH's own default
/// origin, so a vehicle at the world origin spawns where PX4 would put it unasked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeodeticOrigin {
    pub lat_deg: f64,
    pub lon_deg: f64,
    /// Metres above mean sea level of the world's z = 0.
    pub alt_m: f64,
}

/// PX4 SIH's default origin (47.397742 N, 8.545594 E, 489.4 m AMSL).
pub const SIH_ORIGIN: GeodeticOrigin = GeodeticOrigin {
    lat_deg: 47.397742,
    lon_deg: 8.545594,
    alt_m: 489.4,
};

/// Metres per degree of latitude (WGS-84 mean; the flat-earth approximation is exact to
/// centimetres over the few hundred metres of a map).
const METRES_PER_DEG_LAT: f64 = 111_319.49;

impl GeodeticOrigin {
    /// A world ENU point → (latitude °, longitude °, altitude m AMSL).
    pub fn to_geodetic(&self, p: &Vec3) -> (f64, f64, f64) {
        let lat = self.lat_deg + p.y / METRES_PER_DEG_LAT;
        let lon = self.lon_deg + p.x / (METRES_PER_DEG_LAT * self.lat_deg.to_radians().cos());
        (lat, lon, self.alt_m + p.z)
    }
}

/// A free vector (velocity, acceleration, offset) from ENU to NED axes.
pub fn enu_vector_to_ned(v: &Vec3) -> Vec3 {
    Vec3::new(v.y, v.x, -v.z)
}

/// A free vector from NED to ENU axes (the same swap; it is its own inverse).
pub fn ned_vector_to_enu(v: &Vec3) -> Vec3 {
    Vec3::new(v.y, v.x, -v.z)
}

/// Yaw in ENU (from +x/east, counter-clockwise) → yaw in NED (from north, clockwise), wrapped to
/// (-π, π].
pub fn enu_yaw_to_ned(yaw: f64) -> f64 {
    wrap_angle(FRAC_PI_2 - yaw)
}

/// Inverse of [`enu_yaw_to_ned`].
pub fn ned_yaw_to_enu(yaw: f64) -> f64 {
    wrap_angle(FRAC_PI_2 - yaw)
}

/// Wraps an angle to (-π, π].
pub fn wrap_angle(a: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    let w = a.rem_euclid(TAU);
    if w > PI { w - TAU } else { w }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn north_is_plus_y_in_enu_and_plus_x_in_ned() {
        let home = Home::new(Vec3::zeros());
        let north_10m_up_5m = Vec3::new(0.0, 10.0, 5.0);
        assert_eq!(
            home.enu_to_ned(&north_10m_up_5m),
            Vec3::new(10.0, 0.0, -5.0)
        );
        let east = Vec3::new(3.0, 0.0, 0.0);
        assert_eq!(home.enu_to_ned(&east), Vec3::new(0.0, 3.0, 0.0));
    }

    #[test]
    fn home_offset_is_applied_before_the_axis_swap() {
        // A vehicle whose pad is 60 m east and 120 m south of the world origin.
        let home = Home::new(Vec3::new(60.0, -120.0, 0.0));
        // Its own pad, 10 m up, is straight above its NED origin.
        assert_eq!(
            home.enu_to_ned(&Vec3::new(60.0, -120.0, 10.0)),
            Vec3::new(0.0, 0.0, -10.0)
        );
        // The world origin is 120 m north and 60 m west of it.
        assert_eq!(
            home.enu_to_ned(&Vec3::zeros()),
            Vec3::new(120.0, -60.0, 0.0)
        );
    }

    #[test]
    fn yaw_conventions() {
        // Facing east: ENU yaw 0, NED yaw +90°.
        assert!((enu_yaw_to_ned(0.0) - FRAC_PI_2).abs() < 1e-12);
        // Facing north: ENU yaw +90°, NED yaw 0.
        assert!(enu_yaw_to_ned(FRAC_PI_2).abs() < 1e-12);
    }

    proptest! {
        #[test]
        fn positions_round_trip(h in prop::array::uniform3(-500.0..500.0f64), p in prop::array::uniform3(-500.0..500.0f64)) {
            let home = Home::new(Vec3::from(h));
            let p = Vec3::from(p);
            prop_assert!((home.ned_to_enu(&home.enu_to_ned(&p)) - p).norm() < 1e-9);
        }

        #[test]
        fn yaw_round_trips(yaw in -3.1..3.1f64) {
            prop_assert!((ned_yaw_to_enu(enu_yaw_to_ned(yaw)) - yaw).abs() < 1e-9);
        }
    }

    #[test]
    fn geodetic_offsets_are_metres_on_the_ground() {
        let (lat, lon, alt) = SIH_ORIGIN.to_geodetic(&Vec3::new(100.0, 200.0, 2.0));
        let north = (lat - SIH_ORIGIN.lat_deg) * METRES_PER_DEG_LAT;
        let east =
            (lon - SIH_ORIGIN.lon_deg) * METRES_PER_DEG_LAT * SIH_ORIGIN.lat_deg.to_radians().cos();
        assert!((north - 200.0).abs() < 1e-6 && (east - 100.0).abs() < 1e-6);
        assert!((alt - 491.4).abs() < 1e-9);
    }
}

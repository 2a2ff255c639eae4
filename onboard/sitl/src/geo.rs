//! Where the simulated world is on the Earth: a fixed geodetic origin for world ENU (0, 0, 0)
//! and a flat-earth projection around it, good to centimetres over the few kilometres a
//! scenario spans. Pure.
//!
//! The defaults are PX4 SIH's (`SIH_LOC_LAT0`, `SIH_LOC_LON0`, `SIH_LOC_H0`): PX4 reports
//! altitudes above mean sea level (AMSL), and take-off altitudes are AMSL, so the origin's
//! altitude is deliberately not zero.

use tacos_shared::Vec3;
use tacos_shared::frames::ned_vector_to_enu;

/// SIH's default latitude of its origin (degrees).
pub const DEFAULT_ORIGIN_LAT_DEG: f64 = 47.397742;
/// SIH's default longitude of its origin (degrees).
pub const DEFAULT_ORIGIN_LON_DEG: f64 = 8.545594;
/// SIH's default altitude of its origin (m AMSL): the ground at world z = 0.
pub const DEFAULT_ORIGIN_AMSL_M: f64 = 489.4;
/// PX4's `CONSTANTS_RADIUS_OF_EARTH` (m).
const EARTH_RADIUS_M: f64 = 6_371_000.0;

/// The geodetic position of world ENU (0, 0, 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeoOrigin {
    pub lat_deg: f64,
    pub lon_deg: f64,
    /// Metres above mean sea level.
    pub amsl_m: f64,
}

impl Default for GeoOrigin {
    fn default() -> Self {
        GeoOrigin {
            lat_deg: DEFAULT_ORIGIN_LAT_DEG,
            lon_deg: DEFAULT_ORIGIN_LON_DEG,
            amsl_m: DEFAULT_ORIGIN_AMSL_M,
        }
    }
}

/// A geodetic position in MAVLink's integer units.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GlobalPosition {
    /// Latitude, degrees × 10⁷.
    pub lat_e7: i32,
    /// Longitude, degrees × 10⁷.
    pub lon_e7: i32,
    /// Altitude AMSL, millimetres.
    pub alt_mm: i32,
}

impl GeoOrigin {
    pub fn is_valid(&self) -> bool {
        self.lat_deg.is_finite()
            && self.lon_deg.is_finite()
            && self.amsl_m.is_finite()
            && self.lat_deg.abs() <= 85.0
            && self.lon_deg.abs() <= 180.0
            && self.amsl_m.abs() <= 100_000.0
    }

    /// Metres above mean sea level of a world ENU point.
    pub fn amsl(&self, enu: &Vec3) -> f64 {
        self.amsl_m + enu.z
    }

    /// The geodetic position of a world ENU point (flat earth around the origin).
    pub fn global(&self, enu: &Vec3) -> GlobalPosition {
        let lat = self.lat_deg + (enu.y / EARTH_RADIUS_M).to_degrees();
        let lon = self.lon_deg
            + (enu.x / (EARTH_RADIUS_M * self.lat_deg.to_radians().cos())).to_degrees();
        GlobalPosition {
            lat_e7: saturating_i32(lat * 1e7),
            lon_e7: saturating_i32(lon * 1e7),
            alt_mm: saturating_i32(self.amsl(enu) * 1000.0),
        }
    }
}

/// One vehicle's local NED frame on the Earth: its origin is its spawn point, `spawn_enu` in
/// world ENU.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalFrame {
    pub origin: GeoOrigin,
    pub spawn_enu: Vec3,
}

impl LocalFrame {
    /// Metres above mean sea level of the local origin.
    pub fn ground_amsl(&self) -> f64 {
        self.origin.amsl(&self.spawn_enu)
    }

    /// The geodetic position of a point of the local NED frame.
    pub fn global(&self, ned: &Vec3) -> GlobalPosition {
        self.origin
            .global(&(self.spawn_enu + ned_vector_to_enu(ned)))
    }
}

/// Rounds to the nearest integer, saturating at the ends of `i32` (NaN → 0).
pub fn saturating_i32(x: f64) -> i32 {
    // `as` saturates and maps NaN to 0.
    x.round() as i32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_origin_is_sihs_and_metres_map_to_degrees() {
        let o = GeoOrigin::default();
        assert!(o.is_valid());
        let at = o.global(&Vec3::zeros());
        assert_eq!(
            (at.lat_e7, at.lon_e7, at.alt_mm),
            (473_977_420, 85_455_940, 489_400)
        );
        // 100 m north: 100 / 6371 km rad ≈ 8.993e-4 degrees.
        let north = o.global(&Vec3::new(0.0, 100.0, 0.0));
        assert_eq!(north.lat_e7 - at.lat_e7, 8_993);
        assert_eq!(north.lon_e7, at.lon_e7);
        // 100 m east is more degrees of longitude at 47° N.
        let east = o.global(&Vec3::new(100.0, 0.0, 2.5));
        assert_eq!(east.lat_e7, at.lat_e7);
        assert_eq!(east.lon_e7 - at.lon_e7, 13_286);
        assert_eq!(east.alt_mm, 491_900);
        assert!((o.amsl(&Vec3::new(0.0, 0.0, 10.0)) - 499.4).abs() < 1e-9);
    }

    #[test]
    fn a_local_frame_starts_at_its_spawn_point() {
        let frame = LocalFrame {
            origin: GeoOrigin::default(),
            spawn_enu: Vec3::new(100.0, 0.0, 3.0),
        };
        assert!((frame.ground_amsl() - 492.4).abs() < 1e-9);
        let here = frame.global(&Vec3::zeros());
        assert_eq!(here, frame.origin.global(&Vec3::new(100.0, 0.0, 3.0)));
        // 100 m north and 10 m up in NED.
        let there = frame.global(&Vec3::new(100.0, 0.0, -10.0));
        assert_eq!(there.lat_e7 - here.lat_e7, 8_993);
        assert_eq!(there.alt_mm - here.alt_mm, 10_000);
    }

    #[test]
    fn nonsense_origins_are_invalid() {
        for o in [
            GeoOrigin {
                lat_deg: f64::NAN,
                ..GeoOrigin::default()
            },
            GeoOrigin {
                lat_deg: 90.0,
                ..GeoOrigin::default()
            },
            GeoOrigin {
                amsl_m: f64::INFINITY,
                ..GeoOrigin::default()
            },
        ] {
            assert!(!o.is_valid(), "{o:?}");
        }
        assert_eq!(saturating_i32(f64::NAN), 0);
        assert_eq!(saturating_i32(1e20), i32::MAX);
    }
}

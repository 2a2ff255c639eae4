//! World ENU references → the vehicle's local NED targets, and the SET_POSITION_TARGET type mask.
//!
//! This is the one place where the classic crash (a goto sent in the wrong frame) can happen, so
//! it is small, pure and tested with a non-zero home.

use tacos_shared::Vec3;
use tacos_shared::frames::{Home, enu_vector_to_ned, enu_yaw_to_ned};

/// A reference in the world frame (ENU), as the planner thinks of it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnuReference {
    pub position: Vec3,
    pub velocity: Vec3,
    pub acceleration: Vec3,
    /// ENU yaw in radians; `None` keeps the current heading.
    pub yaw: Option<f64>,
}

impl EnuReference {
    /// Hold still at `position` (velocity and acceleration zero), keeping `yaw`.
    pub fn hold(position: Vec3, yaw: Option<f64>) -> Self {
        EnuReference {
            position,
            velocity: Vec3::zeros(),
            acceleration: Vec3::zeros(),
            yaw,
        }
    }
}

/// The same reference in the vehicle's local NED frame (origin at its home).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NedTarget {
    pub position: Vec3,
    pub velocity: Vec3,
    pub acceleration: Vec3,
    /// NED yaw in radians (from north, clockwise); `None` = ignored by the autopilot.
    pub yaw: Option<f64>,
}

/// World ENU → local NED: positions relative to the home, free vectors only re-axed.
pub fn to_ned(home: &Home, r: &EnuReference) -> NedTarget {
    NedTarget {
        position: home.enu_to_ned(&r.position),
        velocity: enu_vector_to_ned(&r.velocity),
        acceleration: enu_vector_to_ned(&r.acceleration),
        yaw: r.yaw.map(enu_yaw_to_ned),
    }
}

/// POSITION_TARGET_TYPEMASK bits (a set bit means "ignore this field").
pub mod mask {
    pub const YAW_IGNORE: u16 = 1024;
    pub const YAW_RATE_IGNORE: u16 = 2048;
    /// Every position, velocity and acceleration bit (1..=256) plus FORCE_SET (512).
    pub const PVA_AND_FORCE: u16 = 0x3FF;
}

/// Position, velocity and acceleration all used (so PX4 feeds them forward); yaw used when
/// given; yaw rate never.
pub fn type_mask(target: &NedTarget) -> u16 {
    let mut m = mask::YAW_RATE_IGNORE;
    if target.yaw.is_none() {
        m |= mask::YAW_IGNORE;
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    fn close(a: &Vec3, b: &Vec3) -> bool {
        (a - b).norm() < 1e-9
    }

    #[test]
    fn north_east_and_up_of_a_non_zero_home_is_plus_north_plus_east_minus_down() {
        // The classic crash: a vehicle whose home is not the world origin is sent to a point
        // north-east of and above its home. Any axis or offset mistake flips a sign here.
        let home = Home::new(Vec3::new(-35.0, 80.0, 2.0));
        let goal = EnuReference {
            position: Vec3::new(-35.0 + 12.0, 80.0 + 7.0, 2.0 + 10.0), // 12 m east, 7 m north, 10 m up
            velocity: Vec3::new(1.0, 2.0, 0.5),                        // east, north, up
            acceleration: Vec3::new(-0.1, 0.2, -0.3),
            yaw: Some(FRAC_PI_2), // facing north
        };
        let ned = to_ned(&home, &goal);
        assert!(
            close(&ned.position, &Vec3::new(7.0, 12.0, -10.0)),
            "{:?}",
            ned.position
        );
        assert!(ned.position.x > 0.0 && ned.position.y > 0.0 && ned.position.z < 0.0);
        assert!(close(&ned.velocity, &Vec3::new(2.0, 1.0, -0.5)));
        assert!(close(&ned.acceleration, &Vec3::new(0.2, -0.1, 0.3)));
        assert!(
            ned.yaw.is_some_and(|y| y.abs() < 1e-12),
            "north is NED yaw 0"
        );
    }

    #[test]
    fn the_home_itself_is_the_ned_origin() {
        let home = Home::new(Vec3::new(60.0, -120.0, 0.0));
        let ned = to_ned(
            &home,
            &EnuReference::hold(Vec3::new(60.0, -120.0, 0.0), None),
        );
        assert!(close(&ned.position, &Vec3::zeros()));
    }

    #[test]
    fn type_mask_uses_pva_and_yaw_only_when_given() {
        let home = Home::new(Vec3::zeros());
        let no_yaw = to_ned(&home, &EnuReference::hold(Vec3::zeros(), None));
        let with_yaw = to_ned(&home, &EnuReference::hold(Vec3::zeros(), Some(0.3)));
        assert_eq!(type_mask(&no_yaw), mask::YAW_IGNORE | mask::YAW_RATE_IGNORE);
        assert_eq!(type_mask(&with_yaw), mask::YAW_RATE_IGNORE);
        assert_eq!(
            type_mask(&with_yaw) & mask::PVA_AND_FORCE,
            0,
            "position, velocity, acceleration all used"
        );
    }
}

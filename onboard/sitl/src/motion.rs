//! The vehicle's body: a point mass whose velocity and acceleration are bounded, driven by a
//! saturated PD law toward a position and/or velocity reference (PX4's position controller in
//! miniature). Pure: no clock, no I/O. All vectors are in the vehicle's local NED frame.

use tacos_shared::Vec3;

/// Fraction of the acceleration limit used when planning to stop at a target, so the velocity
/// loop has some authority left and the vehicle does not overshoot.
const BRAKING_SHARE: f64 = 0.6;
/// Position error → velocity gain (1/s).
const POSITION_GAIN: f64 = 1.2;
/// Velocity error → acceleration gain (1/s).
const VELOCITY_GAIN: f64 = 4.0;

/// PX4's `MPC_Z_VEL_MAX_UP`: the fastest climb (m/s).
pub const MAX_CLIMB_SPEED: f64 = 3.0;
/// PX4's `MPC_Z_VEL_MAX_DN`: the fastest descent (m/s).
pub const MAX_DESCENT_SPEED: f64 = 1.5;

/// The envelope of one vehicle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionLimits {
    /// Bound on the norm of the velocity (m/s).
    pub max_speed: f64,
    /// Bound on the upward speed (m/s; NED z < 0).
    pub max_climb_speed: f64,
    /// Bound on the downward speed (m/s; NED z > 0).
    pub max_descent_speed: f64,
    /// Bound on the norm of the acceleration (m/s²).
    pub max_accel: f64,
}

impl MotionLimits {
    /// The scenario's limits, with PX4's default vertical speeds (3 m/s up, 1.5 m/s down)
    /// within the scenario's speed bound.
    pub fn from_scenario(max_speed: f64, max_accel: f64) -> Self {
        MotionLimits {
            max_speed,
            max_climb_speed: MAX_CLIMB_SPEED.min(max_speed),
            max_descent_speed: MAX_DESCENT_SPEED.min(max_speed),
            max_accel,
        }
    }

    /// The same envelope with the climb capped at `speed` (PX4's `MPC_TKO_SPEED` in take-off).
    pub fn with_climb_at_most(self, speed: f64) -> Self {
        MotionLimits {
            max_climb_speed: self.max_climb_speed.min(speed),
            ..self
        }
    }

    /// Projects a velocity onto the allowed set (a slab in z intersected with a ball). Both
    /// steps are Euclidean projections onto convex sets, so the composition never moves a
    /// velocity farther than the step that produced it: the acceleration bound survives it.
    pub fn clamp_velocity(&self, v: Vec3) -> Vec3 {
        let mut v = v;
        v.z = v.z.clamp(-self.max_climb_speed, self.max_descent_speed);
        clamp_norm(v, self.max_speed)
    }
}

/// What the controller tracks on each axis; `None` = that part of the reference is not given.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Reference {
    pub position: [Option<f64>; 3],
    pub velocity: [Option<f64>; 3],
    pub acceleration: [Option<f64>; 3],
}

impl Reference {
    /// Hold a fixed point.
    pub fn hold(p: Vec3) -> Self {
        Reference {
            position: [Some(p.x), Some(p.y), Some(p.z)],
            ..Reference::default()
        }
    }

    /// Fly at a fixed velocity.
    pub fn velocity(v: Vec3) -> Self {
        Reference {
            velocity: [Some(v.x), Some(v.y), Some(v.z)],
            ..Reference::default()
        }
    }
}

/// Position and velocity of the point mass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointMass {
    pub position: Vec3,
    pub velocity: Vec3,
}

impl PointMass {
    pub fn at_rest(position: Vec3) -> Self {
        PointMass {
            position,
            velocity: Vec3::zeros(),
        }
    }

    /// The acceleration the controller asks for to track `reference`, within the limits.
    pub fn command(&self, reference: &Reference, limits: &MotionLimits) -> Vec3 {
        // Position error on the axes that have a position reference.
        let mut error = Vec3::zeros();
        let mut feed_forward_v = Vec3::zeros();
        let mut feed_forward_a = Vec3::zeros();
        let mut acceleration_only = [false; 3];
        for i in 0..3 {
            if let Some(p) = reference.position[i] {
                error[i] = p - self.position[i];
            }
            feed_forward_v[i] = reference.velocity[i].unwrap_or(0.0);
            feed_forward_a[i] = reference.acceleration[i].unwrap_or(0.0);
            acceleration_only[i] = reference.position[i].is_none()
                && reference.velocity[i].is_none()
                && reference.acceleration[i].is_some();
        }
        // Toward the target at a speed from which it can still stop in time.
        let distance = error.norm();
        let correction = if distance > 1e-9 {
            let stopping = (2.0 * BRAKING_SHARE * limits.max_accel * distance).sqrt();
            error * ((POSITION_GAIN * distance).min(stopping) / distance)
        } else {
            Vec3::zeros()
        };
        let wanted_v = limits.clamp_velocity(feed_forward_v + correction);
        let mut a = Vec3::zeros();
        for i in 0..3 {
            a[i] = if acceleration_only[i] {
                feed_forward_a[i]
            } else {
                VELOCITY_GAIN * (wanted_v[i] - self.velocity[i]) + feed_forward_a[i]
            };
        }
        clamp_norm(a, limits.max_accel)
    }

    /// Advances by `dt` under acceleration `a` (already within the limits), keeping the
    /// velocity inside its envelope.
    pub fn integrate(&mut self, a: Vec3, dt: f64, limits: &MotionLimits) {
        let v = limits.clamp_velocity(self.velocity + a * dt);
        self.position += (self.velocity + v) * (0.5 * dt);
        self.velocity = v;
    }

    /// One controlled step toward `reference`.
    pub fn track(&mut self, reference: &Reference, limits: &MotionLimits, dt: f64) {
        let a = self.command(reference, limits);
        self.integrate(a, dt, limits);
    }
}

/// Scales `v` down so that its norm is at most `max`.
pub fn clamp_norm(v: Vec3, max: f64) -> Vec3 {
    let n = v.norm();
    if n > max && n > 0.0 { v * (max / n) } else { v }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: MotionLimits = MotionLimits {
        max_speed: 5.0,
        max_climb_speed: 3.0,
        max_descent_speed: 1.5,
        max_accel: 3.0,
    };
    const DT: f64 = 0.01;

    #[test]
    fn reaches_a_far_point_without_breaking_the_limits() {
        let mut body = PointMass::at_rest(Vec3::zeros());
        let goal = Vec3::new(40.0, -30.0, -10.0);
        for _ in 0..4000 {
            let before = body.velocity;
            body.track(&Reference::hold(goal), &LIMITS, DT);
            assert!(body.velocity.norm() <= LIMITS.max_speed + 1e-9);
            assert!(body.velocity.z >= -LIMITS.max_climb_speed - 1e-9);
            assert!(body.velocity.z <= LIMITS.max_descent_speed + 1e-9);
            assert!((body.velocity - before).norm() / DT <= LIMITS.max_accel + 1e-9);
        }
        assert!((body.position - goal).norm() < 0.05, "{:?}", body.position);
        assert!(body.velocity.norm() < 0.05);
    }

    #[test]
    fn climbs_faster_than_it_descends() {
        let limits = MotionLimits::from_scenario(8.0, 3.0);
        assert_eq!(
            (limits.max_climb_speed, limits.max_descent_speed),
            (3.0, 1.5)
        );
        let slow = MotionLimits::from_scenario(1.0, 1.0);
        assert_eq!((slow.max_climb_speed, slow.max_descent_speed), (1.0, 1.0));
        let mut body = PointMass::at_rest(Vec3::zeros());
        for _ in 0..500 {
            body.track(&Reference::hold(Vec3::new(0.0, 0.0, -100.0)), &limits, DT);
        }
        assert!((body.velocity.z + 3.0).abs() < 1e-6, "{}", body.velocity.z);
        for _ in 0..1000 {
            body.track(&Reference::hold(Vec3::new(0.0, 0.0, 100.0)), &limits, DT);
        }
        assert!((body.velocity.z - 1.5).abs() < 1e-6, "{}", body.velocity.z);
        let takeoff = limits.with_climb_at_most(1.5);
        assert_eq!((takeoff.max_climb_speed, takeoff.max_speed), (1.5, 8.0));
    }

    #[test]
    fn does_not_overshoot_much() {
        let mut body = PointMass::at_rest(Vec3::zeros());
        let goal = Vec3::new(20.0, 0.0, 0.0);
        let mut farthest: f64 = 0.0;
        for _ in 0..3000 {
            body.track(&Reference::hold(goal), &LIMITS, DT);
            farthest = farthest.max(body.position.x);
        }
        assert!(farthest < goal.x + 0.2, "overshoot to {farthest}");
    }

    #[test]
    fn velocity_reference_is_followed() {
        let mut body = PointMass::at_rest(Vec3::zeros());
        for _ in 0..500 {
            body.track(&Reference::velocity(Vec3::new(1.0, 2.0, 0.0)), &LIMITS, DT);
        }
        assert!((body.velocity - Vec3::new(1.0, 2.0, 0.0)).norm() < 1e-3);
    }

    #[test]
    fn acceleration_only_axis_is_open_loop() {
        let body = PointMass::at_rest(Vec3::zeros());
        let reference = Reference {
            acceleration: [Some(1.0), None, None],
            ..Reference::default()
        };
        let a = body.command(&reference, &LIMITS);
        assert!((a - Vec3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
    }
}

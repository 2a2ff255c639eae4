//! A straight-line, speed- and acceleration-limited reference between two points
//! (trapezoidal speed profile). The distributed planner replaces it for goto; it stays as the
//! fallback shape of simple moves.

use tacos_shared::Vec3;

#[derive(Debug, Clone, PartialEq)]
pub struct StraightLine {
    from: Vec3,
    to: Vec3,
    start: f64,
    distance: f64,
    v_peak: f64,
    accel: f64,
    t_ramp: f64,
    t_cruise: f64,
}

/// Position, velocity and acceleration of the reference at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceState {
    pub position: Vec3,
    pub velocity: Vec3,
    pub acceleration: Vec3,
}

impl StraightLine {
    /// A move from `from` to `to` starting at time `start` (s), at up to `speed` and `accel`.
    pub fn new(from: Vec3, to: Vec3, start: f64, speed: f64, accel: f64) -> Self {
        let distance = (to - from).norm();
        let speed = speed.max(1e-3);
        let accel = accel.max(1e-3);
        // Peak speed: reach `speed` if the distance allows, else a triangle profile.
        let v_peak = speed.min((distance * accel).sqrt());
        let t_ramp = v_peak / accel;
        let ramp_distance = v_peak * t_ramp; // both ramps together
        let t_cruise = if v_peak > 0.0 {
            (distance - ramp_distance).max(0.0) / v_peak
        } else {
            0.0
        };
        StraightLine {
            from,
            to,
            start,
            distance,
            v_peak,
            accel,
            t_ramp,
            t_cruise,
        }
    }

    pub fn target(&self) -> Vec3 {
        self.to
    }

    /// Total time of the move, seconds.
    pub fn duration(&self) -> f64 {
        2.0 * self.t_ramp + self.t_cruise
    }

    pub fn is_finished(&self, now: f64) -> bool {
        now - self.start >= self.duration()
    }

    /// Fraction of the distance covered by the reference at `now`.
    pub fn progress(&self, now: f64) -> f32 {
        if self.distance <= 0.0 {
            return 1.0;
        }
        (self.along(now).0 / self.distance).clamp(0.0, 1.0) as f32
    }

    /// Distance along the line, speed and acceleration at `now`.
    fn along(&self, now: f64) -> (f64, f64, f64) {
        let t = (now - self.start).max(0.0);
        let (a, tr, tc) = (self.accel, self.t_ramp, self.t_cruise);
        if t < tr {
            (0.5 * a * t * t, a * t, a)
        } else if t < tr + tc {
            (0.5 * a * tr * tr + self.v_peak * (t - tr), self.v_peak, 0.0)
        } else if t < 2.0 * tr + tc {
            let td = t - tr - tc;
            (
                0.5 * a * tr * tr + self.v_peak * tc + self.v_peak * td - 0.5 * a * td * td,
                self.v_peak - a * td,
                -a,
            )
        } else {
            (self.distance, 0.0, 0.0)
        }
    }

    pub fn sample(&self, now: f64) -> ReferenceState {
        if self.distance <= 0.0 {
            return ReferenceState {
                position: self.to,
                velocity: Vec3::zeros(),
                acceleration: Vec3::zeros(),
            };
        }
        let dir = (self.to - self.from) / self.distance;
        let (s, v, a) = self.along(now);
        ReferenceState {
            position: self.from + dir * s,
            velocity: dir * v,
            acceleration: dir * a,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn respects_limits_and_arrives() {
        let line = StraightLine::new(Vec3::zeros(), Vec3::new(30.0, 40.0, 0.0), 1.0, 5.0, 2.0);
        let mut last = line.sample(1.0).position;
        let mut t = 1.0;
        while t < 1.0 + line.duration() + 1.0 {
            let s = line.sample(t);
            assert!(s.velocity.norm() <= 5.0 + 1e-9);
            assert!(s.acceleration.norm() <= 2.0 + 1e-9);
            assert!(
                (s.position - last).norm() <= 5.0 * 0.01 + 1e-9,
                "jump at t={t}"
            );
            last = s.position;
            t += 0.01;
        }
        assert!((line.sample(t).position - Vec3::new(30.0, 40.0, 0.0)).norm() < 1e-9);
        assert!(line.is_finished(t));
        assert_eq!(line.progress(t), 1.0);
    }

    #[test]
    fn short_moves_use_a_triangle_profile() {
        let line = StraightLine::new(Vec3::zeros(), Vec3::new(1.0, 0.0, 0.0), 0.0, 10.0, 1.0);
        assert!((line.duration() - 2.0).abs() < 1e-9);
        assert!((line.sample(1.0).position.x - 0.5).abs() < 1e-9);
    }
}

//! A planned trajectory: a double integrator with piecewise-constant acceleration, sampled at
//! `dt`. Sampling between the knots is exact (quadratic in time), so the 50 Hz setpoints follow
//! the same curve the constraints were written for.

use tacos_shared::Vec3;

/// Position, velocity and acceleration of the reference at one instant (world ENU): what is
/// streamed to the writer as a setpoint.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceState {
    pub position: Vec3,
    pub velocity: Vec3,
    pub acceleration: Vec3,
}

impl ReferenceState {
    /// Stand still at `position`.
    pub fn still(position: Vec3) -> Self {
        ReferenceState {
            position,
            velocity: Vec3::zeros(),
            acceleration: Vec3::zeros(),
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// Time of the first knot (the clock the planner was called with), seconds.
    pub start: f64,
    pub dt: f64,
    /// K + 1 positions, the first the state the plan started from.
    pub positions: Vec<Vec3>,
    /// K + 1 velocities.
    pub velocities: Vec<Vec3>,
    /// K accelerations, each held for one step.
    pub accelerations: Vec<Vec3>,
}

impl Plan {
    /// Integrates `accelerations` from (`position`, `velocity`).
    pub fn integrate(
        start: f64,
        dt: f64,
        position: Vec3,
        velocity: Vec3,
        accelerations: Vec<Vec3>,
    ) -> Plan {
        let mut positions = Vec::with_capacity(accelerations.len() + 1);
        let mut velocities = Vec::with_capacity(accelerations.len() + 1);
        let (mut p, mut v) = (position, velocity);
        positions.push(p);
        velocities.push(v);
        for a in &accelerations {
            p += v * dt + a * (0.5 * dt * dt);
            v += a * dt;
            positions.push(p);
            velocities.push(v);
        }
        Plan {
            start,
            dt,
            positions,
            velocities,
            accelerations,
        }
    }

    /// A plan that stays at `position`.
    pub fn hold(start: f64, dt: f64, steps: usize, position: Vec3) -> Plan {
        Plan::integrate(
            start,
            dt,
            position,
            Vec3::zeros(),
            vec![Vec3::zeros(); steps],
        )
    }

    /// Brakes from (`position`, `velocity`) at up to `max_accel` straight against the velocity,
    /// then holds. Each step's deceleration is capped so the speed reaches exactly zero.
    pub fn braking(
        start: f64,
        dt: f64,
        steps: usize,
        position: Vec3,
        velocity: Vec3,
        max_accel: f64,
    ) -> Plan {
        let mut accelerations = Vec::with_capacity(steps);
        let mut v = velocity;
        for _ in 0..steps {
            let speed = v.norm();
            let a = if speed > 1e-12 && dt > 0.0 {
                -v / speed * max_accel.min(speed / dt)
            } else {
                Vec3::zeros()
            };
            v += a * dt;
            accelerations.push(a);
        }
        Plan::integrate(start, dt, position, velocity, accelerations)
    }

    /// Number of steps (K). Robust to inconsistent hand-made plans: the shortest of the three
    /// sequences decides.
    pub fn steps(&self) -> usize {
        self.accelerations
            .len()
            .min(self.positions.len().saturating_sub(1))
            .min(self.velocities.len().saturating_sub(1))
    }

    pub fn end_time(&self) -> f64 {
        self.start + self.dt * self.steps() as f64
    }

    /// The positions to publish on `drone/<id>/path` (K + 1 points at `dt` from `start`).
    pub fn path(&self) -> &[Vec3] {
        &self.positions
    }

    pub fn is_finite(&self) -> bool {
        self.start.is_finite()
            && self.dt.is_finite()
            && [&self.positions, &self.velocities, &self.accelerations]
                .iter()
                .all(|vs| vs.iter().all(|v| v.iter().all(|c| c.is_finite())))
    }

    /// The reference at time `t`: exact on the plan, the first state before it, and a hold at
    /// the last position (zero velocity) after it ends.
    pub fn sample(&self, t: f64) -> ReferenceState {
        let Some(&first) = self.positions.first() else {
            return ReferenceState {
                position: Vec3::zeros(),
                velocity: Vec3::zeros(),
                acceleration: Vec3::zeros(),
            };
        };
        let tau = t - self.start;
        let k_max = self.steps();
        if k_max == 0 || !(tau.is_finite() && self.dt > 0.0) || tau <= 0.0 {
            return ReferenceState {
                position: first,
                velocity: self.velocities.first().copied().unwrap_or_default(),
                acceleration: self.accelerations.first().copied().unwrap_or_default(),
            };
        }
        let k = (tau / self.dt).floor();
        if k >= k_max as f64 {
            return ReferenceState {
                position: self.positions[k_max],
                velocity: Vec3::zeros(),
                acceleration: Vec3::zeros(),
            };
        }
        let k = k as usize;
        let s = tau - k as f64 * self.dt;
        let (p, v, a) = (self.positions[k], self.velocities[k], self.accelerations[k]);
        ReferenceState {
            position: p + v * s + a * (0.5 * s * s),
            velocity: v + a * s,
            acceleration: a,
        }
    }

    /// The Bézier control points of segment `k` (time `[k dt, (k+1) dt]`), whose convex hull
    /// contains the segment: `p_k, p_k + v_k dt/2, p_{k+1}`. Segment 0 is split at `dt/2`
    /// into two quadratic pieces (five points) so that the only points fixed by the current
    /// state are `p_0` and `p_0 + v_0 dt/4`: the planner constrains every other one.
    pub fn control_points(&self, k: usize) -> Vec<Vec3> {
        if k >= self.steps() {
            return Vec::new();
        }
        let dt = self.dt;
        let (p, v, a) = (self.positions[k], self.velocities[k], self.accelerations[k]);
        if k == 0 {
            let h = dt / 2.0;
            let ph = p + v * h + a * (0.5 * h * h);
            vec![
                p,
                p + v * (h / 2.0),
                ph,
                p + v * (1.5 * h) + a * (h * h),
                self.positions[1],
            ]
        } else {
            vec![p, p + v * (dt / 2.0), self.positions[k + 1]]
        }
    }

    /// The control points of segment `k` that a solve places: all but, in segment 0, the two
    /// fixed by the current state (see [`Plan::control_points`]).
    pub fn free_control_points(&self, k: usize) -> Vec<Vec3> {
        let mut points = self.control_points(k);
        if k == 0 {
            points.drain(..2.min(points.len()));
        }
        points
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampling_is_exact_and_continuous() {
        let plan = Plan::integrate(
            10.0,
            0.1,
            Vec3::new(1.0, 2.0, 3.0),
            Vec3::new(1.0, 0.0, 0.0),
            vec![Vec3::new(0.0, 1.0, 0.0), Vec3::new(-1.0, 0.0, 2.0)],
        );
        let s = plan.sample(10.1);
        assert!((s.position - plan.positions[1]).norm() < 1e-12);
        assert!((s.velocity - plan.velocities[1]).norm() < 1e-12);
        // Continuity across the knot.
        let before = plan.sample(10.1 - 1e-9);
        assert!((before.position - s.position).norm() < 1e-8);
        assert!((before.velocity - s.velocity).norm() < 1e-8);
        // After the end: hold.
        let after = plan.sample(11.0);
        assert_eq!(after.position, plan.positions[2]);
        assert_eq!(after.velocity, Vec3::zeros());
        // Before the start: the first state.
        assert_eq!(plan.sample(0.0).position, plan.positions[0]);
    }

    #[test]
    fn control_points_contain_the_segments() {
        let plan = Plan::integrate(
            0.0,
            0.1,
            Vec3::zeros(),
            Vec3::new(5.0, 0.0, 0.0),
            vec![Vec3::new(0.0, 4.0, 0.0), Vec3::new(-4.0, -4.0, 1.0)],
        );
        for k in 0..2 {
            let cps = plan.control_points(k);
            // Every sample of the segment is a convex combination: check against the
            // bounding box of the control points.
            for i in 0..=20 {
                let t = (k as f64 + i as f64 / 20.0) * 0.1;
                let p = plan.sample(t).position;
                for axis in 0..3 {
                    let lo = cps.iter().map(|c| c[axis]).fold(f64::INFINITY, f64::min);
                    let hi = cps
                        .iter()
                        .map(|c| c[axis])
                        .fold(f64::NEG_INFINITY, f64::max);
                    assert!(p[axis] >= lo - 1e-12 && p[axis] <= hi + 1e-12);
                }
            }
        }
    }

    #[test]
    fn braking_stops_within_the_acceleration_limit() {
        let plan = Plan::braking(0.0, 0.1, 30, Vec3::zeros(), Vec3::new(6.0, 8.0, 0.0), 4.0);
        assert!(plan.accelerations.iter().all(|a| a.norm() <= 4.0 + 1e-9));
        assert!(plan.velocities.last().is_some_and(|v| v.norm() < 1e-9));
        // Straight along the initial velocity: 10 m/s at 4 m/s² stops after 12.5 m.
        let end = plan.positions[30];
        assert!((end.norm() - 12.5).abs() < 0.5, "{end:?}");
        assert!((end.normalize() - Vec3::new(0.6, 0.8, 0.0)).norm() < 1e-9);
    }
}

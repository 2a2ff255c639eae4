//! The target tracker: a constant-velocity Kalman filter per followed target, fed by
//! `world/targets`, giving the planner a moving goal. When observations stop the track coasts
//! on its prediction for a configured time, then the target is reported lost.

use nalgebra::{Matrix3, Matrix6, Vector6};
use tacos_shared::{DroneId, Vec3};

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerConfig {
    /// Standard deviation of the target's unmodelled acceleration, m/s².
    pub accel_noise: f64,
    /// Standard deviation of a position observation, m.
    pub position_noise: f64,
    /// Standard deviation of a velocity observation, m/s.
    pub velocity_noise: f64,
    /// How long the track coasts without observations before the target counts as lost, s.
    pub coast_s: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            accel_noise: 1.0,
            position_noise: 0.5,
            velocity_noise: 0.5,
            coast_s: 3.0,
        }
    }
}

/// The filter's estimate of one target.
#[derive(Debug, Clone, PartialEq)]
pub struct Track {
    cfg: TrackerConfig,
    /// State [p; v] at time `t`.
    x: Vector6<f64>,
    p: Matrix6<f64>,
    t: f64,
    last_observed: f64,
}

fn transition(dt: f64) -> Matrix6<f64> {
    let mut f = Matrix6::identity();
    for i in 0..3 {
        f[(i, i + 3)] = dt;
    }
    f
}

/// White-acceleration process noise for a step of `dt`.
fn process_noise(dt: f64, sigma_a: f64) -> Matrix6<f64> {
    let q = sigma_a * sigma_a;
    let (dt2, dt3, dt4) = (dt * dt, dt * dt * dt, dt * dt * dt * dt);
    let mut m = Matrix6::zeros();
    for i in 0..3 {
        m[(i, i)] = dt4 / 4.0 * q;
        m[(i, i + 3)] = dt3 / 2.0 * q;
        m[(i + 3, i)] = dt3 / 2.0 * q;
        m[(i + 3, i + 3)] = dt2 * q;
    }
    m
}

impl Track {
    /// Starts a track at the first observation.
    pub fn new(cfg: TrackerConfig, position: Vec3, velocity: Vec3, now: f64) -> Track {
        let mut x = Vector6::zeros();
        x.fixed_rows_mut::<3>(0).copy_from(&position);
        x.fixed_rows_mut::<3>(3).copy_from(&velocity);
        let mut p = Matrix6::identity();
        p.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(Matrix3::identity() * cfg.position_noise.powi(2)));
        p.fixed_view_mut::<3, 3>(3, 3)
            .copy_from(&(Matrix3::identity() * cfg.velocity_noise.powi(2)));
        Track {
            cfg,
            x,
            p,
            t: now,
            last_observed: now,
        }
    }

    fn predict_to(&mut self, now: f64) {
        let dt = now - self.t;
        if dt <= 0.0 {
            return;
        }
        let f = transition(dt);
        self.x = f * self.x;
        self.p = f * self.p * f.transpose() + process_noise(dt, self.cfg.accel_noise);
        self.t = now;
    }

    /// Fuses an observation of position and velocity made at `now`.
    pub fn observe(&mut self, position: Vec3, velocity: Vec3, now: f64) {
        if !(tacos_shared::geometry::is_finite(&position)
            && tacos_shared::geometry::is_finite(&velocity))
        {
            return;
        }
        self.predict_to(now);
        let mut z = Vector6::zeros();
        z.fixed_rows_mut::<3>(0).copy_from(&position);
        z.fixed_rows_mut::<3>(3).copy_from(&velocity);
        let mut r = Matrix6::zeros();
        for i in 0..3 {
            r[(i, i)] = self.cfg.position_noise.powi(2);
            r[(i + 3, i + 3)] = self.cfg.velocity_noise.powi(2);
        }
        // H = I: the innovation covariance is P + R.
        let Some(s_inv) = (self.p + r).try_inverse() else {
            return;
        };
        let k = self.p * s_inv;
        self.x += k * (z - self.x);
        self.p = (Matrix6::identity() - k) * self.p;
        self.p = 0.5 * (self.p + self.p.transpose());
        self.last_observed = self.last_observed.max(now);
    }

    /// Predicted position and velocity at `at` (no state change).
    pub fn predict(&self, at: f64) -> (Vec3, Vec3) {
        let x = transition((at - self.t).max(0.0)) * self.x;
        (
            x.fixed_rows::<3>(0).into_owned(),
            x.fixed_rows::<3>(3).into_owned(),
        )
    }

    pub fn silence(&self, now: f64) -> f64 {
        (now - self.last_observed).max(0.0)
    }

    /// True once the target has not been observed for longer than the coast time.
    pub fn lost(&self, now: f64) -> bool {
        self.silence(now) > self.cfg.coast_s
    }
}

/// Where this drone holds relative to the target: trackers of one target spread evenly on a
/// circle of `radius` (sorted by id, so every drone computes the same assignment), at `altitude`.
pub fn tracking_offset(me: &DroneId, trackers: &[DroneId], radius: f64, altitude: f64) -> Vec3 {
    let mut all: Vec<&DroneId> = trackers.iter().chain(std::iter::once(me)).collect();
    all.sort();
    all.dedup();
    let n = all.len().max(1);
    let i = all.iter().position(|d| *d == me).unwrap_or(0);
    let angle = std::f64::consts::TAU * i as f64 / n as f64;
    Vec3::new(radius * angle.cos(), radius * angle.sin(), altitude)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_constant_velocity_target_is_tracked_with_a_settling_error() {
        // Observations at 10 Hz with deterministic noise of ±0.5 m and ±0.4 m/s.
        let truth = |t: f64| {
            (
                Vec3::new(-60.0 + 3.0 * t, -40.0 + 1.0 * t, 0.0),
                Vec3::new(3.0, 1.0, 0.0),
            )
        };
        let noise = |k: usize| ((k as f64 * 12.9898).sin() * 43758.5453).rem_euclid(1.0) - 0.5;
        let (p0, v0) = truth(0.0);
        let mut track = Track::new(
            TrackerConfig::default(),
            p0 + Vec3::new(2.0, -2.0, 0.0),
            Vec3::zeros(),
            0.0,
        );
        let mut errors = Vec::new();
        for k in 1..300 {
            let t = k as f64 * 0.1;
            let (p, v) = truth(t);
            track.observe(
                p + Vec3::new(noise(k), noise(k + 7), 0.0),
                v + Vec3::new(0.8 * noise(k + 3), 0.8 * noise(k + 5), 0.0),
                t,
            );
            let (est, _) = track.predict(t);
            errors.push((est - p).norm());
        }
        let late = errors[200..].iter().cloned().fold(0.0, f64::max);
        assert!(errors[0] > late, "the error did not shrink");
        assert!(late < 0.6, "late error {late:.2} m");
        let _ = v0;
        // Prediction ahead follows the velocity.
        let (ahead, vel) = track.predict(31.0);
        assert!(
            (ahead - truth(31.0).0).norm() < 1.0 && (vel - Vec3::new(3.0, 1.0, 0.0)).norm() < 0.3
        );
    }

    #[test]
    fn coasts_then_reports_the_target_lost() {
        let mut track = Track::new(
            TrackerConfig {
                coast_s: 2.0,
                ..TrackerConfig::default()
            },
            Vec3::zeros(),
            Vec3::new(1.0, 0.0, 0.0),
            0.0,
        );
        track.observe(Vec3::new(0.1, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), 0.1);
        assert!(!track.lost(2.0));
        assert!(track.lost(2.2));
        let (p, _) = track.predict(2.1);
        assert!(
            (p.x - 2.1).abs() < 0.3,
            "coasting follows the last velocity: {p:?}"
        );
    }

    #[test]
    fn several_trackers_take_distinct_places() {
        let ids: Vec<DroneId> = ["alfa", "bravo", "charlie"]
            .iter()
            .map(|d| DroneId::new(*d).expect("valid"))
            .collect();
        let offsets: Vec<Vec3> = ids
            .iter()
            .map(|me| tracking_offset(me, &ids, 8.0, 10.0))
            .collect();
        for i in 0..3 {
            assert!((offsets[i].xy().norm() - 8.0).abs() < 1e-9);
            for j in i + 1..3 {
                assert!(
                    (offsets[i] - offsets[j]).norm() > 8.0,
                    "{i} and {j} too close"
                );
            }
        }
        // A lone tracker takes the first place whatever its id.
        assert_eq!(
            tracking_offset(&ids[2], &[], 8.0, 10.0),
            Vec3::new(8.0, 0.0, 10.0)
        );
    }
}

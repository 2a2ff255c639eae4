//! How far the vehicle strays from the plan it is flying: the autopilot's tracking error, kept as
//! a peak that decays, so the planner's separation margin covers the vehicle it actually has.
//!
//! Why: the margin for the tracking error was a fixed sixth of the safety distance (0.1 m in the
//! lab). PX4 SIH's position control strays 0.2–0.4 m from its setpoints (its flight logs:
//! `trajectory_setpoint` against `vehicle_local_position`), and the lab's drones, whose pads are
//! 1 m apart, came within 0.59 m of each other (safety distance 0.6 m) in 2 of 3 runs.

/// A decaying peak of the distance between the vehicle and its plan, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackingError {
    peak: f64,
    at: f64,
    half_life_s: f64,
}

impl TrackingError {
    /// Nothing seen yet; a peak halves every `half_life_s` seconds.
    pub fn new(half_life_s: f64) -> TrackingError {
        TrackingError {
            peak: 0.0,
            at: 0.0,
            half_life_s,
        }
    }

    /// The vehicle was `error` metres from its plan at `now`. A non-finite error is ignored.
    pub fn observe(&mut self, now: f64, error: f64) {
        if !error.is_finite() || !now.is_finite() {
            return;
        }
        self.peak = self.value(now).max(error);
        self.at = now;
    }

    /// The peak as it stands at `now`.
    pub fn value(&self, now: f64) -> f64 {
        let age = (now - self.at).max(0.0);
        if self.half_life_s <= 0.0 {
            return self.peak;
        }
        self.peak * 0.5f64.powf(age / self.half_life_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_peak_holds_then_decays_by_half_each_half_life() {
        let mut e = TrackingError::new(4.0);
        assert_eq!(e.value(0.0), 0.0);
        e.observe(1.0, 0.4);
        e.observe(1.1, 0.1);
        assert!((e.value(1.1) - 0.4 * 0.5f64.powf(0.1 / 4.0)).abs() < 1e-12);
        assert!((e.value(5.0) - 0.2).abs() < 1e-12);
        // A larger error takes over at once; a NaN changes nothing.
        e.observe(5.0, 0.5);
        e.observe(5.0, f64::NAN);
        assert_eq!(e.value(5.0), 0.5);
        // A clock that steps back does not make the peak grow.
        assert_eq!(e.value(4.0), 0.5);
    }
}

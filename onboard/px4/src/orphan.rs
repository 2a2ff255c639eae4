//! When the writer lands the vehicle on its own: its onboard (the planner) has been silent for
//! longer than a bound while the vehicle flies. The writer first holds at the last setpoint
//! (`reference`), which covers an onboard being restarted; an onboard that does not come back
//! within the bound leaves a vehicle nobody steers, so it is landed. PX4's own offboard-loss
//! failsafe covers the writer's death. Pure: the clock is passed in.

use std::time::{Duration, Instant};

#[derive(Debug, Clone, PartialEq)]
pub struct OrphanLanding {
    land_after: Duration,
    /// The silence (identified by the last setpoint's arrival) a landing was asked for, so one
    /// silence asks once.
    landed_silence: Option<Instant>,
}

impl OrphanLanding {
    pub fn new(land_after: Duration) -> Self {
        OrphanLanding {
            land_after,
            landed_silence: None,
        }
    }

    /// True once per silence: the last setpoint came at `last_setpoint`, longer than the bound
    /// ago, and the vehicle is `flying` (armed and not already landing). Before any setpoint
    /// there is no onboard to have lost, and nothing is done.
    pub fn poll(&mut self, last_setpoint: Option<Instant>, flying: bool, now: Instant) -> bool {
        let Some(last) = last_setpoint else {
            return false;
        };
        let silent = now.saturating_duration_since(last) >= self.land_after;
        if !silent || !flying || self.landed_silence == Some(last) {
            return false;
        }
        self.landed_silence = Some(last);
        true
    }

    pub fn land_after(&self) -> Duration {
        self.land_after
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_vehicle_is_landed_once_per_silence_longer_than_the_bound_and_only_while_flying() {
        let t0 = Instant::now();
        let s = |secs: f64| t0 + Duration::from_secs_f64(secs);
        let mut o = OrphanLanding::new(Duration::from_secs(15));
        assert!(
            !o.poll(None, true, s(100.0)),
            "no onboard ever: nothing to lose"
        );
        assert!(
            !o.poll(Some(s(0.0)), true, s(14.9)),
            "within the bound: the hold covers it"
        );
        assert!(
            !o.poll(Some(s(0.0)), false, s(20.0)),
            "on the ground: nothing to land"
        );
        assert!(o.poll(Some(s(0.0)), true, s(20.0)));
        assert!(
            !o.poll(Some(s(0.0)), true, s(21.0)),
            "asked once per silence"
        );
        // The onboard came back (a new setpoint) and went silent again: a new silence.
        assert!(!o.poll(Some(s(30.0)), true, s(40.0)));
        assert!(o.poll(Some(s(30.0)), true, s(45.0)));
    }
}

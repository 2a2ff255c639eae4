//! The ground-silence failsafe: hold after a first silence, land after a longer one.

use tacos_shared::messages::FailsafeStage;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FailsafeTimer {
    hold_after: f64,
    land_after: f64,
    last_heard: f64,
}

impl FailsafeTimer {
    /// Silence is counted from `now` until the ground is first heard.
    pub fn new(hold_after: f64, land_after: f64, now: f64) -> Self {
        FailsafeTimer {
            hold_after,
            land_after: land_after.max(hold_after),
            last_heard: now,
        }
    }

    pub fn heard(&mut self, now: f64) {
        self.last_heard = self.last_heard.max(now);
    }

    /// `deaf_s` seconds this process could not listen (a stall: `crate::stall`) are not silence:
    /// the silence counted so far is kept, the stall's time is left out of it.
    pub fn excuse(&mut self, deaf_s: f64, now: f64) {
        if deaf_s.is_finite() && deaf_s > 0.0 {
            self.last_heard = (self.last_heard + deaf_s).min(now);
        }
    }

    pub fn silence(&self, now: f64) -> f64 {
        (now - self.last_heard).max(0.0)
    }

    pub fn stage(&self, now: f64) -> Option<FailsafeStage> {
        let silence = self.silence(now);
        if silence >= self.land_after {
            Some(FailsafeStage::Landing)
        } else if silence >= self.hold_after {
            Some(FailsafeStage::Holding)
        } else {
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escalates_with_silence_and_clears_when_heard() {
        let mut t = FailsafeTimer::new(3.0, 10.0, 0.0);
        assert_eq!(t.stage(2.9), None);
        assert_eq!(t.stage(3.0), Some(FailsafeStage::Holding));
        assert_eq!(t.stage(10.0), Some(FailsafeStage::Landing));
        t.heard(10.5);
        assert_eq!(t.stage(11.0), None);
    }

    #[test]
    fn a_stall_of_this_process_is_not_counted_as_silence() {
        let mut t = FailsafeTimer::new(3.0, 10.0, 0.0);
        // Heard at 1, then 2 s of silence, then 13 s deaf, resuming at 16.
        t.heard(1.0);
        t.excuse(13.0, 16.0);
        assert_eq!(t.silence(16.0), 2.0, "the 2 s before the stall still count");
        assert_eq!(t.stage(16.5), None);
        assert_eq!(t.stage(17.0), Some(FailsafeStage::Holding), "3 s listened");
        t.excuse(100.0, 17.0);
        assert_eq!(t.silence(17.0), 0.0, "never heard in the future");
        t.excuse(f64::NAN, 18.0);
        assert_eq!(t.silence(18.0), 1.0);
    }
}

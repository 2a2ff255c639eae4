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
}

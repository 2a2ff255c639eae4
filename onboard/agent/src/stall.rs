//! This process's own stalls, seen from its control ticks.
//!
//! On a loaded companion computer (or 20 onboards on two cores) the whole process can be
//! descheduled for seconds: no tick runs, and no heartbeat or path is taken in, although the
//! ground and the neighbours went on publishing. The silences the failsafes judge must not
//! count that time, or every drone would hold (or land) on resuming because it was not
//! listening. [`StallWatch`] measures the time lost between two ticks; the shell excuses it from
//! the ground's and the peers' silence (`FailsafeTimer::excuse`, `Motion::excuse_peers`).

/// The control ticks' spacing, to tell a stall from a tick that is merely late.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StallWatch {
    period: f64,
    /// A gap longer than this between two ticks is a stall.
    stall_after: f64,
    last_tick: Option<f64>,
}

impl StallWatch {
    /// `period` is the control ticks' nominal spacing; a gap over `stall_after` is a stall.
    pub fn new(period: f64, stall_after: f64) -> Self {
        StallWatch {
            period,
            stall_after: stall_after.max(period),
            last_tick: None,
        }
    }

    /// A tick at `now`: the time this process was deaf since the last tick (the gap beyond the
    /// nominal period), when the gap was a stall. A clock that went back is no stall.
    pub fn tick(&mut self, now: f64) -> Option<f64> {
        let previous = self.last_tick.replace(now)?;
        let gap = now - previous;
        (gap > self.stall_after).then_some(gap - self.period)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_gap_over_the_bound_is_a_stall_of_the_time_beyond_one_period() {
        let mut watch = StallWatch::new(0.02, 0.25);
        assert_eq!(
            watch.tick(100.0),
            None,
            "the first tick has nothing to compare"
        );
        assert_eq!(watch.tick(100.02), None);
        assert_eq!(watch.tick(100.2), None, "late, not stalled");
        let deaf = watch.tick(113.2).map(|s| (s * 1e6).round() / 1e6);
        assert_eq!(deaf, Some(12.98), "13 s without a tick, less the period");
        assert_eq!(watch.tick(113.22), None);
        assert_eq!(watch.tick(110.0), None, "a clock set back is no stall");
    }
}

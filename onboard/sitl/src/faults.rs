//! Fault injection: the scenario's scripted faults, and what a fault does to a vehicle's link.

use tacos_shared::scenario::{FaultKind, FaultSpec};

/// A human-readable name for a fault, as `WorldEvent::FaultInjected` carries it.
pub fn describe(kind: &FaultKind) -> String {
    match kind {
        FaultKind::VehicleDies => "vehicle dies".to_owned(),
        FaultKind::LinkDrops { duration_s } => format!("MAVLink link drops for {duration_s:.1} s"),
    }
}

/// The scenario's faults not yet injected, soonest first.
#[derive(Debug, Clone, Default)]
pub struct FaultSchedule {
    pending: Vec<FaultSpec>,
}

impl FaultSchedule {
    pub fn new(faults: &[FaultSpec]) -> Self {
        let mut pending = faults.to_vec();
        // Latest first, so the due ones pop off the end.
        pending.sort_by(|a, b| b.at_s.total_cmp(&a.at_s));
        FaultSchedule { pending }
    }

    /// Removes and returns the faults due at `time` (seconds since the start).
    pub fn due(&mut self, time: f64) -> Vec<FaultSpec> {
        let mut due = Vec::new();
        while self.pending.last().is_some_and(|f| f.at_s <= time) {
            due.extend(self.pending.pop());
        }
        due
    }
}

/// The faults in force on one vehicle's link.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LinkFaults {
    dead: bool,
    down_until: Option<f64>,
}

impl LinkFaults {
    /// Applies `kind` at `now`; overlapping link drops extend each other.
    pub fn apply(&mut self, kind: &FaultKind, now: f64) {
        match kind {
            FaultKind::VehicleDies => self.dead = true,
            FaultKind::LinkDrops { duration_s } => {
                let until = now + duration_s.max(0.0);
                self.down_until = Some(self.down_until.map_or(until, |t| t.max(until)));
            }
        }
    }

    /// True when MAVLink passes in both directions.
    pub fn link_up(&self, now: f64) -> bool {
        !self.dead && !self.dropped(now)
    }

    /// True while a link drop is in force (whether or not the vehicle is alive).
    pub fn dropped(&self, now: f64) -> bool {
        self.down_until.is_some_and(|t| now < t)
    }

    pub fn dead(&self) -> bool {
        self.dead
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(at_s: f64, kind: FaultKind) -> FaultSpec {
        FaultSpec {
            at_s,
            drone: "alfa".into(),
            kind,
        }
    }

    #[test]
    fn schedule_releases_faults_in_time_order() {
        let mut s = FaultSchedule::new(&[
            spec(20.0, FaultKind::VehicleDies),
            spec(5.0, FaultKind::LinkDrops { duration_s: 3.0 }),
        ]);
        assert!(s.due(4.9).is_empty());
        assert_eq!(
            s.due(5.0),
            vec![spec(5.0, FaultKind::LinkDrops { duration_s: 3.0 })]
        );
        assert!(s.due(19.0).is_empty());
        assert_eq!(s.due(100.0).len(), 1);
        assert!(s.due(200.0).is_empty());
    }

    #[test]
    fn link_drops_end_and_death_does_not() {
        let mut l = LinkFaults::default();
        assert!(l.link_up(0.0));
        l.apply(&FaultKind::LinkDrops { duration_s: 2.0 }, 1.0);
        l.apply(&FaultKind::LinkDrops { duration_s: 0.5 }, 1.5);
        assert!(!l.link_up(2.9) && l.dropped(2.9));
        assert!(l.link_up(3.0));
        l.apply(&FaultKind::VehicleDies, 4.0);
        assert!(!l.link_up(100.0) && l.dead() && !l.dropped(100.0));
    }
}

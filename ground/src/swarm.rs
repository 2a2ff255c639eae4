//! The swarm view: what the ground knows of every drone, from status messages and liveliness.
//!
//! Pure state; `link` feeds it. Times are passed in so the view can be tested without clocks.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;
use tacos_shared::messages::DroneStatus;
use tacos_shared::{DroneId, DroneMode};

/// A status older than this makes the drone's link "stale".
pub const STALE_AFTER_S: f64 = 1.0;

#[derive(Debug, Clone)]
pub struct DroneEntry {
    pub id: DroneId,
    /// The drone's liveliness token is present.
    pub alive: bool,
    pub status: Option<DroneStatus>,
    pub last_status_at: Option<Instant>,
    /// When the token disappeared, if it did.
    pub gone_at: Option<Instant>,
}

/// A status that a mission can use: the autopilot is linked, the drone not unavailable, and
/// TACOS, not PX4, flies it.
fn usable(status: &DroneStatus) -> bool {
    status.autopilot_link && status.mode != DroneMode::Unavailable && status.flown_by_tacos()
}

impl DroneEntry {
    /// In the swarm as the membership changes count it: its token present and its last
    /// report usable (a drone heard only by its token counts too).
    pub fn present(&self) -> bool {
        self.alive && self.status.as_ref().is_none_or(usable)
    }

    /// Seconds since the last status, if any arrived.
    pub fn link_age(&self, now: Instant) -> Option<f64> {
        self.last_status_at
            .map(|t| now.saturating_duration_since(t).as_secs_f64())
    }

    /// True while the drone reports an action that has not finished.
    pub fn busy(&self) -> bool {
        self.status
            .as_ref()
            .and_then(|s| s.action.as_ref())
            .is_some_and(|p| !p.state.is_finished())
    }

    /// True when the drone can take a new action now: available and not busy with one.
    pub fn ready(&self, now: Instant) -> bool {
        self.effective_mode(now) != DroneMode::Unavailable && !self.busy()
    }

    /// The mode the ground should assume: unavailable when gone or stale, or while PX4 flies it
    /// out of offboard (only hold and land, which take it back, may be sent then).
    pub fn effective_mode(&self, now: Instant) -> DroneMode {
        match (&self.status, self.link_age(now)) {
            (Some(status), Some(age))
                if self.alive && age <= STALE_AFTER_S && status.flown_by_tacos() =>
            {
                status.mode
            }
            _ => DroneMode::Unavailable,
        }
    }
}

/// What changed, for whoever watches the view.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum SwarmChange {
    Joined(DroneId),
    Left(DroneId),
    Status(DroneId),
}

/// The membership changes that take `known` to `now`: for a watcher that missed some (a lagging
/// channel), the difference is what it must act on.
pub fn membership_diff(known: &BTreeSet<DroneId>, now: &BTreeSet<DroneId>) -> Vec<SwarmChange> {
    let left = known.difference(now).cloned().map(SwarmChange::Left);
    let joined = now.difference(known).cloned().map(SwarmChange::Joined);
    left.chain(joined).collect()
}

#[derive(Debug, Default, Clone)]
pub struct SwarmView {
    drones: BTreeMap<DroneId, DroneEntry>,
}

impl SwarmView {
    fn entry(&mut self, id: &DroneId) -> &mut DroneEntry {
        self.drones.entry(id.clone()).or_insert_with(|| DroneEntry {
            id: id.clone(),
            alive: false,
            status: None,
            last_status_at: None,
            gone_at: None,
        })
    }

    /// A drone whose own report turns unusable (its autopilot died or its link to it broke,
    /// while its onboard process still runs) has left the swarm as far as missions go, and
    /// joins again when the report recovers: the same changes as its liveliness token's.
    pub fn apply_status(&mut self, status: DroneStatus, now: Instant) -> SwarmChange {
        let id = status.drone.clone();
        let entry = self.entry(&id);
        let before = entry.status.as_ref().map(usable);
        let after = usable(&status);
        // A status can arrive just before the liveliness token; it proves the drone is there.
        entry.alive = true;
        entry.gone_at = None;
        entry.status = Some(status);
        entry.last_status_at = Some(now);
        match (before, after) {
            (Some(true), false) => SwarmChange::Left(id),
            (Some(false), true) => SwarmChange::Joined(id),
            _ => SwarmChange::Status(id),
        }
    }

    pub fn apply_liveliness(
        &mut self,
        id: &DroneId,
        alive: bool,
        now: Instant,
    ) -> Option<SwarmChange> {
        let entry = self.entry(id);
        if entry.alive == alive {
            return None;
        }
        entry.alive = alive;
        if alive {
            entry.gone_at = None;
            Some(SwarmChange::Joined(id.clone()))
        } else {
            entry.gone_at = Some(now);
            Some(SwarmChange::Left(id.clone()))
        }
    }

    /// A view of these entries (a replayed mission trace's snapshot: `mission::core::trace`).
    pub fn from_entries(entries: impl IntoIterator<Item = DroneEntry>) -> SwarmView {
        SwarmView {
            drones: entries.into_iter().map(|e| (e.id.clone(), e)).collect(),
        }
    }

    pub fn get(&self, id: &DroneId) -> Option<&DroneEntry> {
        self.drones.get(id)
    }

    pub fn drones(&self) -> impl Iterator<Item = &DroneEntry> {
        self.drones.values()
    }

    /// The drones present now ([`DroneEntry::present`]).
    pub fn present_ids(&self) -> BTreeSet<DroneId> {
        self.drones
            .values()
            .filter(|e| e.present())
            .map(|e| e.id.clone())
            .collect()
    }

    pub fn alive_ids(&self) -> Vec<DroneId> {
        self.drones
            .values()
            .filter(|d| d.alive)
            .map(|d| d.id.clone())
            .collect()
    }
}

/// A drone's status as the ground's unit tests build it: in `mode`, armed when airborne, linked
/// to its autopilot, at (-50, -130, 10) of the city, with no action.
#[cfg(test)]
pub(crate) fn test_status(id: &str, mode: DroneMode) -> DroneStatus {
    DroneStatus {
        drone: DroneId::new(id).expect("valid"),
        counter: 1,
        mode,
        armed: mode.is_airborne(),
        position: tacos_shared::Vec3::new(-50.0, -130.0, 10.0),
        velocity: tacos_shared::Vec3::zeros(),
        autopilot_link: true,
        action: None,
        failsafe: None,
        peers_silent: false,
        malformed_actions: 0,
        ground: None,
        refused: None,
        autopilot_took_over: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn status(id: &str) -> DroneStatus {
        test_status(id, DroneMode::Flying)
    }

    #[test]
    fn a_watcher_that_missed_changes_gets_them_from_the_view() {
        let t0 = Instant::now();
        let mut view = SwarmView::default();
        let [alfa, bravo, charlie] =
            ["alfa", "bravo", "charlie"].map(|d| DroneId::new(d).expect("valid"));
        for id in [&alfa, &bravo] {
            view.apply_liveliness(id, true, t0);
            view.apply_status(status(id.as_str()), t0);
        }
        let known = view.present_ids();
        // Missed: bravo's autopilot died, charlie joined, alfa's token went and came back.
        view.apply_status(
            DroneStatus {
                mode: DroneMode::Unavailable,
                autopilot_link: false,
                ..status("bravo")
            },
            t0,
        );
        view.apply_liveliness(&charlie, true, t0);
        view.apply_liveliness(&alfa, false, t0);
        view.apply_liveliness(&alfa, true, t0);
        assert_eq!(
            membership_diff(&known, &view.present_ids()),
            [SwarmChange::Left(bravo), SwarmChange::Joined(charlie)]
        );
    }

    #[test]
    fn stale_or_gone_drones_are_unavailable() {
        let t0 = Instant::now();
        let mut view = SwarmView::default();
        let alfa = DroneId::new("alfa").expect("valid");
        assert_eq!(
            view.apply_liveliness(&alfa, true, t0),
            Some(SwarmChange::Joined(alfa.clone()))
        );
        view.apply_status(status("alfa"), t0);
        let entry = view.get(&alfa).expect("known");
        assert_eq!(
            entry.effective_mode(t0 + Duration::from_millis(500)),
            DroneMode::Flying
        );
        assert_eq!(
            entry.effective_mode(t0 + Duration::from_millis(1500)),
            DroneMode::Unavailable
        );
        assert_eq!(
            view.apply_liveliness(&alfa, false, t0),
            Some(SwarmChange::Left(alfa.clone()))
        );
        assert_eq!(
            view.get(&alfa).expect("known").effective_mode(t0),
            DroneMode::Unavailable
        );
        assert!(view.alive_ids().is_empty());
    }

    #[test]
    fn a_drone_whose_autopilot_dies_leaves_and_rejoins_when_it_recovers() {
        let t0 = Instant::now();
        let mut view = SwarmView::default();
        let alfa = DroneId::new("alfa").expect("valid");
        let dead = DroneStatus {
            mode: DroneMode::Unavailable,
            autopilot_link: false,
            ..status("alfa")
        };
        // Booting without an autopilot, then up: one join.
        assert_eq!(
            view.apply_status(dead.clone(), t0),
            SwarmChange::Status(alfa.clone())
        );
        assert_eq!(
            view.apply_status(status("alfa"), t0),
            SwarmChange::Joined(alfa.clone())
        );
        assert_eq!(
            view.apply_status(status("alfa"), t0),
            SwarmChange::Status(alfa.clone())
        );
        assert_eq!(
            view.apply_status(dead.clone(), t0),
            SwarmChange::Left(alfa.clone())
        );
        assert_eq!(
            view.apply_status(dead, t0),
            SwarmChange::Status(alfa.clone())
        );
        assert_eq!(
            view.apply_status(status("alfa"), t0),
            SwarmChange::Joined(alfa)
        );
    }

    #[test]
    fn a_drone_px4_flies_out_of_offboard_leaves_missions_and_rejoins_when_it_is_back() {
        let t0 = Instant::now();
        let mut view = SwarmView::default();
        let alfa = DroneId::new("alfa").expect("valid");
        let taken = DroneStatus {
            autopilot_took_over: Some(tacos_shared::px4_mode::Px4Mode::Hold),
            ..status("alfa")
        };
        view.apply_liveliness(&alfa, true, t0);
        view.apply_status(status("alfa"), t0);
        assert_eq!(
            view.apply_status(taken, t0),
            SwarmChange::Left(alfa.clone())
        );
        assert!(view.present_ids().is_empty());
        assert_eq!(
            view.get(&alfa).expect("known").effective_mode(t0),
            DroneMode::Unavailable
        );
        assert_eq!(
            view.apply_status(status("alfa"), t0),
            SwarmChange::Joined(alfa.clone())
        );
        assert_eq!(
            view.get(&alfa).expect("known").effective_mode(t0),
            DroneMode::Flying
        );
    }
}

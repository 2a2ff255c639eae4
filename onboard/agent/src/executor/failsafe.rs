//! The executor's failsafes: what a silent ground station, or neighbours that have all fallen
//! silent, make an airborne drone do, and which actions are still taken meanwhile.

use super::{Executor, Task};
use tacos_shared::action::Action;
use tacos_shared::messages::{FailsafeStage, FailureReason};

impl Executor {
    /// Sets the failsafe's stage (`None` = the ground is heard again) and makes the task what
    /// the stage asks for, whatever happened before: called every tick, it acts on the state,
    /// not on changes of stage, so a drone that is airborne while the ground has been silent
    /// past a bound (it took off after the stage was set, or a task replaced the hold) holds or
    /// lands all the same. Holding allows a landing; landing allows nothing else. A drone PX4
    /// flies is left to PX4 (`left_to_px4`).
    pub fn set_failsafe(&mut self, stage: Option<FailsafeStage>, now: f64) {
        self.failsafe = stage;
        let Some(stage) = stage else { return };
        if !self.airborne() || self.left_to_px4() {
            return;
        }
        let landing = matches!(self.task, Task::Land { .. });
        match stage {
            FailsafeStage::Holding if !landing && !matches!(self.task, Task::Hold) => {
                self.fail_and_hold_here("ground silent: holding");
            }
            FailsafeStage::Landing if !landing => {
                self.fail(FailureReason::Failsafe("ground silent: landing".into()));
                self.start_landing(now);
            }
            _ => {}
        }
    }

    /// Whether none of the neighbours this drone knows has been heard for the bound (the
    /// runtime judges it from `Motion::peers_silence`). An airborne drone then stops where it
    /// is and holds there through the planner, which keeps every neighbour where it was last
    /// heard (with a margin growing with the silence): flying on, it would cross airspace the
    /// others may have entered since. Like the ground's failsafe it acts on the state, every
    /// tick, and a landing goes on. When a neighbour is heard again the drone stays in its
    /// hold until the ground gives it work. A drone PX4 flies is left to PX4 (`left_to_px4`).
    pub fn set_peers_silent(&mut self, silent: bool) {
        self.peers_silent = silent;
        if !silent || !self.airborne() || self.left_to_px4() {
            return;
        }
        if !matches!(self.task, Task::Land { .. } | Task::Hold) {
            self.fail_and_hold_here("no neighbour heard: holding where it is");
        }
    }

    /// Whether the failsafes leave the drone to PX4: PX4 flies it out of offboard, unasked (an
    /// RC pilot's switch, another ground station, PX4's own failsafe or geofence). Taking it
    /// back into offboard, or commanding a landing, would override that decision; PX4 applies
    /// its own link-loss failsafes. An action from the pilot (hold, land) still takes it back.
    fn left_to_px4(&self) -> bool {
        self.took_over.is_some()
    }

    /// Fails the action for a failsafe and holds where the vehicle is now, under offboard
    /// control (not at an older hold point, which `fail` would keep).
    fn fail_and_hold_here(&mut self, why: &str) {
        self.fail(FailureReason::Failsafe(why.into()));
        self.hold_point = self.vehicle.map(|v| v.position);
        self.task = Task::Hold;
        self.ensure_offboard();
    }

    pub fn peers_silent(&self) -> bool {
        self.peers_silent
    }

    /// Why `action` is refused on arrival because of a failsafe: only what makes the drone
    /// safer (land, hold) is taken while one is on, and only a landing in the landing stage.
    /// A hold taken there would not last (the next tick's `set_failsafe` fails it and lands),
    /// and for a drone PX4 flies it would first take the drone back from PX4 only to land it.
    pub(super) fn failsafe_refusal(&self, action: &Action) -> Option<&'static str> {
        if matches!(action, Action::Land) {
            return None;
        }
        if matches!(action, Action::Hold) {
            return (self.failsafe == Some(FailsafeStage::Landing)).then_some(
                "ground silent long enough to land: only a landing is taken until a ground \
                 station in control is heard",
            );
        }
        if self.failsafe.is_some() {
            // A ground that sends without beating is not in control.
            return Some(
                "ground silent: only land and hold are taken until a ground station in \
                 control is heard",
            );
        }
        if self.peers_silent && self.airborne() {
            return Some(
                "no neighbour heard: only land and hold are taken until one is heard, since \
                 the others' whereabouts are unknown",
            );
        }
        None
    }
}

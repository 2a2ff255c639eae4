//! What `undo` and `cancel` work from: the memory of the last instruction the models carried
//! out (where every drone was when the pilot gave it, and which drones its plan moved), and the
//! steps that fly one drone back to where it was. Pure: the direct commands (`commands`) read
//! the swarm and send the steps through the safety gate one after another.

use std::collections::{BTreeMap, BTreeSet};
use tacos_shared::{DroneId, Vec3};

/// Within this distance on the ground, a drone counts as on the spot it started from.
pub const SAME_SPOT_M: f64 = 0.5;

/// Where a drone was when the instruction was given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Before {
    pub position: Vec3,
    pub airborne: bool,
}

/// One step of flying a drone back. `GotoAbove` is resolved when it is sent, at the height the
/// drone then flies at (after a take-off, the take-off altitude).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum UndoStep {
    TakeOff,
    Goto(Vec3),
    GotoAbove { x: f64, y: f64 },
    Land,
}

impl UndoStep {
    pub fn describe(&self) -> String {
        match self {
            UndoStep::TakeOff => "take off".into(),
            UndoStep::Goto(p) => format!("fly back to ({:.1}, {:.1}, {:.1})", p.x, p.y, p.z),
            UndoStep::GotoAbove { x, y } => format!("fly back over ({x:.1}, {y:.1})"),
            UndoStep::Land => "land".into(),
        }
    }
}

/// The steps that take a drone from where it is now back to `before`: a drone that was in the
/// air flies back to the same point (taking off first if it has landed since); a drone that was
/// on the ground flies back over its spot, if it left it, and lands.
pub fn undo_steps(before: &Before, now: Vec3, airborne_now: bool) -> Vec<UndoStep> {
    let moved_off_spot = (now.xy() - before.position.xy()).norm() > SAME_SPOT_M;
    let mut steps = Vec::new();
    if before.airborne {
        if !airborne_now {
            steps.push(UndoStep::TakeOff);
        }
        steps.push(UndoStep::Goto(before.position));
        return steps;
    }
    if !airborne_now && !moved_off_spot {
        return steps;
    }
    if !airborne_now {
        steps.push(UndoStep::TakeOff);
    }
    if moved_off_spot {
        steps.push(UndoStep::GotoAbove {
            x: before.position.x,
            y: before.position.y,
        });
    }
    steps.push(UndoStep::Land);
    steps
}

/// The last instruction the models carried out, as `undo` and `cancel` need it.
#[derive(Debug, Clone, Default)]
pub struct InstructionMemory {
    /// The pilot's words, `None` before the first instruction.
    pub instruction: Option<String>,
    pub before: BTreeMap<DroneId, Before>,
    /// The drones an action of this instruction was sent to.
    pub moved: BTreeSet<DroneId>,
    /// Counts instructions: a step of an undo stops when a newer instruction came.
    pub generation: u64,
    /// Why `undo` may no longer fly this instruction back (it was undone, or the pilot landed).
    pub closed: Option<&'static str>,
}

impl InstructionMemory {
    /// A new instruction: where every drone is now.
    pub fn begin(&mut self, instruction: &str, before: BTreeMap<DroneId, Before>) {
        self.instruction = Some(instruction.to_owned());
        self.before = before;
        self.moved.clear();
        self.generation += 1;
        self.closed = None;
    }

    pub fn moved(&mut self, drone: &DroneId) {
        self.moved.insert(drone.clone());
    }

    /// Why there is nothing to undo, if there is not.
    pub fn nothing_to_undo(&self) -> Option<String> {
        let Some(instruction) = &self.instruction else {
            return Some("nothing to undo: no instruction has been carried out yet".into());
        };
        if let Some(why) = self.closed {
            return Some(format!("nothing to undo: {instruction:?} {why}"));
        }
        if self.moved.is_empty() {
            return Some(format!("nothing to undo: {instruction:?} moved no drone"));
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(x: f64, y: f64, z: f64) -> Vec3 {
        Vec3::new(x, y, z)
    }

    #[test]
    fn a_drone_that_was_flying_flies_back_to_its_point() {
        let before = Before {
            position: at(1.0, 2.0, 10.0),
            airborne: true,
        };
        assert_eq!(
            undo_steps(&before, at(30.0, 2.0, 12.0), true),
            vec![UndoStep::Goto(at(1.0, 2.0, 10.0))]
        );
        // Landed since: up first.
        assert_eq!(
            undo_steps(&before, at(30.0, 2.0, 0.0), false),
            vec![UndoStep::TakeOff, UndoStep::Goto(at(1.0, 2.0, 10.0))]
        );
    }

    #[test]
    fn a_drone_that_was_on_the_ground_goes_back_to_its_spot_and_lands() {
        let before = Before {
            position: at(1.0, 2.0, 0.0),
            airborne: false,
        };
        // Took off and hovers over its spot: it lands.
        assert_eq!(
            undo_steps(&before, at(1.2, 2.1, 10.0), true),
            vec![UndoStep::Land]
        );
        // Took off and flew away: back over the spot, then down.
        assert_eq!(
            undo_steps(&before, at(20.0, 2.0, 10.0), true),
            vec![UndoStep::GotoAbove { x: 1.0, y: 2.0 }, UndoStep::Land]
        );
        // Flew away and landed there: up, back, down.
        assert_eq!(
            undo_steps(&before, at(20.0, 2.0, 0.0), false),
            vec![
                UndoStep::TakeOff,
                UndoStep::GotoAbove { x: 1.0, y: 2.0 },
                UndoStep::Land
            ]
        );
        // Never left its spot: nothing.
        assert!(undo_steps(&before, at(1.1, 2.0, 0.0), false).is_empty());
    }

    #[test]
    fn the_memory_says_why_there_is_nothing_to_undo() {
        let mut memory = InstructionMemory::default();
        assert!(memory.nothing_to_undo().is_some());
        let alfa = DroneId::new("alfa").expect("a valid id");
        memory.begin("alfa, go north", BTreeMap::new());
        assert!(
            memory
                .nothing_to_undo()
                .is_some_and(|w| w.contains("moved no drone"))
        );
        memory.moved(&alfa);
        assert_eq!(memory.nothing_to_undo(), None);
        memory.closed = Some("was undone already");
        assert!(
            memory
                .nothing_to_undo()
                .is_some_and(|w| w.contains("undone already"))
        );
        let generation = memory.generation;
        memory.begin("bravo, take off", BTreeMap::new());
        assert_eq!(memory.generation, generation + 1);
        assert!(memory.moved.is_empty() && memory.closed.is_none());
    }
}

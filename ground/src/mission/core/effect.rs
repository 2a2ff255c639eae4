//! What the core asks the engine to do.

use super::call_start::Ask;
use super::calls::Coordination;
use crate::mission::aids::Aid;
use crate::mission::directives::Directive;
use crate::mission::log::{Record, RefusedBy};
use crate::mission::report::{EventTopic, MissionUpdate, Overtaken};
use crate::safety::CheckedAction;
use tacos_prompts::render::HistoryEntry;

#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Effect {
    /// Write a record to the mission log.
    Note(Record),
    /// Tell the pilot (the terminal, a script, the evaluation).
    Tell(MissionUpdate),
    /// A part of a model's reply was refused (by the checks or the safety gate): counted,
    /// logged and told to the pilot.
    Refused {
        layer: &'static str,
        refusal: String,
        by: RefusedBy,
    },
    /// Add to the Coordinator's memory of the mission (and to the log it is resumed from).
    /// Kept by the core (`Core::absorb`), as are `WorkReplaced` and `Replan`.
    Remember(HistoryEntry),
    /// The models' work was replaced or ended: a reply asked for before is not used.
    WorkReplaced,
    /// Carry out the pilot's direct command `text` at once (`commands`); the override it
    /// raises comes back as `Input::Overridden`.
    Direct { text: String, directive: Directive },
    /// The pilot's instruction was taken: what the drones did before it is kept for `undo`.
    InstructionBegun(String),
    /// Send `checked` (checked by the gate on this step's snapshot) for plan task `task`; the
    /// result comes back as `Input::Sent`.
    Send {
        checked: CheckedAction,
        task: String,
    },
    /// A Supervisor (or monolithic) cycle was done (the statistics' cycles).
    CycleCounted,
    /// Abort the model call in flight of `layer` and never use its reply (told to the pilot).
    DropCall { layer: &'static str, by: Overtaken },
    /// A plan completed after this many cycles (the statistics' cycles per plan).
    PlanCycles(u32),
    /// Run this model call beside the mission (one at a time); its reply comes back as an
    /// input.
    Ask(Ask),
    /// Take a snapshot with a drone heard (waiting a little for a silent swarm) and feed
    /// `Input::Coordinate` with it: the Coordinator's request is built on that snapshot.
    Coordinate(Coordination),
    /// Ask the Coordinator for an automatic replan with this instruction (queued after the work
    /// waiting for it; a cycle in flight is dropped).
    Replan(String),
}

impl Effect {
    /// A small-model aid changed what happens: the record the log keeps of it.
    pub(crate) fn aid_fired(aid: Aid, detail: String) -> Effect {
        Effect::Note(Record::AidFired { aid, detail })
    }

    /// An event the log keeps and the pilot is told.
    pub(crate) fn told(topic: EventTopic, text: String) -> [Effect; 2] {
        [
            Effect::Note(Record::Event { text: text.clone() }),
            Effect::Tell(MissionUpdate::Event { topic, text }),
        ]
    }
}

//! What the core asks the engine to do.

use crate::mission::aids::Aid;
use crate::mission::log::{Record, RefusedBy};
use crate::mission::report::{MissionUpdate, Overtaken};
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
    Remember(HistoryEntry),
    /// The models' work was replaced or ended: a reply asked for before is not used.
    WorkReplaced,
    /// Abort the model call in flight of `layer` and never use its reply (told to the pilot).
    DropCall { layer: &'static str, by: Overtaken },
    /// A plan completed after this many cycles (the statistics' cycles per plan).
    PlanCycles(u32),
    /// Ask the Coordinator for an automatic replan with this instruction (queued after the work
    /// waiting for it; a cycle in flight is dropped).
    Replan(String),
}

impl Effect {
    /// A small-model aid changed what happens: the record the log keeps of it.
    pub(crate) fn aid_fired(aid: Aid, detail: String) -> Effect {
        Effect::Note(Record::AidFired { aid, detail })
    }
}

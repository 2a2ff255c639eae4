//! What one cycle's model call carries: its question and the reply as the model gave it
//! (`cycles` asks; the core's `CycleChoice` is the reply as checked).

use crate::mission::core::CycleRequest;
use tacos_prompts::schema::Output;
use tacos_prompts::{Call, MonolithicReply, ReplyError, SupervisorReply};

/// One cycle's question to its model: the Supervisor's or the monolithic model's.
pub(super) struct CycleAsk {
    pub(super) layer: &'static str,
    pub(super) output: Output,
    pub(super) parse: fn(&str) -> Result<CycleReply, ReplyError>,
    /// The messages, the schema, the calls the reply may choose from (`core::CycleRequest`).
    pub(super) request: CycleRequest,
}

/// A Supervisor or monolithic reply: reasoning, calls to issue now, and the model's claim that
/// the work is complete (`plan_complete` or `done`).
pub(super) struct CycleReply {
    pub(super) reasoning: String,
    pub(super) actions: Vec<Call>,
    pub(super) claim: bool,
}

impl From<SupervisorReply> for CycleReply {
    fn from(r: SupervisorReply) -> Self {
        CycleReply {
            reasoning: r.reasoning,
            actions: r.actions,
            claim: r.plan_complete,
        }
    }
}

impl From<MonolithicReply> for CycleReply {
    fn from(r: MonolithicReply) -> Self {
        CycleReply {
            reasoning: r.reasoning,
            actions: r.actions,
            claim: r.done,
        }
    }
}

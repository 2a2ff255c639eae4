//! What one cycle's model call carries: which cycle it is for, its question, the reply as the
//! model gave it and as checked, and what the cycle did (`cycles` asks and answers).

use super::Mission;
use crate::mission::core::CycleRequest;
use crate::safety::CheckedAction;
use tacos_prompts::schema::Output;
use tacos_prompts::{Call, MonolithicReply, ReplyError, SupervisorReply};
use tacos_shared::DroneId;

/// Which cycle a call is for, and what its answer completes.
pub(super) enum CycleKind {
    Supervisor,
    /// `offered`: the numbered callables offered, whose ids the next cycle does not reuse.
    Monolithic {
        offered: u32,
    },
}

/// What a cycle's reply is for, carried beside its call.
pub(super) struct CycleWork {
    pub(super) kind: CycleKind,
    pub(super) issued: fn(&mut Mission, Call, DroneId, u64),
    /// `CallQueue::epoch` when the call started: a reply from before a plan was adopted or
    /// ended is for other work.
    pub(super) epoch: u64,
}

/// A cycle's reply as checked: the calls that passed, and what the pilot is told.
pub(super) struct CycleChoice {
    pub(super) reasoning: String,
    pub(super) claim: bool,
    pub(super) all_passed: bool,
    pub(super) accepted: Vec<(Call, CheckedAction)>,
    pub(super) later: Vec<String>,
}

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

/// What a cycle did.
pub(super) struct CycleOutcome {
    pub(super) reasoning: String,
    /// The model claimed the work complete.
    pub(super) claim: bool,
    /// Every call of the accepted reply passed the checks and was issued (none was a later
    /// step left for a later cycle).
    pub(super) all_passed: bool,
    pub(super) sent: Vec<String>,
}

impl CycleOutcome {
    /// A claim of completion counts only from a reply whose every call passed and was issued:
    /// a reply that names a rejected call or a later step and says "done" meant that call to be
    /// part of the work.
    pub(super) fn claim_stands(&self) -> bool {
        self.claim && self.all_passed
    }
}

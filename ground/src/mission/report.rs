//! What the mission engine reports: its errors, its updates to whoever shows the mission
//! (terminal, script runner, evaluation), and its counters.

use super::log::RefusedBy;
use std::time::Duration;
use tacos_llm::LlmError;

#[derive(Debug, PartialEq, thiserror::Error)]
pub enum MissionError {
    #[error("{layer}: the model server failed: {error}")]
    Llm {
        layer: &'static str,
        error: LlmError,
    },
    #[error("{layer}: no acceptable reply after {attempts} attempts; last problem: {reason}")]
    NoValidReply {
        layer: &'static str,
        attempts: u32,
        reason: String,
    },
    #[error("no drone is available to carry out a plan")]
    NoDroneAvailable,
    /// Found before any model call (`mission::addressed`).
    #[error(
        "there is no drone {} in this swarm (its drones: {}); nothing was sent: address one of those",
        names.join(" or "),
        swarm.join(", ")
    )]
    UnknownDrones {
        names: Vec<String>,
        swarm: Vec<String>,
    },
    /// The Coordinator's reply to the pilot instead of a plan.
    #[error("the Coordinator declined: {refusal} (nothing was sent)")]
    Declined { refusal: String },
    #[error("not sending {action} to {drone}: the pilot gave a direct command meanwhile")]
    Overridden { drone: String, action: String },
    #[error("sending {action} to {drone} failed: {reason}")]
    Send {
        drone: String,
        action: String,
        reason: String,
    },
    /// An error as a mission trace recorded it, in its words (`core::trace`): a replay tells
    /// the pilot the same.
    #[error("{0}")]
    Recorded(String),
}

/// What an engine event is about: whoever shows it sorts it by this, never by its text.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EventTopic {
    /// A direct command was carried out (its outcome per drone in the text).
    Direct,
    /// A target was seen.
    Detection,
    /// A drone became unavailable, or a fault was injected.
    Failure,
    /// A drone joined the swarm.
    Joined,
    /// The plan ended without completing (interrupted, abandoned).
    PlanEnded,
    /// The engine's bookkeeping: repeats dropped, later steps left, a take-off added.
    Note,
}

/// What the engine reports to whoever shows the mission (terminal, script runner, eval).
#[derive(Debug, Clone, PartialEq)]
pub enum MissionUpdate {
    Thinking {
        layer: &'static str,
    },
    Plan {
        reasoning: String,
        calls: Vec<String>,
    },
    Cycle {
        plan_cycle: u32,
        reasoning: String,
        actions: Vec<String>,
    },
    /// A call of a model's reply that the checks refused ("T2 alfa goto(x): why"); the reply
    /// goes back to `layer` with the reasons unless it was the last attempt.
    Rejected {
        layer: &'static str,
        refusal: String,
        by: RefusedBy,
    },
    Sent {
        drone: String,
        action: String,
        seq: u64,
    },
    Outcome {
        drone: String,
        action: String,
        /// "done", "failed: …", …, as the log has it.
        outcome: String,
        /// It did not end done: it failed, or its end is unknown.
        failed: bool,
    },
    Event {
        topic: EventTopic,
        text: String,
    },
    PlanComplete {
        cycles: u32,
    },
    Error(String),
    Call {
        layer: &'static str,
        latency: Duration,
        prompt_tokens: u32,
        completion_tokens: u32,
    },
    /// A reply as it is being written (a streaming backend; at most a few a second): the
    /// reasoning and the complete calls so far. Shown, never acted on.
    Writing {
        layer: &'static str,
        reasoning: String,
        calls: Vec<String>,
    },
    /// A model call in flight was dropped: its reply, whenever it comes, is not used.
    CallDropped {
        layer: &'static str,
        by: Overtaken,
    },
}

/// What overtook a model call in flight, so that its reply would be stale.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Overtaken {
    /// The pilot's direct command ended the plan the call was for.
    DirectCommand,
    /// A newer instruction or an automatic replan is waiting for the Coordinator: a Supervisor
    /// (or monolithic) reply for the plan before it would act on an old picture.
    NewerWork,
    /// The pilot closed the session.
    SessionClosed,
}

impl std::fmt::Display for Overtaken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Overtaken::DirectCommand => "a direct command",
            Overtaken::NewerWork => "a newer instruction or replan",
            Overtaken::SessionClosed => "the session closing",
        })
    }
}

/// Counters for the evaluation harness.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MissionStats {
    pub model_calls: u32,
    pub coordinator_calls: u32,
    pub supervisor_calls: u32,
    /// Supervisor (or monolithic) cycles of each finished plan, in order.
    pub cycles_per_plan: Vec<u32>,
    pub cycles_total: u32,
    pub actions_sent: u32,
    pub gate_rejections: u32,
    pub prompt_tokens: u64,
    pub completion_tokens: u64,
    pub call_latency_total: Duration,
}

/// The mission's counters, shared with the model calls that run beside the engine (a call
/// dropped in flight has counted what it did).
#[derive(Debug, Clone, Default)]
pub struct SharedStats(std::sync::Arc<std::sync::Mutex<MissionStats>>);

impl SharedStats {
    pub fn update(&self, f: impl FnOnce(&mut MissionStats)) {
        // A panic while counting leaves counters, not invariants: go on with them.
        let mut stats = self.0.lock().unwrap_or_else(|e| e.into_inner());
        f(&mut stats);
    }

    pub fn snapshot(&self) -> MissionStats {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

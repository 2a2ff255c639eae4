//! Asking a model: the request, the call, its accounting, and the effects of the repair loop
//! (`core::Repair`), which decides what a reply comes to and whether to ask again.

use super::early::OnWritten;
use crate::link::GroundLink;
use crate::mission::aids::ModelAids;
use crate::mission::core::{Checked, Effect, Next, Repair};
use crate::mission::log::{MissionLog, Record, RefusedBy};
use crate::mission::report::{MissionError, MissionUpdate, SharedStats};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tacos_llm::{ChatMessage, ChatReply, ChatRequest, LlmBackend, ResponseSchema, Streamed};
use tacos_prompts::ReplyError;
use tacos_prompts::partial::partial_reply;
use tacos_prompts::schema::Output;
use tokio::sync::mpsc;

/// How often a reply being written is told to the pilot.
const WRITING_EVERY: Duration = Duration::from_millis(250);

/// Asks models: the backend, the repair loop's bounds, and where calls are recorded. A clone
/// runs each call on its own task, beside the engine (`driver::in_flight`).
#[derive(Clone)]
pub(super) struct Caller {
    pub(super) backend: Arc<dyn LlmBackend>,
    /// Told of every call in flight, so a simulation holds real time meanwhile.
    pub(super) link: Arc<GroundLink>,
    pub(super) log: Arc<MissionLog>,
    pub(super) updates: mpsc::UnboundedSender<MissionUpdate>,
    pub(super) max_repairs: u32,
    /// `compact-repair-echo` and `keep-partial-plan` act here.
    pub(super) aids: ModelAids,
    pub(super) temperature: f32,
    pub(super) seed: Option<u64>,
    pub(super) stats: SharedStats,
    /// Told the reply's text each time it grows: a cycle call's calls sent early (`early`).
    pub(super) on_written: Option<OnWritten>,
}

impl Caller {
    /// Asks a model and runs the repair loop (`core::Repair`) on its replies: each is parsed
    /// with `parse` and checked with `check`, and a reply with refused parts is sent back with
    /// the reasons up to `max_repairs` times. After the last attempt what passed is returned,
    /// except for a reply that must pass `whole` (a plan: its calls belong together), which then
    /// fails unless the `keep-partial-plan` aid is on.
    #[allow(clippy::too_many_arguments)]
    pub(super) async fn ask<T, U>(
        &self,
        layer: &'static str,
        messages: Vec<ChatMessage>,
        output: Output,
        schema: serde_json::Value,
        max_tokens: u32,
        parse: fn(&str) -> Result<T, ReplyError>,
        whole: bool,
        mut check: impl FnMut(&T) -> Checked<U>,
    ) -> Result<U, MissionError> {
        let mut repair = Repair::new(layer, messages, schema, self.max_repairs, whole, self.aids);
        loop {
            let attempt = repair.attempt();
            let request = ChatRequest {
                messages: repair.messages().to_vec(),
                schema: Some(ResponseSchema {
                    name: output.name().into(),
                    schema: repair.schema().clone(),
                }),
                max_tokens,
                temperature: self.temperature,
                seed: self.seed,
                reasoning_effort: Some("low".into()),
            };
            self.log.note(Record::LlmRequest {
                layer: layer.into(),
                attempt,
                messages: serde_json::to_value(&request.messages).unwrap_or_default(),
            });
            self.stats.update(|s| s.model_calls += 1);
            let in_flight = self.link.model_call();
            let told = self.writing_told(layer);
            let on_written = self.on_written.clone();
            let progress = move |so_far: Streamed<'_>| {
                if let Some(on_written) = &on_written {
                    on_written(so_far.content);
                }
                told(so_far);
            };
            let reply = self.backend.chat_streamed(&request, &progress).await;
            // A reply that comes back within the poll in which the engine dropped this call (a
            // backend that answers without waiting, or a thread that lost its core between a
            // call's start and its first wait) would otherwise be logged, checked and repaired
            // in that same poll: the abort takes effect at the first await. This is one.
            tokio::task::yield_now().await;
            drop(in_flight);
            let mut effects = Vec::new();
            let next = match reply {
                Ok(reply) => {
                    self.account(layer, attempt, &reply);
                    repair.replied(&reply.content, parse, &mut check, &mut effects)
                }
                Err(error) => {
                    self.log.note(Record::LlmError {
                        layer: layer.into(),
                        attempt,
                        error: error.to_string(),
                    });
                    repair.failed(error, &mut effects)
                }
            };
            self.apply(effects);
            if let Next::Done(answer) = next {
                return answer;
            }
        }
    }

    /// Carries out the repair loop's effects.
    fn apply(&self, effects: Vec<Effect>) {
        for effect in effects {
            match effect {
                Effect::Refused { layer, refusal, by } => {
                    refused(&self.log, &self.updates, &self.stats, layer, refusal, by)
                }
                Effect::Note(Record::AidFired { aid, detail }) => self.log.aid_fired(aid, detail),
                Effect::Note(record) => self.log.note(record),
                Effect::Tell(update) => {
                    let _ = self.updates.send(update);
                }
                other => tracing::warn!(?other, "an effect the repair loop does not hand back"),
            }
        }
    }

    /// Tells the pilot a reply as it is being written (`MissionUpdate::Writing`), at most every
    /// [`WRITING_EVERY`]: its reasoning (the server's, or the `reasoning` field being written)
    /// and its complete calls.
    fn writing_told(&self, layer: &'static str) -> impl Fn(Streamed<'_>) + Send + Sync + use<> {
        let updates = self.updates.clone();
        let last_told: Mutex<Option<Instant>> = Mutex::new(None);
        move |so_far: Streamed<'_>| {
            let now = Instant::now();
            {
                let mut last = last_told.lock().unwrap_or_else(|e| e.into_inner());
                if last.is_some_and(|t| now.duration_since(t) < WRITING_EVERY) {
                    return;
                }
                *last = Some(now);
            }
            let read = partial_reply(so_far.content);
            let reasoning = match so_far.reasoning.trim() {
                "" => read.reasoning.unwrap_or_default(),
                thought => thought.to_owned(),
            };
            let _ = updates.send(MissionUpdate::Writing {
                layer,
                reasoning,
                calls: read.calls.iter().map(ToString::to_string).collect(),
            });
        }
    }

    pub(super) fn account(&self, layer: &'static str, attempt: u32, reply: &ChatReply) {
        self.stats.update(|stats| {
            stats.prompt_tokens += u64::from(reply.usage.prompt_tokens);
            stats.completion_tokens += u64::from(reply.usage.completion_tokens);
            stats.call_latency_total += reply.latency;
        });
        self.log.note(Record::LlmReply {
            layer: layer.into(),
            attempt,
            content: reply.content.clone(),
            reasoning: reply.reasoning.clone(),
            latency_ms: reply.latency.as_millis() as u64,
            prompt_tokens: reply.usage.prompt_tokens,
            completion_tokens: reply.usage.completion_tokens,
        });
        let _ = self.updates.send(MissionUpdate::Call {
            layer,
            latency: reply.latency,
            prompt_tokens: reply.usage.prompt_tokens,
            completion_tokens: reply.usage.completion_tokens,
        });
    }
}

/// A refused part of a reply: counted, logged and told to the pilot.
pub(super) fn refused(
    log: &MissionLog,
    updates: &mpsc::UnboundedSender<MissionUpdate>,
    stats: &SharedStats,
    layer: &'static str,
    refusal: String,
    by: RefusedBy,
) {
    stats.update(|s| s.gate_rejections += 1);
    log.note(Record::GateRejected {
        layer: layer.into(),
        call: refusal.clone(),
        reason: String::new(),
        by,
    });
    let _ = updates.send(MissionUpdate::Rejected { layer, refusal, by });
}

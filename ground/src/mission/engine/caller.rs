//! Asking a model: the request, the parse and check of its reply, and the repair loop that sends
//! a rejected reply back with the reasons.

use super::early::OnWritten;
use crate::link::GroundLink;
use crate::mission::aids::{Aid, ModelAids};
use crate::mission::log::{MissionLog, Record, RefusedBy};
use crate::mission::report::{MissionError, MissionUpdate, SharedStats};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tacos_llm::{
    ChatMessage, ChatReply, ChatRequest, LlmBackend, LlmError, ResponseSchema, Streamed,
};
use tacos_prompts::ReplyError;
use tacos_prompts::partial::partial_reply;
use tacos_prompts::schema::Output;
use tokio::sync::mpsc;

/// How often a reply being written is told to the pilot.
const WRITING_EVERY: Duration = Duration::from_millis(250);

/// Asks models: the backend, the repair loop's bounds, and where calls are recorded. A clone
/// runs each call on its own task, beside the engine (`engine::in_flight`).
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

/// The result of checking one reply: what may be done, and why the rest may not.
pub(super) struct Checked<U> {
    pub(super) accepted: U,
    /// Nothing of the reply passed: `keep-partial-plan` has nothing to keep, and the pilot is
    /// told the refusals instead of an empty plan.
    pub(super) nothing_passed: bool,
    pub(super) rejections: Vec<String>,
    /// The calls the safety gate refused, with its reasons (counted apart from the checks').
    pub(super) gate_refusals: Vec<String>,
    /// The schema for the repair round, when the reply missed something the grammar can hold
    /// the next one to; `None`: the same schema again.
    pub(super) narrowed: Option<serde_json::Value>,
}

impl Caller {
    /// Asks a model, parses and checks its reply, and sends rejected replies back with the
    /// reasons up to `max_repairs` times. After the last attempt what passed is returned, except
    /// for a reply that must pass `whole` (a plan: its calls belong together), which then fails
    /// unless the `keep-partial-plan` aid is on.
    #[allow(clippy::too_many_arguments)]
    pub(super) async fn ask<T, U>(
        &self,
        layer: &'static str,
        mut messages: Vec<ChatMessage>,
        output: Output,
        mut schema: serde_json::Value,
        max_tokens: u32,
        parse: fn(&str) -> Result<T, ReplyError>,
        whole: bool,
        mut check: impl FnMut(&T) -> Checked<U>,
    ) -> Result<U, MissionError> {
        let attempts = self.max_repairs + 1;
        let mut last_problem = String::new();
        // What passed in the last checked reply: a repair round that the backend cannot answer
        // (e.g. the repair prompt has outgrown the embedded model's window) leaves it in force.
        let mut passed_before: Option<U> = None;
        for attempt in 1..=attempts {
            let request = ChatRequest {
                messages: messages.clone(),
                schema: Some(ResponseSchema {
                    name: output.name().into(),
                    schema: schema.clone(),
                }),
                max_tokens,
                temperature: self.temperature,
                seed: self.seed,
                reasoning_effort: Some("low".into()),
            };
            self.log.note(Record::LlmRequest {
                layer: layer.into(),
                attempt,
                messages: serde_json::to_value(&messages).unwrap_or_default(),
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
            drop(in_flight);
            let reply = match reply {
                Ok(reply) => reply,
                Err(LlmError::Truncated(n)) => {
                    self.log.note(Record::LlmError {
                        layer: layer.into(),
                        attempt,
                        error: LlmError::Truncated(n).to_string(),
                    });
                    last_problem = format!("the reply was cut off at {n} tokens");
                    messages.push(ChatMessage::user(format!("Your reply was cut off at {n} tokens. Answer again, shorter: brief reasoning, same JSON structure.")));
                    continue;
                }
                Err(error) => {
                    self.log.note(Record::LlmError {
                        layer: layer.into(),
                        attempt,
                        error: error.to_string(),
                    });
                    if let Some(passed) = self.keep_partial(layer, passed_before, &error) {
                        return Ok(passed);
                    }
                    return Err(MissionError::Llm { layer, error });
                }
            };
            self.account(layer, attempt, &reply);
            let problems = match parse(&reply.content) {
                Err(e) => vec![e.to_string()],
                Ok(parsed) => {
                    let mut checked = check(&parsed);
                    let by_checks = checked.rejections.iter().map(|r| (RefusedBy::Checks, r));
                    let by_gate = checked
                        .gate_refusals
                        .iter()
                        .map(|r| (RefusedBy::SafetyGate, r));
                    for (by, r) in by_checks.chain(by_gate) {
                        self.stats.update(|s| s.gate_rejections += 1);
                        self.log.note(Record::GateRejected {
                            layer: layer.into(),
                            call: r.clone(),
                            reason: String::new(),
                            by,
                        });
                        let _ = self.updates.send(MissionUpdate::Rejected {
                            layer,
                            refusal: r.clone(),
                            by,
                        });
                    }
                    checked.rejections.append(&mut checked.gate_refusals);
                    if checked.rejections.is_empty() {
                        return Ok(checked.accepted);
                    }
                    if attempt == attempts {
                        if !whole {
                            return Ok(checked.accepted);
                        }
                        let refused = distinct_problems(checked.rejections).join("; ");
                        if self.aids.is_on(Aid::KeepPartialPlan) && !checked.nothing_passed {
                            let detail = format!(
                                "{layer}: kept what passed of the last reply; refused: {refused}"
                            );
                            self.log.aid_fired(Aid::KeepPartialPlan, detail);
                            return Ok(checked.accepted);
                        }
                        return Err(MissionError::NoValidReply {
                            layer,
                            attempts,
                            reason: refused,
                        });
                    }
                    if let Some(narrowed) = checked.narrowed {
                        schema = narrowed;
                    }
                    passed_before = (!checked.nothing_passed).then_some(checked.accepted);
                    checked.rejections
                }
            };
            let problems = distinct_problems(problems);
            last_problem = problems.join("; ");
            let echo = if self.aids.is_on(Aid::CompactRepairEcho) {
                let (echo, left_out) = without_repeated_items(&reply.content);
                if left_out > 0 {
                    self.log.aid_fired(
                        Aid::CompactRepairEcho,
                        format!("{layer}: {left_out} repeated items left out of the echoed reply"),
                    );
                }
                echo
            } else {
                reply.content.clone()
            };
            messages.push(ChatMessage::assistant(echo));
            messages.push(ChatMessage::user(format!(
                "Your reply was rejected:\n- {}\nAnswer again with the corrected JSON object only.",
                problems.join("\n- ")
            )));
        }
        if let Some(passed) = self.keep_partial(layer, passed_before, &last_problem) {
            return Ok(passed);
        }
        Err(MissionError::NoValidReply {
            layer,
            attempts,
            reason: last_problem,
        })
    }

    /// What passed in the round before a repair round that failed (`why`), kept when the
    /// `keep-partial-plan` aid is on.
    fn keep_partial<U>(
        &self,
        layer: &str,
        passed_before: Option<U>,
        why: &dyn std::fmt::Display,
    ) -> Option<U> {
        let passed = passed_before.filter(|_| self.aids.is_on(Aid::KeepPartialPlan))?;
        self.log.aid_fired(
            Aid::KeepPartialPlan,
            format!("{layer}: the repair round failed ({why}); what passed the round before stays"),
        );
        Some(passed)
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

/// `reply` as echoed back in a repair round: in its lists of objects, an item equal to an
/// earlier one but for its `task` is left out (the engine drops such repeats anyway). A 135M
/// model that loops on one call writes it until the list is full, and echoed whole, its 680
/// tokens pushed a 6-drone repair round past the embedded model's 4096-token window. A reply
/// that is not a JSON object is echoed as it is. Also returns how many items were left out.
pub(super) fn without_repeated_items(reply: &str) -> (String, usize) {
    let Ok(serde_json::Value::Object(mut object)) = serde_json::from_str(reply) else {
        return (reply.to_owned(), 0);
    };
    let mut left_out = 0;
    for value in object.values_mut() {
        let serde_json::Value::Array(items) = value else {
            continue;
        };
        let mut seen: Vec<serde_json::Value> = Vec::new();
        items.retain(|item| {
            let mut key = item.clone();
            if let Some(o) = key.as_object_mut() {
                o.remove("task");
            }
            let new = !seen.contains(&key);
            seen.push(key);
            left_out += usize::from(!new);
            new
        });
    }
    match serde_json::to_string(&object) {
        Ok(text) => (text, left_out),
        Err(_) => (reply.to_owned(), 0),
    }
}

/// The problems of a reply, each said once: the same refusal of the same call under other task
/// ids ("T2 alfa start_tracking(car_1): …", "T3 alfa start_tracking(car_1): …") is one line.
pub(super) fn distinct_problems(problems: Vec<String>) -> Vec<String> {
    let mut seen: Vec<String> = Vec::new();
    problems
        .into_iter()
        .filter(|p| {
            let key = match p.split_once(' ') {
                Some((first, rest))
                    if first.len() > 1
                        && first.starts_with(['T', 'A'])
                        && first[1..].chars().all(|c| c.is_ascii_digit()) =>
                {
                    rest.to_owned()
                }
                _ => p.clone(),
            };
            let new = !seen.contains(&key);
            seen.push(key);
            new
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_repair_echo_leaves_out_repeated_items_and_problems_are_said_once() {
        let reply = r#"{"reasoning": "r", "plan": [
            {"task": "T1", "drone": "alfa", "action": "goto", "target": "car_1", "xyz": null},
            {"task": "T2", "drone": "alfa", "action": "arm_takeoff", "target": "none", "xyz": null},
            {"task": "T3", "drone": "alfa", "action": "arm_takeoff", "target": "none", "xyz": null},
            {"task": "T4", "drone": "alfa", "action": "goto", "target": "car_2", "xyz": null}]}"#;
        let echoed: serde_json::Value =
            serde_json::from_str(&without_repeated_items(reply).0).expect("JSON");
        let tasks: Vec<&str> = echoed["plan"]
            .as_array()
            .expect("plan")
            .iter()
            .filter_map(|c| c["task"].as_str())
            .collect();
        assert_eq!(tasks, ["T1", "T2", "T4"]);
        assert_eq!(echoed["reasoning"], "r");
        assert_eq!(without_repeated_items(reply).1, 1);
        assert_eq!(without_repeated_items("Sure!"), ("Sure!".to_owned(), 0));
        let problems = distinct_problems(vec![
            "T2 alfa start_tracking(car_1): car_1 is not a target".into(),
            "T3 alfa start_tracking(car_1): car_1 is not a target".into(),
            "T4 bravo start_tracking(car_1): car_1 is not a target".into(),
            "the plan is empty".into(),
            "the plan is empty".into(),
        ]);
        assert_eq!(
            problems,
            [
                "T2 alfa start_tracking(car_1): car_1 is not a target",
                "T4 bravo start_tracking(car_1): car_1 is not a target",
                "the plan is empty"
            ]
        );
    }
}

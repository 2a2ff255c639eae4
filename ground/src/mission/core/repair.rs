//! The repair loop of one model call, as a state machine: each reply is parsed and checked, a
//! reply with refused parts is sent back with the reasons, up to `max_repairs` times, and the
//! loop ends with what may be done or why nothing may. The engine's `Caller` drives it: it asks
//! the model for [`Repair::messages`] under [`Repair::schema`], hands the outcome to
//! [`Repair::replied`] or [`Repair::failed`], carries out the effects, and asks again while the
//! answer is [`Next::Ask`]. The `compact-repair-echo` and `keep-partial-plan` aids act here.

use super::effect::Effect;
use crate::mission::aids::{Aid, ModelAids};
use crate::mission::log::RefusedBy;
use crate::mission::report::{EventTopic, MissionError};
use tacos_llm::{ChatMessage, LlmError};
use tacos_prompts::ReplyError;

/// The result of checking one reply: what may be done, and why the rest may not.
pub(crate) struct Checked<U> {
    pub(crate) accepted: U,
    /// Nothing of the reply passed: `keep-partial-plan` has nothing to keep, and the pilot is
    /// told the refusals instead of an empty plan.
    pub(crate) nothing_passed: bool,
    pub(crate) rejections: Vec<String>,
    /// The calls the safety gate refused, with its reasons (counted apart from the checks').
    pub(crate) gate_refusals: Vec<String>,
    /// The schema for the repair round, when the reply missed something the grammar can hold
    /// the next one to; `None`: the same schema again.
    pub(crate) narrowed: Option<serde_json::Value>,
    /// What makes a reply doubtful without making it wrong: a reply with nothing refused but
    /// doubts is sent back once, on the first attempt, and what comes back is judged as usual
    /// (the same reply again passes). A plan whose every call changes nothing is one: the
    /// pilot's "find the suspect" answered with six take-offs of drones in the air, but also
    /// "alfa, land" with alfa on the ground, which is right.
    pub(crate) doubts: Vec<String>,
}

/// What the engine does next.
#[derive(Debug)]
pub(crate) enum Next<U> {
    /// Ask the model again ([`Repair::messages`] now holds the repair round).
    Ask,
    /// The call's answer.
    Done(Result<U, MissionError>),
}

/// One call's repair loop: the conversation so far, the schema of the next attempt, and what
/// passed in the last checked reply.
pub(crate) struct Repair<U> {
    layer: &'static str,
    messages: Vec<ChatMessage>,
    schema: serde_json::Value,
    /// The attempt being asked, from 1.
    attempt: u32,
    attempts: u32,
    /// The reply's parts belong together (a plan): after the last attempt, a reply with refused
    /// parts fails unless `keep-partial-plan` is on; otherwise what passed is the answer.
    whole: bool,
    aids: ModelAids,
    /// What passed in the last checked reply: a repair round the backend cannot answer (e.g.
    /// the repair prompt has outgrown the embedded model's window) leaves it in force when
    /// `keep-partial-plan` is on.
    passed_before: Option<U>,
    /// The first reply, sent back for its doubts only: it stands if no later reply passes.
    doubted: Option<U>,
    last_problem: String,
}

impl<U> Repair<U> {
    pub(crate) fn new(
        layer: &'static str,
        messages: Vec<ChatMessage>,
        schema: serde_json::Value,
        max_repairs: u32,
        whole: bool,
        aids: ModelAids,
    ) -> Self {
        Repair {
            layer,
            messages,
            schema,
            attempt: 1,
            attempts: max_repairs + 1,
            whole,
            aids,
            passed_before: None,
            doubted: None,
            last_problem: String::new(),
        }
    }

    /// The attempt to ask now, from 1.
    pub(crate) fn attempt(&self) -> u32 {
        self.attempt
    }

    /// The conversation to send.
    pub(crate) fn messages(&self) -> &[ChatMessage] {
        &self.messages
    }

    /// The schema the reply is held to.
    pub(crate) fn schema(&self) -> &serde_json::Value {
        &self.schema
    }

    /// The model answered `content`: parsed with `parse`, checked with `check`. The refusals
    /// are told (as [`Effect::Refused`]).
    pub(crate) fn replied<T>(
        &mut self,
        content: &str,
        parse: fn(&str) -> Result<T, ReplyError>,
        check: impl FnOnce(&T) -> Checked<U>,
        effects: &mut Vec<Effect>,
    ) -> Next<U> {
        let problems = match parse(content) {
            Err(e) => vec![e.to_string()],
            Ok(parsed) => {
                let mut checked = check(&parsed);
                let by_checks = checked.rejections.iter().map(|r| (RefusedBy::Checks, r));
                let by_gate = (checked.gate_refusals.iter()).map(|r| (RefusedBy::SafetyGate, r));
                for (by, refusal) in by_checks.chain(by_gate) {
                    effects.push(Effect::Refused {
                        layer: self.layer,
                        refusal: refusal.clone(),
                        by,
                    });
                }
                checked.rejections.append(&mut checked.gate_refusals);
                if checked.rejections.is_empty() {
                    if checked.doubts.is_empty() || self.attempt > 1 || self.attempts == 1 {
                        return Next::Done(Ok(checked.accepted));
                    }
                    let text = format!(
                        "{}: reply sent back once: {}",
                        self.layer,
                        checked.doubts.join("; ")
                    );
                    effects.extend(Effect::told(EventTopic::Note, text));
                    self.doubted = Some(checked.accepted);
                    checked.doubts
                } else {
                    if self.attempt == self.attempts {
                        return Next::Done(self.last_reply_refused(checked, effects));
                    }
                    if let Some(narrowed) = checked.narrowed {
                        self.schema = narrowed;
                    }
                    self.passed_before = (!checked.nothing_passed).then_some(checked.accepted);
                    checked.rejections
                }
            }
        };
        let problems = distinct_problems(problems);
        self.last_problem = problems.join("; ");
        let echo = if self.aids.is_on(Aid::CompactRepairEcho) {
            let (echo, left_out) = without_repeated_items(content);
            if left_out > 0 {
                let detail = format!(
                    "{}: {left_out} repeated items left out of the echoed reply",
                    self.layer
                );
                effects.push(Effect::aid_fired(Aid::CompactRepairEcho, detail));
            }
            echo
        } else {
            content.to_owned()
        };
        self.messages.push(ChatMessage::assistant(echo));
        let repair_round = if self.doubted.is_some() && self.attempt == 1 {
            format!(
                "Check your reply:\n- {}\nAnswer again with the JSON object only: a changed \
                 one, or the same one if it is what the instruction needs.",
                problems.join("\n- ")
            )
        } else {
            format!(
                "Your reply was rejected:\n- {}\nAnswer again with the corrected JSON object \
                 only.",
                problems.join("\n- ")
            )
        };
        self.messages.push(ChatMessage::user(repair_round));
        self.next_attempt(effects)
    }

    /// The model call failed with `error`. A reply cut off at the token limit is asked again,
    /// shorter; any other failure ends the call.
    pub(crate) fn failed(&mut self, error: LlmError, effects: &mut Vec<Effect>) -> Next<U> {
        if let LlmError::Truncated(n) = error {
            self.last_problem = format!("the reply was cut off at {n} tokens");
            self.messages.push(ChatMessage::user(format!(
                "Your reply was cut off at {n} tokens. Answer again, shorter: brief reasoning, \
                 same JSON structure."
            )));
            return self.next_attempt(effects);
        }
        if let Some(passed) = self.keep_partial(&error, effects) {
            return Next::Done(Ok(passed));
        }
        Next::Done(Err(MissionError::Llm {
            layer: self.layer,
            error,
        }))
    }

    /// The last attempt's reply had refused parts.
    fn last_reply_refused(
        &mut self,
        checked: Checked<U>,
        effects: &mut Vec<Effect>,
    ) -> Result<U, MissionError> {
        if !self.whole {
            return Ok(checked.accepted);
        }
        if let Some(first) = self.first_reply_stands(effects) {
            return Ok(first);
        }
        let refused = distinct_problems(checked.rejections).join("; ");
        if self.aids.is_on(Aid::KeepPartialPlan) && !checked.nothing_passed {
            let detail = format!(
                "{}: kept what passed of the last reply; refused: {refused}",
                self.layer
            );
            effects.push(Effect::aid_fired(Aid::KeepPartialPlan, detail));
            return Ok(checked.accepted);
        }
        Err(MissionError::NoValidReply {
            layer: self.layer,
            attempts: self.attempts,
            reason: refused,
        })
    }

    /// Another attempt, or the end when this was the last.
    fn next_attempt(&mut self, effects: &mut Vec<Effect>) -> Next<U> {
        if self.attempt < self.attempts {
            self.attempt += 1;
            return Next::Ask;
        }
        let why = self.last_problem.clone();
        if let Some(passed) = self.keep_partial(&why, effects) {
            return Next::Done(Ok(passed));
        }
        Next::Done(Err(MissionError::NoValidReply {
            layer: self.layer,
            attempts: self.attempts,
            reason: why,
        }))
    }

    /// What passed in the round before a repair round that failed (`why`), kept when the
    /// `keep-partial-plan` aid is on.
    fn keep_partial(
        &mut self,
        why: &dyn std::fmt::Display,
        effects: &mut Vec<Effect>,
    ) -> Option<U> {
        if let Some(first) = self.first_reply_stands(effects) {
            return Some(first);
        }
        if !self.aids.is_on(Aid::KeepPartialPlan) {
            return None;
        }
        let passed = self.passed_before.take()?;
        let detail = format!(
            "{}: the repair round failed ({why}); what passed the round before stays",
            self.layer
        );
        effects.push(Effect::aid_fired(Aid::KeepPartialPlan, detail));
        Some(passed)
    }
}

impl<U> Repair<U> {
    /// The first reply, if it was sent back for doubts only: no later reply did better.
    fn first_reply_stands(&mut self, effects: &mut Vec<Effect>) -> Option<U> {
        let first = self.doubted.take()?;
        let text = format!("{}: no better reply came: the first one stands", self.layer);
        effects.extend(Effect::told(EventTopic::Note, text));
        Some(first)
    }
}

/// `reply` as echoed back in a repair round: in its lists of objects, an item equal to an
/// earlier one but for its `task` is left out (the engine drops such repeats anyway). A 135M
/// model that loops on one call writes it until the list is full, and echoed whole, its 680
/// tokens pushed a 6-drone repair round past the embedded model's 4096-token window. A reply
/// that is not a JSON object is echoed as it is. Also returns how many items were left out.
pub(crate) fn without_repeated_items(reply: &str) -> (String, usize) {
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
pub(crate) fn distinct_problems(problems: Vec<String>) -> Vec<String> {
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

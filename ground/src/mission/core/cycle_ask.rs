//! The Supervisor's and the monolithic model's request for one cycle, built from one snapshot:
//! the messages, the schema (only what can start now), the calls the reply may choose from and
//! the tasks issued so far. No request when there is no decision to make: nothing of the plan
//! can start, or no drone can take an action.

use super::book::PlanBook;
use super::prompt_view::{plan_lines, trackable};
use super::snapshot::Snapshot;
use super::start::{Start, startable};
use crate::mission::config::Mode;
use crate::mission::resume::PlanTask;
use crate::safety::SafetyGate;
use tacos_llm::ChatMessage;
use tacos_prompts::offer::{callable_schema, startable_schema};
use tacos_prompts::render::{self, TaskStatus};
use tacos_prompts::{Call, texts};
use tacos_shared::scenario::Scenario;

/// A cycle's request.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct CycleRequest {
    pub(crate) messages: Vec<ChatMessage>,
    pub(crate) schema: serde_json::Value,
    /// The calls the reply may choose from (the Supervisor's startable calls); `None`: any call
    /// that passes the live checks (the monolithic model, which has no plan).
    pub(crate) only: Option<Vec<Call>>,
    /// The tasks issued so far, so a running or finished task is not issued again.
    pub(crate) tasks: Vec<(Call, TaskStatus)>,
    /// The swarm's size, for the reply's token budget.
    pub(crate) drones: usize,
}

/// The Supervisor's request for the plan in force, or `None` when there is none or nothing of
/// it can start now: then the Supervisor has no decision to make, and the engine waits for the
/// swarm (an outcome, a membership change or the cycle timeout). `mode`: the plan's reasoning
/// is shown in `tacos`, not in `wor`.
pub(crate) fn supervisor_ask(
    book: &PlanBook,
    snap: &Snapshot,
    gate: &SafetyGate,
    events: &[String],
    mode: Mode,
) -> Option<CycleRequest> {
    let plan = book.plan.as_ref()?;
    let scenario = gate.scenario();
    let startable = startable(plan, &Start::new(snap, gate, book));
    if startable.is_empty() {
        return None;
    }
    let reasoning = (mode == Mode::Tacos).then_some(plan.reasoning.as_str());
    let progress: Vec<_> = plan.tasks.iter().map(PlanTask::progress).collect();
    let user = render::supervisor_request(
        reasoning,
        &progress,
        &render::swarm(&snap.drone_lines(scenario)),
        &snap.world_text(scenario, events),
    );
    let tasks = plan_lines(book);
    Some(CycleRequest {
        messages: supervisor_messages(user),
        schema: startable_schema(&startable),
        only: Some(startable),
        tasks,
        drones: snap.swarm_ids(scenario).len(),
    })
}

/// The monolithic model's request and the number of fresh task ids it offers, or `None` when
/// no drone can take an action.
pub(crate) fn monolithic_ask(
    book: &PlanBook,
    snap: &Snapshot,
    scenario: &Scenario,
    events: &[String],
) -> Option<(CycleRequest, u32)> {
    let callable = snap.callable(scenario, book);
    if callable.is_empty() {
        return None;
    }
    let user = render::monolithic_request(
        &book.mnl.instructions,
        &render::swarm(&snap.drone_lines(scenario)),
        &snap.world_text(scenario, events),
        &book.mnl.executed,
    );
    let (drones, places) = snap.enums(scenario);
    let mut messages = monolithic_fixed_messages();
    messages.push(ChatMessage::user(user));
    let request = CycleRequest {
        messages,
        schema: callable_schema(&callable, &drones, &places, &trackable(scenario)),
        only: None,
        tasks: (book.mnl.tasks.iter())
            .map(|t| (t.call.clone(), t.status.clone()))
            .collect(),
        drones: drones.len(),
    };
    Some((request, callable.len() as u32))
}

/// The Supervisor's messages: its configuration prompt, the few-shot cycles, then the request.
pub fn supervisor_messages(user: String) -> Vec<ChatMessage> {
    let mut messages = supervisor_fixed_messages();
    messages.push(ChatMessage::user(user));
    messages
}

/// The beginning every monolithic request shares: its configuration prompt.
pub fn monolithic_fixed_messages() -> Vec<ChatMessage> {
    vec![ChatMessage::system(texts::MONOLITHIC)]
}

/// The beginning every Supervisor request shares: its configuration prompt and the few-shot
/// cycles.
pub fn supervisor_fixed_messages() -> Vec<ChatMessage> {
    let mut messages = vec![ChatMessage::system(texts::SUPERVISOR)];
    for example in texts::supervisor_examples().unwrap_or_default() {
        messages.push(ChatMessage::user(example.context));
        messages.push(ChatMessage::assistant(example.reply.to_string()));
    }
    messages
}

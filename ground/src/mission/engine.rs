//! The mission engine: Coordinator, Supervisor (or the monolithic model), the repair loop, the
//! pending plan, the two memories, automatic replans, and the bookkeeping of what was sent.

use super::directives::{self, Directive};
use super::grounding;
use super::input::MissionInputs;
use super::log::{MissionLog, Record};
use super::resolve::{claimed_points, nearest_first, position_of, resolve};
use super::untrusted;
use crate::link::GroundLink;
use crate::safety::{CheckedAction, SafetyGate};
use crate::swarm::SwarmChange;
use crate::task_guard::AbortOnDrop;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tacos_llm::{ChatMessage, ChatReply, ChatRequest, LlmBackend, LlmError, ResponseSchema};
use tacos_prompts::render::{self, DroneLine, HistoryEntry, TaskStatus};
use tacos_prompts::schema::{self, Output};
use tacos_prompts::{
    ActionName, Call, CoordinatorReply, MonolithicReply, ReplyError, SupervisorReply, texts,
};
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionState, FailureReason, TargetObservation, WorldEvent};
use tacos_shared::{DroneId, DroneMode};
use tokio::sync::{mpsc, watch};

/// The ablation modes of the paper.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Coordinator + Supervisor, the Supervisor sees the Coordinator's reasoning.
    Tacos,
    /// The Supervisor does not get the Coordinator's reasoning.
    Wor,
    /// One model plans and executes; its history keeps executed actions only.
    Mnl,
}

impl Mode {
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Tacos => "tacos",
            Mode::Wor => "wor",
            Mode::Mnl => "mnl",
        }
    }
}

impl std::str::FromStr for Mode {
    type Err = String;
    fn from_str(s: &str) -> Result<Mode, String> {
        match s {
            "tacos" => Ok(Mode::Tacos),
            "wor" => Ok(Mode::Wor),
            "mnl" => Ok(Mode::Mnl),
            other => Err(format!("unknown mode {other:?} (tacos, wor, mnl)")),
        }
    }
}

#[derive(Debug, Clone)]
pub struct MissionConfig {
    pub mode: Mode,
    /// How many times a rejected or unparsable reply goes back to its model.
    pub max_repairs: u32,
    /// A Supervisor cycle runs at the latest this long after the previous one while a plan runs.
    pub cycle_timeout: Duration,
    /// A plan is abandoned after this many Supervisor cycles.
    pub max_cycles_per_plan: u32,
    /// A plan is abandoned when one of its tasks has failed this many times: a goal that cannot
    /// be reached is reported to the pilot, not retried until the cycle limit.
    pub max_task_failures: u32,
    pub coordinator_max_tokens: u32,
    pub supervisor_max_tokens: u32,
    pub temperature: f32,
    pub seed: Option<u64>,
}

impl Default for MissionConfig {
    fn default() -> Self {
        MissionConfig {
            mode: Mode::Tacos,
            max_repairs: 2,
            cycle_timeout: Duration::from_secs(10),
            max_cycles_per_plan: 30,
            max_task_failures: 3,
            coordinator_max_tokens: 600,
            supervisor_max_tokens: 400,
            temperature: 0.0,
            seed: Some(7),
        }
    }
}

#[derive(Debug, thiserror::Error)]
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
    #[error("not sending {action} to {drone}: the pilot gave a direct command meanwhile")]
    Overridden { drone: String, action: String },
    #[error("sending {action} to {drone} failed: {reason}")]
    Send {
        drone: String,
        action: String,
        reason: String,
    },
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
    Rejected {
        call: String,
        reason: String,
    },
    Sent {
        drone: String,
        action: String,
        seq: u64,
    },
    Outcome {
        drone: String,
        action: String,
        outcome: String,
    },
    Event(String),
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

#[derive(Debug, Clone)]
struct PlanTask {
    call: Call,
    status: TaskStatus,
    sent: Option<(DroneId, u64)>,
    /// Times this task has failed; the plan is given up at `max_task_failures`.
    failures: u32,
}

#[derive(Debug, Clone)]
struct ActivePlan {
    reasoning: String,
    tasks: Vec<PlanTask>,
    /// The Supervisor's memory for this plan; cleared with it.
    memory: Vec<String>,
    cycles: u32,
    /// Since when nothing of the plan has been running and nothing could start.
    stuck_since: Option<Instant>,
}

/// How long a plan may have nothing running and nothing that can start before it is given up
/// (long enough for a drone's link to come back, or an outcome to arrive).
const STUCK_AFTER: Duration = Duration::from_secs(20);

/// The monolithic variant's state. The model's prompt holds the instructions and the executed
/// actions only; `tasks` is the engine's own bookkeeping of what it issued for them.
#[derive(Debug, Default)]
struct Monolithic {
    instructions: Vec<String>,
    executed: Vec<String>,
    /// Every call issued for the current instructions, with its status.
    tasks: Vec<PlanTask>,
    /// The number of the next fresh task id (`A<n>`) offered to the model.
    next_task: u32,
    /// The model's last reply said that its actions carry out the instructions, and every call
    /// in it passed the checks. There is no plan to hold the model to, so the engine checks
    /// what it can: the instructions count as carried out only once every action issued for
    /// them has finished successfully. A failure, a lost or joined drone, or a new instruction
    /// withdraws the claim and the model is asked again.
    claimed_done: bool,
    active: bool,
    cycles: u32,
}

/// Asks models: the backend, the repair loop's bounds, and where calls are recorded.
struct Caller {
    backend: Arc<dyn LlmBackend>,
    /// Told of every call in flight, so a simulation holds real time meanwhile.
    link: Arc<GroundLink>,
    log: Arc<MissionLog>,
    updates: mpsc::UnboundedSender<MissionUpdate>,
    max_repairs: u32,
    temperature: f32,
    seed: Option<u64>,
}

/// The statistics of a mission task whose input has been closed: it ends after any model call
/// in flight; a task that does not end within 5 s, or panicked, reports none.
pub async fn stats_when_done(task: tokio::task::JoinHandle<MissionStats>) -> MissionStats {
    match tokio::time::timeout(std::time::Duration::from_secs(5), task).await {
        Ok(Ok(stats)) => stats,
        _ => MissionStats::default(),
    }
}

pub struct Mission {
    cfg: MissionConfig,
    caller: Caller,
    gate: SafetyGate,
    link: Arc<GroundLink>,
    log: Arc<MissionLog>,
    updates: mpsc::UnboundedSender<MissionUpdate>,
    targets: watch::Receiver<Vec<TargetObservation>>,
    history: Vec<HistoryEntry>,
    events: Vec<String>,
    plan: Option<ActivePlan>,
    mnl: Monolithic,
    stats: MissionStats,
    /// Counts the direct commands `PilotInput` carried out; a change the engine has not yet
    /// seen means a model's proposal is older than the pilot's command (see `mission::input`).
    overrides: watch::Receiver<u64>,
}

/// Logs where every live drone is, twice a second, for `tacos-ground plot`, until aborted.
async fn log_positions(link: Arc<GroundLink>, log: Arc<MissionLog>) {
    let mut tick = tokio::time::interval(Duration::from_millis(500));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tick.tick().await;
        let records: Vec<Record> = {
            let view = link.view();
            view.drones()
                .filter(|e| e.alive)
                .filter_map(|entry| {
                    let s = entry.status.as_ref()?;
                    Some(Record::Position {
                        drone: entry.id.to_string(),
                        x: s.position.x,
                        y: s.position.y,
                        z: s.position.z,
                        speed: s.velocity.norm(),
                    })
                })
                .collect()
        };
        for record in records {
            log.note(record);
        }
    }
}

/// The result of checking one reply: what may be done, and why the rest may not.
struct Checked<U> {
    accepted: U,
    rejections: Vec<String>,
    /// The schema for the repair round, when the reply missed something the grammar can hold
    /// the next one to; `None`: the same schema again.
    narrowed: Option<serde_json::Value>,
}

impl Mission {
    pub async fn new(
        cfg: MissionConfig,
        backend: Arc<dyn LlmBackend>,
        gate: SafetyGate,
        link: Arc<GroundLink>,
        log: Arc<MissionLog>,
        updates: mpsc::UnboundedSender<MissionUpdate>,
    ) -> Result<Mission, crate::link::LinkError> {
        let targets = link.watch_targets().await?;
        let drones = {
            let view = link.view();
            gate.scenario()
                .drones
                .iter()
                .filter(|d| view.get(&d.id).is_some())
                .map(|d| d.id.to_string())
                .collect()
        };
        log.note(Record::MissionStart {
            mode: cfg.mode.as_str().into(),
            backend: backend.describe(),
            scenario: gate.scenario().name.clone(),
            drones,
        });
        let caller = Caller {
            backend,
            link: link.clone(),
            log: log.clone(),
            updates: updates.clone(),
            max_repairs: cfg.max_repairs,
            temperature: cfg.temperature,
            seed: cfg.seed,
        };
        Ok(Mission {
            cfg,
            caller,
            gate,
            link,
            log,
            updates,
            targets,
            history: Vec::new(),
            events: Vec::new(),
            plan: None,
            mnl: Monolithic::default(),
            stats: MissionStats::default(),
            // No sender: never changes until `run_with` brings the pilot's.
            overrides: watch::channel(0).1,
        })
    }

    pub fn stats(&self) -> &MissionStats {
        &self.stats
    }

    /// True while a plan (or the monolithic model's work) is under way.
    pub fn busy(&self) -> bool {
        match self.cfg.mode {
            Mode::Mnl => self.mnl.active,
            _ => self.plan.is_some(),
        }
    }

    fn tell(&self, update: MissionUpdate) {
        let _ = self.updates.send(update);
    }

    /// Runs the mission until `inputs` closes: pilot lines in, cycles on every change.
    pub async fn run(self, inputs: mpsc::Receiver<String>) -> MissionStats {
        let (_no_overrides, overrides) = watch::channel(0);
        self.run_with(MissionInputs {
            lines: inputs,
            overrides,
        })
        .await
    }

    /// As `run`, with the direct commands of a `PilotInput` carried out beside the engine.
    pub async fn run_with(mut self, inputs: MissionInputs) -> MissionStats {
        let MissionInputs {
            lines: mut inputs,
            overrides: mut wake,
        } = inputs;
        self.overrides = wake.clone();
        let mut wake_open = true;
        let mut membership = self.link.membership();
        let mut events = match self.link.watch_events().await {
            Ok(rx) => rx,
            Err(e) => {
                self.tell(MissionUpdate::Error(e.to_string()));
                return self.stats;
            }
        };
        // Positions are sampled beside the engine, which waits minutes on a model call while
        // the drones fly on; the guard stops the sampler with the mission.
        let _positions = AbortOnDrop(tokio::spawn(log_positions(
            self.link.clone(),
            self.log.clone(),
        )));
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        // After a model call, one tick, not a burst of the ones missed.
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let mut last_cycle = self.link.clock().instant();
        loop {
            let mut cycle_due = false;
            tokio::select! {
                changed = wake.changed(), if wake_open => if changed.is_err() {
                    wake_open = false;
                },
                line = inputs.recv() => match line {
                    Some(text) => {
                        // The pilot's direct command came before this line.
                        self.take_override();
                        if let Err(e) = self.pilot(&text).await {
                            self.tell(MissionUpdate::Error(e.to_string()));
                        }
                        cycle_due = self.busy();
                    }
                    None => break,
                },
                change = membership.recv() => match change {
                    Ok(change) => {
                        if let Err(e) = self.membership_changed(change).await {
                            self.tell(MissionUpdate::Error(e.to_string()));
                        }
                        cycle_due = self.busy();
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => break,
                },
                event = events.recv() => if let Some(event) = event && self.world_event(event) {
                    cycle_due = self.busy();
                },
                _ = tick.tick() => {
                    cycle_due = self.poll_outcomes() || (self.busy() && self.link.clock().instant().duration_since(last_cycle) >= self.cfg.cycle_timeout);
                }
            }
            self.take_override();
            if cycle_due && self.busy() {
                last_cycle = self.link.clock().instant();
                if let Err(e) = self.cycle().await {
                    self.tell(MissionUpdate::Error(e.to_string()));
                }
            }
        }
        self.log.note(Record::MissionEnd {
            outcome: "pilot closed the session".into(),
        });
        self.stats
    }

    /// After a direct command carried out by `PilotInput`: the models' plan ends, as with one
    /// the engine carries out itself. True when there was one.
    fn take_override(&mut self) -> bool {
        if !self.overrides.has_changed().unwrap_or(false) {
            return false;
        }
        self.overrides.borrow_and_update();
        if let Some(plan) = self.plan.take() {
            self.finish_plan(plan, "interrupted by a direct command");
        }
        self.mnl.active = false;
        true
    }

    /// A line from the pilot: a direct command, or an instruction for the models.
    pub async fn pilot(&mut self, text: &str) -> Result<(), MissionError> {
        let text = text.trim();
        if text.is_empty() {
            return Ok(());
        }
        let drones = self.swarm_ids();
        if let Some(directive) = directives::parse(text, &drones) {
            self.direct(text, directive).await;
            return Ok(());
        }
        self.log.note(Record::Pilot {
            text: text.to_owned(),
        });
        match self.cfg.mode {
            Mode::Mnl => {
                self.mnl.instructions.push(text.to_owned());
                self.mnl.active = true;
                self.mnl.cycles = 0;
                self.mnl.claimed_done = false;
                self.mnl.tasks.retain(|t| t.status == TaskStatus::Running);
                Ok(())
            }
            Mode::Tacos | Mode::Wor => {
                self.history.push(HistoryEntry::Pilot(text.to_owned()));
                self.coordinate(text).await
            }
        }
    }

    async fn direct(&mut self, text: &str, directive: Directive) {
        let (targets, action): (Vec<String>, Action) = match directive {
            Directive::LandAll => (
                self.link
                    .view()
                    .alive_ids()
                    .iter()
                    .map(|d| d.to_string())
                    .collect(),
                Action::Land,
            ),
            Directive::HoldAll => (
                self.link
                    .view()
                    .alive_ids()
                    .iter()
                    .map(|d| d.to_string())
                    .collect(),
                Action::Hold,
            ),
            Directive::Land(d) => (vec![d], Action::Land),
            Directive::Hold(d) => (vec![d], Action::Hold),
        };
        let mut outcomes = Vec::new();
        for drone in targets {
            let checked = {
                let view = self.link.view();
                self.gate
                    .check(&view, &drone, &action, self.link.clock().instant())
            };
            match checked {
                Ok(c) => match self.send(&c, None).await {
                    Ok(seq) => outcomes.push(format!("{drone}: sent #{seq}")),
                    Err(e) => outcomes.push(format!("{drone}: {e}")),
                },
                Err(r) => outcomes.push(format!("{drone}: refused: {r}")),
            }
        }
        let outcome = outcomes.join("; ");
        self.log.note(Record::Direct {
            text: text.to_owned(),
            outcome: outcome.clone(),
        });
        self.tell(MissionUpdate::Event(format!(
            "direct command {text:?}: {outcome}"
        )));
        // A direct command overrides whatever the models were doing.
        if let Some(plan) = self.plan.take() {
            self.finish_plan(plan, "interrupted by a direct command");
        }
        self.mnl.active = false;
    }

    async fn membership_changed(&mut self, change: SwarmChange) -> Result<(), MissionError> {
        let text = match &change {
            SwarmChange::Joined(d) => format!("{d} joined the swarm"),
            SwarmChange::Left(d) => format!("{d} became unavailable"),
            SwarmChange::Status(_) => return Ok(()),
        };
        self.log.note(Record::Event { text: text.clone() });
        self.tell(MissionUpdate::Event(text.clone()));
        // What the lost drone leaves undone, named in the replan's instruction so the
        // Coordinator hands exactly that on (a done start_tracking is still work while the
        // drone follows: without this, the chase would end with its tracker).
        let lost_work = match &change {
            SwarmChange::Left(d) => {
                let following = self.following_of(d);
                self.fail_tasks_of(d, following.as_deref(), "drone lost");
                self.unfinished_work_of(d, following)
            }
            _ => Vec::new(),
        };
        match self.cfg.mode {
            Mode::Mnl => {
                self.mnl.executed.push(format!("event: {text}"));
                self.mnl.claimed_done = false;
                Ok(())
            }
            Mode::Tacos | Mode::Wor => {
                self.history.push(HistoryEntry::Event(text.clone()));
                // Replan only when there is work that the change may affect.
                if self.plan.is_some() || !lost_work.is_empty() {
                    self.log.note(Record::Replan {
                        reason: text.clone(),
                    });
                    let subtasks = if lost_work.is_empty() {
                        String::new()
                    } else {
                        format!(" ({})", lost_work.join(", "))
                    };
                    self.coordinate(&format!("(automatic replan) {text}: reassign its unfinished subtasks{subtasks} and keep the mission going")).await
                } else {
                    Ok(())
                }
            }
        }
    }

    /// Takes in a world event whose names are the scenario's; one that is not is logged and
    /// left out of every prompt. True when it was taken in.
    fn world_event(&mut self, event: WorldEvent) -> bool {
        let event = match untrusted::checked_event(event, self.gate.scenario()) {
            Ok(event) => event,
            Err(why) => {
                tracing::warn!(%why, "world event ignored");
                self.log.note(Record::Event {
                    text: format!("world event ignored: {why}"),
                });
                return false;
            }
        };
        let text = event.to_string();
        self.events.push(text.clone());
        self.log.note(Record::Event { text: text.clone() });
        self.tell(MissionUpdate::Event(text.clone()));
        match self.cfg.mode {
            Mode::Mnl => self.mnl.executed.push(format!("event: {text}")),
            _ => self.history.push(HistoryEntry::Event(text)),
        }
        true
    }

    /// The targets seen now that the scenario has: a name from the network reaches a prompt
    /// only when it is one of the map's (`untrusted`).
    fn visible_targets(&self) -> Vec<TargetObservation> {
        let seen = self.targets.borrow();
        let known = untrusted::known_targets(&seen, self.gate.scenario());
        let unknown = seen.len() - known.len();
        if unknown > 0 {
            tracing::debug!(
                unknown,
                "observations of targets the map does not have left out"
            );
        }
        known
    }

    /// Fails `drone`'s running tasks, and its done start_tracking while it still followed the
    /// target (tracking goes on after the task is done): failed tasks may start on any drone.
    /// `following`: the target it followed ([`Self::following_of`]).
    fn fail_tasks_of(&mut self, drone: &DroneId, following: Option<&str>, why: &str) {
        let tasks = self
            .plan
            .iter_mut()
            .flat_map(|p| p.tasks.iter_mut())
            .chain(self.mnl.tasks.iter_mut());
        for t in tasks.filter(|t| t.sent.as_ref().is_some_and(|(d, _)| d == drone)) {
            let still_following = t.status == TaskStatus::Done
                && t.call.action == ActionName::StartTracking
                && following == t.call.target_name();
            if t.status == TaskStatus::Running || still_following {
                t.status = TaskStatus::Failed(why.to_owned());
            }
        }
    }

    /// The target `drone` was following when last heard of: its last action is a start_tracking
    /// that was under way, done, or ended by the autopilot link's loss (not by losing the
    /// target, and not replaced by a newer action).
    fn following_of(&self, drone: &DroneId) -> Option<String> {
        let view = self.link.view();
        let progress = view.get(drone)?.status.as_ref()?.action.as_ref()?;
        let Action::StartTracking { target } = &progress.action else {
            return None;
        };
        match &progress.state {
            ActionState::Running { .. }
            | ActionState::Done
            | ActionState::Failed(FailureReason::AutopilotLinkLost) => Some(target.clone()),
            ActionState::Failed(_) => None,
        }
    }

    /// `drone`'s unfinished work in the plan (its tasks not done: failed with it, or not yet
    /// started), and the target it was following if no such task names it, as call texts.
    fn unfinished_work_of(&self, drone: &DroneId, following: Option<String>) -> Vec<String> {
        let mut work: Vec<String> = Vec::new();
        let mut tracking_named = false;
        for t in self.plan.iter().flat_map(|p| p.tasks.iter()) {
            let its = match &t.sent {
                Some((d, _)) => d == drone,
                None => t.call.drone == drone.as_str(),
            };
            if its && t.status != TaskStatus::Done {
                tracking_named |= t.call.action == ActionName::StartTracking
                    && following.as_deref() == t.call.target_name();
                work.push(t.call.to_string());
            }
        }
        if let Some(target) = following.filter(|_| !tracking_named) {
            work.push(format!("{drone} start_tracking({target})"));
        }
        work
    }

    /// Looks for finished actions; true when any task changed state.
    fn poll_outcomes(&mut self) -> bool {
        let mut finished: Vec<(String, String, String)> = Vec::new();
        {
            let view = self.link.view();
            let tasks = self
                .plan
                .iter_mut()
                .flat_map(|p| p.tasks.iter_mut())
                .chain(self.mnl.tasks.iter_mut());
            // Running tasks, and tracking that is done (the drone reached its station) but goes
            // on: a target lost later fails the task, so the Supervisor can give it again.
            let watched = |t: &PlanTask| {
                t.status == TaskStatus::Running
                    || (t.status == TaskStatus::Done && t.call.action == ActionName::StartTracking)
            };
            for task in tasks.filter(|t| watched(t)) {
                let Some((drone, seq)) = &task.sent else {
                    continue;
                };
                let running = task.status == TaskStatus::Running;
                let status = view.get(drone).and_then(|e| e.status.as_ref());
                let progress = status.and_then(|s| s.action.as_ref());
                let refused = status
                    .and_then(|s| s.refused.as_ref())
                    .filter(|r| r.seq == *seq && running);
                let new = match (refused, progress) {
                    (Some(r), _) => Some(TaskStatus::Failed(format!(
                        "refused by the drone: {}",
                        r.why
                    ))),
                    (None, Some(p)) if p.seq == *seq => match &p.state {
                        ActionState::Done if running => Some(TaskStatus::Done),
                        ActionState::Failed(why) => Some(TaskStatus::Failed(why.to_string())),
                        _ => None,
                    },
                    (None, Some(p)) if p.seq > *seq && running => {
                        Some(TaskStatus::Failed("replaced by a newer action".into()))
                    }
                    _ => None,
                };
                if let Some(status) = new {
                    let outcome = match &status {
                        TaskStatus::Done => "done".to_owned(),
                        TaskStatus::Failed(why) => format!("failed: {why}"),
                        _ => String::new(),
                    };
                    finished.push((drone.to_string(), task.call.to_string(), outcome));
                    self.log.note(Record::ActionOutcome {
                        drone: drone.to_string(),
                        task: Some(task.call.task.clone()),
                        seq: *seq,
                        outcome: finished.last().map(|f| f.2.clone()).unwrap_or_default(),
                    });
                    if matches!(status, TaskStatus::Failed(_)) {
                        task.failures += 1;
                    }
                    task.status = status;
                }
            }
        }
        // After the outcomes: a task that just finished may make the next one's effect hold.
        self.mark_satisfied_tasks(&mut finished);
        for (drone, action, outcome) in &finished {
            self.tell(MissionUpdate::Outcome {
                drone: drone.clone(),
                action: action.clone(),
                outcome: outcome.clone(),
            });
            match self.cfg.mode {
                Mode::Mnl => {
                    self.mnl.executed.push(format!("{action}: {outcome}"));
                    if outcome != "done" {
                        self.mnl.claimed_done = false;
                    }
                }
                _ => {
                    if let Some(plan) = self.plan.as_mut() {
                        plan.memory.push(format!("{action}: {outcome}"));
                    }
                }
            }
        }
        if let Some(plan) = self.plan.take() {
            let given_up = plan
                .tasks
                .iter()
                .find(|t| t.failures >= self.cfg.max_task_failures)
                .map(|t| match &t.status {
                    TaskStatus::Failed(why) => {
                        format!("{} failed {} times (last: {why})", t.call, t.failures)
                    }
                    _ => format!("{} failed {} times", t.call, t.failures),
                });
            if plan.tasks.iter().all(|t| t.status == TaskStatus::Done) {
                self.finish_plan(plan, "complete");
            } else if let Some(why) = given_up {
                self.finish_plan(plan, &format!("abandoned: {why}"));
                self.tell(MissionUpdate::Error(format!(
                    "the plan was given up: {why}"
                )));
            } else {
                self.plan = Some(plan);
            }
        }
        self.judge_monolithic();
        !finished.is_empty()
    }

    /// The plan's calls that could start now: tasks not started, on their own drone; failed
    /// tasks, on any available drone; each only if its drone is idle-ready (not busy), the call
    /// resolves, and the safety gate would let it through.
    fn startable_calls(&self) -> Vec<Call> {
        let Some(plan) = self.plan.as_ref() else {
            return Vec::new();
        };
        // Before the view is locked: `swarm_ids` locks it too, and the lock is not reentrant.
        let swarm = self.swarm_ids();
        let pending = self.drones_with_pending_actions();
        let view = self.link.view();
        let now = self.link.clock().instant();
        let visible = self.visible_targets();
        let ready = |drone: &str| {
            DroneId::new(drone)
                .ok()
                .and_then(|id| view.get(&id))
                .is_some_and(|e| e.ready(now) && !pending.contains(&e.id))
        };
        let mut out = Vec::new();
        // No order is imposed here: the plan's temporal dependencies are the Supervisor's to
        // infer (the paper's division of labour); the drone's mode rules what is possible.
        for task in &plan.tasks {
            let drones: Vec<String> = match &task.status {
                TaskStatus::NotStarted => vec![task.call.drone.clone()],
                TaskStatus::Failed(_) => swarm.clone(),
                _ => continue,
            };
            for drone in drones.into_iter().filter(|d| ready(d)) {
                let call = Call {
                    drone: drone.clone(),
                    ..task.call.clone()
                };
                let claimed = claimed_points(&view, &drone, now);
                let Ok(action) = resolve(
                    &call,
                    self.gate.scenario(),
                    &visible,
                    &claimed,
                    position_of(&view, &drone),
                ) else {
                    continue;
                };
                if self.gate.check(&view, &drone, &action, now).is_ok() {
                    out.push(call);
                }
            }
        }
        out
    }

    /// Drones with an action the engine sent and has not yet seen finish. A drone's status lags
    /// a send by up to a status period, so right after a cycle it can still look idle and ready:
    /// offering it again would have the model choose a call that is stale by the time it answers.
    fn drones_with_pending_actions(&self) -> Vec<DroneId> {
        self.plan
            .iter()
            .flat_map(|p| p.tasks.iter())
            .chain(self.mnl.tasks.iter())
            .filter(|t| t.status == TaskStatus::Running)
            .filter_map(|t| t.sent.as_ref().map(|(d, _)| d.clone()))
            .collect()
    }

    /// A task whose effect already holds is done without flying it: a take-off for a drone that
    /// is airborne and idle in the air, a landing or hold for a drone resting on the ground, a
    /// goto for a drone hovering at its point.
    /// Plans from models repeat such calls; sending them would only be refused by the drone.
    fn mark_satisfied_tasks(&mut self, finished: &mut Vec<(String, String, String)>) {
        let visible = self.visible_targets();
        let Some(plan) = self.plan.as_mut() else {
            return;
        };
        let view = self.link.view();
        let now = self.link.clock().instant();
        // As close as the drone itself calls a goto done.
        let arrive = (2.0 * self.gate.scenario().limits.drone_radius).max(0.2);
        // Only a task whose earlier tasks for the same drone are all done: "take off, then land"
        // must not count the landing as done before the take-off.
        let mut open_before: std::collections::HashSet<String> = std::collections::HashSet::new();
        for task in plan.tasks.iter_mut() {
            let blocked = open_before.contains(&task.call.drone);
            if task.status != TaskStatus::Done {
                open_before.insert(task.call.drone.clone());
            }
            if blocked || task.status != TaskStatus::NotStarted {
                continue;
            }
            let Some(entry) = DroneId::new(&task.call.drone)
                .ok()
                .and_then(|id| view.get(&id))
            else {
                continue;
            };
            let mode = entry.effective_mode(now);
            let already_there = task.call.action == ActionName::Goto
                && mode == DroneMode::Flying
                && entry.status.as_ref().is_some_and(|status| {
                    let claimed = claimed_points(&view, &task.call.drone, now);
                    matches!(
                        resolve(
                            &task.call,
                            self.gate.scenario(),
                            &visible,
                            &claimed,
                            position_of(&view, &task.call.drone),
                        ),
                        Ok(Action::Goto { target }) if (status.position - target).norm() <= arrive
                    )
                });
            if (effect_holds(task.call.action, mode) || already_there) && !entry.busy() {
                task.status = TaskStatus::Done;
                let what = if already_there {
                    "already there: nothing to do".to_owned()
                } else {
                    format!("already {mode}: nothing to do")
                };
                self.log.note(Record::Event {
                    text: format!("{}: {what}", task.call),
                });
                finished.push((task.call.drone.clone(), task.call.to_string(), what));
            }
        }
    }

    fn finish_plan(&mut self, plan: ActivePlan, how: &str) {
        for t in plan.tasks.iter().filter(|t| t.status == TaskStatus::Done) {
            self.history.push(HistoryEntry::Executed {
                call: t.call.clone(),
                outcome: "done".into(),
            });
        }
        if how == "complete" {
            self.stats.cycles_per_plan.push(plan.cycles);
            self.log.note(Record::PlanComplete {
                cycles: plan.cycles,
            });
            self.tell(MissionUpdate::PlanComplete {
                cycles: plan.cycles,
            });
        } else {
            self.log.note(Record::Event {
                text: format!("plan ended: {how}"),
            });
            self.tell(MissionUpdate::Event(format!("plan ended: {how}")));
        }
    }

    // ---- state for the prompts ---------------------------------------------------------------

    fn drone_lines(&self) -> Vec<DroneLine> {
        let view = self.link.view();
        let now = self.link.clock().instant();
        self.gate
            .scenario()
            .drones
            .iter()
            .filter_map(|slot| view.get(&slot.id))
            .map(|e| {
                let status = e.status.as_ref();
                let (action, state) = match status.and_then(|s| s.action.as_ref()) {
                    Some(p) => (
                        Some(
                            format!("{} {}", p.task_id.clone().unwrap_or_default(), p.action)
                                .trim()
                                .to_owned(),
                        ),
                        Some(match &p.state {
                            ActionState::Running { progress } => {
                                format!("running {:.0}%", progress * 100.0)
                            }
                            ActionState::Done => "done".into(),
                            ActionState::Failed(why) => format!("failed: {why}"),
                        }),
                    ),
                    None => (None, None),
                };
                DroneLine {
                    id: e.id.to_string(),
                    mode: e.effective_mode(now),
                    position: status.map(|s| s.position).unwrap_or_default(),
                    speed: status.map_or(0.0, |s| s.velocity.norm()),
                    action,
                    state,
                }
            })
            .collect()
    }

    fn world_text(&self) -> String {
        render::world(
            &self.gate.scenario().world,
            &self.visible_targets(),
            &self.events,
        )
    }

    /// The drones of this swarm: those the ground has heard from, in scenario order.
    fn swarm_ids(&self) -> Vec<String> {
        let view = self.link.view();
        self.gate
            .scenario()
            .drones
            .iter()
            .filter(|d| view.get(&d.id).is_some())
            .map(|d| d.id.to_string())
            .collect()
    }

    /// The swarm's drones a plan may use now: all but the unavailable ones (lost link, failed),
    /// in the scenario's order.
    fn available_ids(&self) -> Vec<String> {
        // Before the view is locked: `swarm_ids` locks it too.
        let ids = self.swarm_ids();
        let view = self.link.view();
        let now = self.link.clock().instant();
        ids.into_iter()
            .filter(|d| {
                DroneId::new(d)
                    .ok()
                    .and_then(|id| view.get(&id))
                    .is_some_and(|e| e.effective_mode(now) != DroneMode::Unavailable)
            })
            .collect()
    }

    fn enums(&self) -> (Vec<String>, Vec<String>) {
        let s = self.gate.scenario();
        let drones = self.swarm_ids();
        let places = s
            .world
            .landmarks
            .iter()
            .map(|l| l.name.clone())
            .chain(self.trackable())
            .collect();
        (drones, places)
    }

    /// The targets a drone may be asked to follow: the scenario's targets that are not hidden.
    fn trackable(&self) -> Vec<String> {
        self.gate
            .scenario()
            .targets
            .iter()
            .filter(|t| t.hidden_at.is_none())
            .map(|t| t.name.clone())
            .collect()
    }

    /// The targets that drones follow now (tracking, by their status).
    fn followed_targets(&self) -> Vec<String> {
        let view = self.link.view();
        let now = self.link.clock().instant();
        view.drones()
            .filter(|e| e.effective_mode(now) == DroneMode::Tracking)
            .filter_map(|e| match &e.status.as_ref()?.action.as_ref()?.action {
                Action::StartTracking { target } => Some(target.clone()),
                _ => None,
            })
            .collect()
    }

    fn plan_lines(&self) -> Vec<(Call, TaskStatus)> {
        self.plan
            .iter()
            .flat_map(|p| p.tasks.iter())
            .map(|t| (t.call.clone(), t.status.clone()))
            .collect()
    }

    // ---- the layers ----------------------------------------------------------------------------

    /// Runs the Coordinator for `instruction`; its plan replaces the current one (the pending
    /// plan was in its prompt).
    async fn coordinate(&mut self, instruction: &str) -> Result<(), MissionError> {
        let pending: Vec<(Call, TaskStatus)> = self
            .plan_lines()
            .into_iter()
            .filter(|(_, s)| *s != TaskStatus::Done)
            .collect();
        let (drones, places) = self.enums();
        let names: Vec<String> = drones.iter().chain(&places).cloned().collect();
        let named = render::named_in(instruction, &names);
        let pending_places: Vec<String> = pending
            .iter()
            .filter_map(|(c, _)| c.target_name().map(str::to_owned))
            .collect();
        let scope = grounding::places_in_scope(&places, &named, &pending_places);
        // A plan for a drone that cannot fly it would wait for ever: the grammar offers only the
        // available drones, and the reply check holds a server that ignores the schema to them.
        let available = self.available_ids();
        if available.is_empty() {
            return Err(MissionError::NoDroneAvailable);
        }
        // A target the instruction asks to be followed must be tracked by the plan (or be
        // followed already); a drone named beside it is suggested only if it can fly.
        let follow: Vec<grounding::FollowAsked> =
            grounding::follow_asked(instruction, &drones, &self.trackable())
                .into_iter()
                .map(|a| grounding::FollowAsked {
                    drone: a.drone.filter(|d| available.contains(d)),
                    ..a
                })
                .collect();
        let followed = self.followed_targets();
        let user = render::coordinator_request(
            &render::swarm(&self.drone_lines()),
            &self.world_text(),
            &render::plan(&pending),
            &render::history(&self.history),
            instruction,
            &named,
        );
        let messages = coordinator_messages(user);
        let in_scope = |name: &String| scope.as_ref().is_none_or(|s| s.contains(name));
        let trackable: Vec<String> = self.trackable().into_iter().filter(in_scope).collect();
        let schema = schema::build(
            Output::Coordinator,
            &available,
            scope.as_ref().unwrap_or(&places),
            &trackable,
        );
        let first_schema = schema.clone();
        self.tell(MissionUpdate::Thinking {
            layer: "coordinator",
        });
        self.stats.coordinator_calls += 1;
        let scenario = self.gate.scenario().clone();
        let visible = self.visible_targets();
        let checked = self
            .caller
            .ask(
                &mut self.stats,
                "coordinator",
                messages,
                Output::Coordinator,
                schema,
                self.cfg
                    .coordinator_max_tokens
                    .max(schema::token_budget(Output::Coordinator, drones.len())),
                CoordinatorReply::parse,
                |reply: &CoordinatorReply| {
                    let mut rejections = Vec::new();
                    let mut plan = Vec::new();
                    for call in &reply.plan {
                        let off = scope
                            .as_ref()
                            .and_then(|s| grounding::off_scope(call, &places, s));
                        let checked = match off {
                            Some(why) => Err(why),
                            None if drones.contains(&call.drone)
                                && !available.contains(&call.drone) =>
                            {
                                Err(format!(
                                    "{} is unavailable; the drones available are: {}",
                                    call.drone,
                                    available.join(", ")
                                ))
                            }
                            None => check_static(call, &scenario, &visible),
                        };
                        match checked {
                            Ok(()) => plan.push(call.clone()),
                            Err(why) => rejections.push(format!("{call}: {why}")),
                        }
                    }
                    if reply.plan.is_empty() {
                        rejections.push("the plan is empty".into());
                    }
                    let missing = grounding::untracked(&follow, &plan, &followed);
                    // The repair round's grammar opens the plan with the missing tracking.
                    let narrowed = (!missing.is_empty()).then(|| {
                        let required: Vec<schema::RequiredCall> = missing
                            .iter()
                            .map(|a| schema::RequiredCall {
                                drones: a
                                    .drone
                                    .clone()
                                    .map_or_else(|| available.clone(), |d| vec![d]),
                                action: "start_tracking",
                                target: a.target.clone(),
                            })
                            .collect();
                        schema::requiring(&first_schema, &required)
                    });
                    rejections.extend(missing.iter().map(grounding::FollowAsked::missing_text));
                    Checked {
                        accepted: (reply.reasoning.clone(), plan),
                        rejections,
                        narrowed,
                    }
                },
            )
            .await?;
        let (reasoning, calls) = checked;
        if calls.is_empty() {
            // Every call of the last attempt was refused: the plan in force (if any) stays, and
            // the refusals are in the log's repair requests.
            return Err(MissionError::NoValidReply {
                layer: "coordinator",
                attempts: self.caller.max_repairs + 1,
                reason: "no call of its plan passed the checks".into(),
            });
        }
        let (calls, repeats) = without_repeated_work(calls);
        for call in repeats {
            let text = format!("{call}: repeats {}'s previous task: dropped", call.drone);
            self.log.note(Record::Event { text: text.clone() });
            self.tell(MissionUpdate::Event(text));
        }
        let calls = self.with_implied_takeoffs(calls);
        self.log.note(Record::Plan {
            reasoning: reasoning.clone(),
            plan: serde_json::to_value(&calls).unwrap_or_default(),
        });
        self.tell(MissionUpdate::Plan {
            reasoning: reasoning.clone(),
            calls: calls.iter().map(|c| c.to_string()).collect(),
        });
        self.history.push(HistoryEntry::Plan {
            reasoning: reasoning.clone(),
            plan: calls.clone(),
        });
        // Tasks already running keep their status when the new plan repeats them.
        let running: HashMap<(String, String), PlanTask> = self
            .plan
            .take()
            .into_iter()
            .flat_map(|p| p.tasks)
            .filter(|t| t.status == TaskStatus::Running)
            .map(|t| (same_work(&t.call), t))
            .collect();
        let tasks = calls
            .into_iter()
            .map(|call| match running.get(&same_work(&call)) {
                Some(t) => PlanTask {
                    call,
                    status: TaskStatus::Running,
                    sent: t.sent.clone(),
                    failures: t.failures,
                },
                None => PlanTask {
                    call,
                    status: TaskStatus::NotStarted,
                    sent: None,
                    failures: 0,
                },
            })
            .collect();
        self.plan = Some(ActivePlan {
            reasoning,
            tasks,
            memory: Vec::new(),
            cycles: 0,
            stuck_since: None,
        });
        Ok(())
    }

    /// The plan with a take-off added before the first goto or start_tracking of each drone that
    /// is on the ground and has no take-off anywhere in the plan: the Coordinator's own rule ("a
    /// drone on the ground must take off before goto"), which a small model forgets. Without it
    /// such a task can never start. Each addition is logged; the gate still checks every action.
    fn with_implied_takeoffs(&mut self, calls: Vec<Call>) -> Vec<Call> {
        let grounded: Vec<String> = {
            let view = self.link.view();
            let now = self.link.clock().instant();
            view.drones()
                .filter(|e| e.effective_mode(now) == DroneMode::Idle)
                .map(|e| e.id.to_string())
                .collect()
        };
        let mut next_id = calls
            .iter()
            .filter_map(|c| c.task.strip_prefix('T')?.parse::<u32>().ok())
            .max()
            .unwrap_or(0);
        let mut out: Vec<Call> = Vec::with_capacity(calls.len());
        for call in &calls {
            let needs_air = matches!(call.action, ActionName::Goto | ActionName::StartTracking);
            let takes_off = |c: &Call| c.drone == call.drone && c.action == ActionName::ArmTakeoff;
            if needs_air
                && grounded.contains(&call.drone)
                && !calls.iter().any(takes_off)
                && !out.iter().any(takes_off)
            {
                next_id += 1;
                let takeoff = Call {
                    task: format!("T{next_id}"),
                    drone: call.drone.clone(),
                    action: ActionName::ArmTakeoff,
                    target: schema::NO_TARGET.to_owned(),
                    xyz: None,
                };
                let text = format!(
                    "{call}: {} is on the ground and the plan never takes it off: added {takeoff}",
                    call.drone
                );
                self.log.note(Record::Event { text: text.clone() });
                self.tell(MissionUpdate::Event(text));
                out.push(takeoff);
            }
            out.push(call.clone());
        }
        out
    }

    /// Gives the plan up when, for `STUCK_AFTER`, none of its tasks has been running (or tracking,
    /// for a done start_tracking) and none could start: e.g. a goto for a drone whose plan never takes it off. Without this the
    /// plan would wait for ever.
    fn give_up_if_stuck(&mut self) {
        let now = self.link.clock().instant();
        // Drones following a target for a done start_tracking: the plan is at work, not stuck.
        let tracking: Vec<String> = {
            let view = self.link.view();
            view.drones()
                .filter(|e| e.effective_mode(now) == DroneMode::Tracking)
                .map(|e| e.id.to_string())
                .collect()
        };
        let Some(plan) = self.plan.as_mut() else {
            return;
        };
        let at_work = |t: &PlanTask| {
            t.status == TaskStatus::Running
                || (t.status == TaskStatus::Done
                    && t.call.action == ActionName::StartTracking
                    && tracking.contains(&t.call.drone))
        };
        if plan.tasks.iter().any(at_work) {
            plan.stuck_since = None;
            return;
        }
        let since = *plan.stuck_since.get_or_insert(now);
        if now.duration_since(since) < STUCK_AFTER {
            return;
        }
        let waiting: Vec<String> = plan
            .tasks
            .iter()
            .filter(|t| t.status != TaskStatus::Done)
            .map(|t| t.call.to_string())
            .collect();
        let why = format!(
            "nothing has run or could start for {} s; waiting: {}",
            STUCK_AFTER.as_secs(),
            waiting.join(", ")
        );
        if let Some(plan) = self.plan.take() {
            self.finish_plan(plan, &format!("abandoned: {why}"));
            self.tell(MissionUpdate::Error(format!(
                "the plan was given up: {why}"
            )));
        }
    }

    /// One Supervisor (or monolithic) cycle.
    pub async fn cycle(&mut self) -> Result<(), MissionError> {
        match self.cfg.mode {
            Mode::Mnl => self.monolithic_cycle().await,
            Mode::Tacos | Mode::Wor => self.supervisor_cycle().await,
        }
    }

    async fn supervisor_cycle(&mut self) -> Result<(), MissionError> {
        let Some(plan) = self.plan.as_ref() else {
            return Ok(());
        };
        if plan.cycles >= self.cfg.max_cycles_per_plan {
            if let Some(plan) = self.plan.take() {
                self.finish_plan(plan, "abandoned after too many cycles");
                self.tell(MissionUpdate::Error(format!(
                    "the plan was not complete after {} Supervisor cycles",
                    self.cfg.max_cycles_per_plan
                )));
            }
            return Ok(());
        }
        // What could start now. When nothing can, the Supervisor has no decision to make: wait
        // for the swarm (an outcome, a membership change or the cycle timeout wakes us again).
        let startable = self.startable_calls();
        if startable.is_empty() {
            self.give_up_if_stuck();
            return Ok(());
        }
        // With nothing of the plan running, waiting cannot be right: nothing would change.
        let idle = !plan.tasks.iter().any(|t| t.status == TaskStatus::Running);
        let reasoning = (self.cfg.mode == Mode::Tacos).then(|| plan.reasoning.clone());
        let user = render::supervisor_request(
            reasoning.as_deref(),
            &render::plan(&self.plan_lines()),
            &render::swarm(&self.drone_lines()),
            &self.world_text(),
            &plan.memory,
        );
        if let Some(plan) = self.plan.as_mut() {
            plan.stuck_since = None;
        }
        let ask = CycleAsk {
            layer: "supervisor",
            output: Output::Supervisor,
            messages: supervisor_messages(user),
            schema: startable_schema(&startable, idle),
            parse: |text| SupervisorReply::parse(text).map(CycleReply::from),
            only: Some(startable),
            tasks: self.plan_lines(),
        };
        let cycle = self
            .ask_and_send(ask, |mission, call, drone, seq| {
                let Some(plan) = mission.plan.as_mut() else {
                    return;
                };
                plan.memory.push(format!("issued {call}"));
                let sent = Some((drone, seq));
                match plan.tasks.iter_mut().find(|t| t.call.task == call.task) {
                    Some(t) => {
                        t.call = call;
                        t.status = TaskStatus::Running;
                        t.sent = sent;
                    }
                    None => plan.tasks.push(PlanTask {
                        call,
                        status: TaskStatus::Running,
                        sent,
                        failures: 0,
                    }),
                }
            })
            .await?;
        // The Supervisor's claim that the plan is complete is logged only: the plan is
        // complete when its tasks are done (`poll_outcomes`).
        if let Some(plan) = self.plan.as_mut() {
            plan.cycles += 1;
            let n = plan.cycles;
            self.note_cycle(n, cycle);
        }
        Ok(())
    }

    async fn monolithic_cycle(&mut self) -> Result<(), MissionError> {
        if self.mnl.claimed_done {
            // The model said its actions carry out the instructions: wait for their outcomes.
            return Ok(());
        }
        if self.mnl.cycles >= self.cfg.max_cycles_per_plan {
            self.mnl.active = false;
            let text = format!(
                "the monolithic model did not carry out the instructions in {} cycles",
                self.mnl.cycles
            );
            self.log.note(Record::Event { text: text.clone() });
            self.tell(MissionUpdate::Error(text));
            return Ok(());
        }
        // As for the Supervisor: when no drone can take an action, there is nothing to decide.
        let callable = self.callable_now();
        if callable.is_empty() {
            return Ok(());
        }
        let user = render::monolithic_request(
            &self.mnl.instructions,
            &render::swarm(&self.drone_lines()),
            &self.world_text(),
            &self.mnl.executed,
        );
        let (drones, places) = self.enums();
        let trackable = self.trackable();
        let ask = CycleAsk {
            layer: "monolithic",
            output: Output::Monolithic,
            messages: vec![
                ChatMessage::system(texts::MONOLITHIC),
                ChatMessage::user(user),
            ],
            schema: callable_schema(&callable, &drones, &places, &trackable),
            parse: |text| MonolithicReply::parse(text).map(CycleReply::from),
            only: None,
            tasks: self
                .mnl
                .tasks
                .iter()
                .map(|t| (t.call.clone(), t.status.clone()))
                .collect(),
        };
        let cycle = self
            .ask_and_send(ask, |mission, call, drone, seq| {
                mission.mnl.tasks.push(PlanTask {
                    call,
                    status: TaskStatus::Running,
                    sent: Some((drone, seq)),
                    failures: 0,
                });
            })
            .await?;
        self.mnl.next_task += callable.len() as u32;
        self.mnl.cycles += 1;
        self.mnl.claimed_done = cycle.claim_stands();
        self.note_cycle(self.mnl.cycles, cycle);
        self.judge_monolithic();
        Ok(())
    }

    /// The common part of a Supervisor and a monolithic cycle: ask the model (with the repair
    /// loop), keep the calls that are among `only` (when given) and pass `check_live` and the
    /// safety gate, send them, and hand each sent call to `issued` for the caller's bookkeeping.
    async fn ask_and_send(
        &mut self,
        ask: CycleAsk,
        issued: fn(&mut Mission, Call, DroneId, u64),
    ) -> Result<CycleOutcome, MissionError> {
        self.tell(MissionUpdate::Thinking { layer: ask.layer });
        self.stats.supervisor_calls += 1;
        let max_tokens = self
            .cfg
            .supervisor_max_tokens
            .max(schema::token_budget(ask.output, self.swarm_ids().len()));
        let (reasoning, claim, all_passed, accepted, later) = {
            let (gate, link) = (&self.gate, &self.link);
            let visible = self.visible_targets();
            let (only, tasks) = (&ask.only, &ask.tasks);
            self.caller
                .ask(
                    &mut self.stats,
                    ask.layer,
                    ask.messages,
                    ask.output,
                    ask.schema,
                    max_tokens,
                    ask.parse,
                    |reply: &CycleReply| {
                        let (firsts, later) = first_call_per_drone(&reply.actions);
                        let (calls, mut rejections) = match only {
                            Some(startable) => match_startable(&firsts, startable),
                            None => (firsts, Vec::new()),
                        };
                        let (accepted, live) = check_live(&calls, gate, link, &visible, tasks);
                        rejections.extend(live);
                        Checked {
                            accepted: (
                                reply.reasoning.clone(),
                                reply.claim,
                                rejections.is_empty() && later.is_empty(),
                                accepted,
                                later,
                            ),
                            rejections,
                            narrowed: None,
                        }
                    },
                )
                .await?
        };
        if !later.is_empty() {
            let text = format!(
                "later steps in the same reply, left for a later cycle: {}",
                later.join("; ")
            );
            self.log.note(Record::Event { text: text.clone() });
            self.tell(MissionUpdate::Event(text));
        }
        let mut sent = Vec::new();
        for (call, checked) in accepted {
            let seq = self.send(&checked, Some(call.task.clone())).await?;
            sent.push(call.to_string());
            issued(self, call, checked.drone().clone(), seq);
        }
        Ok(CycleOutcome {
            reasoning,
            claim,
            all_passed,
            sent,
        })
    }

    /// Counts a cycle, logs it with the model's claim, and reports it.
    fn note_cycle(&mut self, plan_cycle: u32, cycle: CycleOutcome) {
        self.stats.cycles_total += 1;
        self.log.note(Record::SupervisorCycle {
            plan_cycle,
            actions: cycle.sent.clone(),
            plan_complete: cycle.claim,
        });
        self.tell(MissionUpdate::Cycle {
            plan_cycle,
            reasoning: cycle.reasoning,
            actions: cycle.sent,
        });
    }

    /// The monolithic model's instructions are carried out when its claim stands and every
    /// action it issued for them has finished (a failure has withdrawn the claim already).
    fn judge_monolithic(&mut self) {
        let m = &self.mnl;
        if !(m.active && m.claimed_done) || m.tasks.iter().any(|t| t.status == TaskStatus::Running)
        {
            return;
        }
        self.mnl.active = false;
        let cycles = self.mnl.cycles;
        self.stats.cycles_per_plan.push(cycles);
        self.log.note(Record::PlanComplete { cycles });
        self.tell(MissionUpdate::PlanComplete { cycles });
    }

    /// What the monolithic model may call now: for each drone that can take an action, a fresh
    /// task id and the actions its mode allows whose effect does not already hold. Points and
    /// targets are checked per call afterwards, by `check_live` and the safety gate.
    fn callable_now(&self) -> Vec<Callable> {
        let swarm = self.swarm_ids();
        let pending = self.drones_with_pending_actions();
        let view = self.link.view();
        let now = self.link.clock().instant();
        let mut out = Vec::new();
        for drone in swarm {
            let Some(entry) = DroneId::new(&drone).ok().and_then(|id| view.get(&id)) else {
                continue;
            };
            if !entry.ready(now) || pending.contains(&entry.id) {
                continue;
            }
            let mode = entry.effective_mode(now);
            let actions: Vec<ActionName> = ALL_ACTIONS
                .into_iter()
                .filter(|a| {
                    !effect_holds(*a, mode)
                        && tacos_shared::action::mode_forbids(&mode_probe(*a), mode).is_none()
                })
                .collect();
            if actions.is_empty() {
                continue;
            }
            out.push(Callable {
                task: format!("A{}", self.mnl.next_task + 1 + out.len() as u32),
                drone,
                actions,
            });
        }
        out
    }

    async fn send(
        &mut self,
        checked: &CheckedAction,
        task: Option<String>,
    ) -> Result<u64, MissionError> {
        // Whatever a model proposed before the pilot's direct command must not follow it.
        if self.overrides.has_changed().unwrap_or(false) {
            return Err(MissionError::Overridden {
                drone: checked.drone().to_string(),
                action: checked.action().to_string(),
            });
        }
        let seq = self
            .link
            .send(checked, task.clone())
            .await
            .map_err(|e| MissionError::Send {
                drone: checked.drone().to_string(),
                action: checked.action().to_string(),
                reason: e.to_string(),
            })?;
        self.stats.actions_sent += 1;
        self.log.note(Record::action_sent(checked, task, seq));
        self.tell(MissionUpdate::Sent {
            drone: checked.drone().to_string(),
            action: checked.action().to_string(),
            seq,
        });
        Ok(seq)
    }
}

impl Caller {
    /// Asks a model, parses and checks its reply, and sends rejected replies back with the
    /// reasons up to `max_repairs` times. After the last attempt only what passed is returned.
    #[allow(clippy::too_many_arguments)]
    async fn ask<T, U>(
        &self,
        stats: &mut MissionStats,
        layer: &'static str,
        mut messages: Vec<ChatMessage>,
        output: Output,
        mut schema: serde_json::Value,
        max_tokens: u32,
        parse: fn(&str) -> Result<T, ReplyError>,
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
            stats.model_calls += 1;
            let in_flight = self.link.model_call();
            let reply = self.backend.chat(&request).await;
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
                    if let Some(passed) = passed_before {
                        return Ok(passed);
                    }
                    return Err(MissionError::Llm { layer, error });
                }
            };
            self.account(stats, layer, attempt, &reply);
            let problems = match parse(&reply.content) {
                Err(e) => vec![e.to_string()],
                Ok(parsed) => {
                    let checked = check(&parsed);
                    for r in &checked.rejections {
                        stats.gate_rejections += 1;
                        self.log.note(Record::GateRejected {
                            layer: layer.into(),
                            call: r.clone(),
                            reason: String::new(),
                        });
                        let _ = self.updates.send(MissionUpdate::Rejected {
                            call: r.clone(),
                            reason: format!("{layer} reply"),
                        });
                    }
                    if checked.rejections.is_empty() || attempt == attempts {
                        return Ok(checked.accepted);
                    }
                    if let Some(narrowed) = checked.narrowed {
                        schema = narrowed;
                    }
                    passed_before = Some(checked.accepted);
                    checked.rejections
                }
            };
            let problems = distinct_problems(problems);
            last_problem = problems.join("; ");
            messages.push(ChatMessage::assistant(without_repeated_items(
                &reply.content,
            )));
            messages.push(ChatMessage::user(format!(
                "Your reply was rejected:\n- {}\nAnswer again with the corrected JSON object only.",
                problems.join("\n- ")
            )));
        }
        if let Some(passed) = passed_before {
            return Ok(passed);
        }
        Err(MissionError::NoValidReply {
            layer,
            attempts,
            reason: last_problem,
        })
    }

    fn account(
        &self,
        stats: &mut MissionStats,
        layer: &'static str,
        attempt: u32,
        reply: &ChatReply,
    ) {
        stats.prompt_tokens += u64::from(reply.usage.prompt_tokens);
        stats.completion_tokens += u64::from(reply.usage.completion_tokens);
        stats.call_latency_total += reply.latency;
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
/// that is not a JSON object is echoed as it is.
fn without_repeated_items(reply: &str) -> String {
    let Ok(serde_json::Value::Object(mut object)) = serde_json::from_str(reply) else {
        return reply.to_owned();
    };
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
            new
        });
    }
    serde_json::to_string(&object).unwrap_or_else(|_| reply.to_owned())
}

/// The problems of a reply, each said once: the same refusal of the same call under other task
/// ids ("T2 alfa start_tracking(car_1): …", "T3 alfa start_tracking(car_1): …") is one line.
fn distinct_problems(problems: Vec<String>) -> Vec<String> {
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

/// One cycle's question to its model: the Supervisor's or the monolithic model's.
struct CycleAsk {
    layer: &'static str,
    output: Output,
    messages: Vec<ChatMessage>,
    schema: serde_json::Value,
    parse: fn(&str) -> Result<CycleReply, ReplyError>,
    /// The calls the reply may choose from (the Supervisor's startable calls); `None`: any call
    /// that passes the live checks (the monolithic model, which has no plan).
    only: Option<Vec<Call>>,
    /// The tasks issued so far, so a running or finished task is not issued again.
    tasks: Vec<(Call, TaskStatus)>,
}

/// A Supervisor or monolithic reply: reasoning, calls to issue now, and the model's claim that
/// the work is complete (`plan_complete` or `done`).
struct CycleReply {
    reasoning: String,
    actions: Vec<Call>,
    claim: bool,
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
struct CycleOutcome {
    reasoning: String,
    /// The model claimed the work complete.
    claim: bool,
    /// Every call of the accepted reply passed the checks and was issued (none was a later
    /// step left for a later cycle).
    all_passed: bool,
    sent: Vec<String>,
}

impl CycleOutcome {
    /// A claim of completion counts only from a reply whose every call passed and was issued:
    /// a reply that names a rejected call or a later step and says "done" meant that call to be
    /// part of the work.
    fn claim_stands(&self) -> bool {
        self.claim && self.all_passed
    }
}

/// One drone the monolithic model may give an action to now, under a fresh task id.
struct Callable {
    task: String,
    drone: String,
    actions: Vec<ActionName>,
}

const ALL_ACTIONS: [ActionName; 6] = [
    ActionName::ArmTakeoff,
    ActionName::Goto,
    ActionName::StartTracking,
    ActionName::StopTracking,
    ActionName::Land,
    ActionName::Hold,
];

/// An action of this kind, for asking whether a mode allows it (the argument does not matter
/// to the mode rules; the real argument is checked by the safety gate).
fn mode_probe(name: ActionName) -> Action {
    match name {
        ActionName::ArmTakeoff => Action::ArmTakeoff,
        ActionName::Goto => Action::Goto {
            target: tacos_shared::Vec3::default(),
        },
        ActionName::StartTracking => Action::StartTracking {
            target: String::new(),
        },
        ActionName::StopTracking => Action::StopTracking,
        ActionName::Land => Action::Land,
        ActionName::Hold => Action::Hold,
    }
}

/// The action's effect already holds for an idle drone in `mode`: take-off when airborne,
/// landing or hold on the ground, stop-tracking when not tracking. Sending it would only be
/// refused by the drone or do nothing.
fn effect_holds(action: ActionName, mode: DroneMode) -> bool {
    match action {
        ActionName::ArmTakeoff => mode.is_airborne(),
        ActionName::Land | ActionName::Hold => mode == DroneMode::Idle,
        ActionName::StopTracking => mode != DroneMode::Tracking,
        ActionName::Goto | ActionName::StartTracking => false,
    }
}

/// The monolithic model's output schema for this cycle: each call is one of the calls that are
/// valid now (a ready drone under its fresh task id, an action its mode allows, and an
/// argument of the right kind: no target for take-off, landing, hold and stop-tracking; a place
/// or a point for goto; a target for tracking). The model still chooses which, and may choose
/// none.
fn callable_schema(
    callable: &[Callable],
    drones: &[String],
    places: &[String],
    trackable: &[String],
) -> serde_json::Value {
    use serde_json::json;
    let mut schema = schema::build(Output::Monolithic, drones, places, trackable);
    let call = |c: &Callable, action: ActionName, target: serde_json::Value, xyz| {
        json!({
            "type": "object",
            "properties": {
                "task": { "type": "string", "enum": [c.task] },
                "drone": { "type": "string", "enum": [c.drone] },
                "action": { "type": "string", "enum": [serde_json::to_value(action).unwrap_or_default()] },
                "target": { "type": "string", "enum": target },
                "xyz": xyz
            },
            "required": ["task", "drone", "action", "target", "xyz"],
            "additionalProperties": false
        })
    };
    let none = json!([schema::NO_TARGET]);
    let null = json!({ "type": "null" });
    let point =
        json!({ "type": "array", "items": { "type": "number" }, "minItems": 3, "maxItems": 3 });
    let mut alternatives = Vec::new();
    for c in callable {
        for &action in &c.actions {
            match action {
                ActionName::Goto => {
                    if !places.is_empty() {
                        alternatives.push(call(c, action, json!(places), null.clone()));
                    }
                    alternatives.push(call(c, action, none.clone(), point.clone()));
                }
                ActionName::StartTracking => {
                    if !trackable.is_empty() {
                        alternatives.push(call(c, action, json!(trackable), null.clone()));
                    }
                }
                _ => alternatives.push(call(c, action, none.clone(), null.clone())),
            }
        }
    }
    if let Some(items) = schema.pointer_mut("/properties/actions/items") {
        *items = json!({ "anyOf": alternatives });
    }
    if let Some(actions) = schema.pointer_mut("/properties/actions") {
        actions["maxItems"] = serde_json::Value::from(callable.len().max(1));
    }
    schema
}

/// The Coordinator's messages: its configuration prompt, the few-shot examples as turns, then
/// the request.
pub fn coordinator_messages(user: String) -> Vec<ChatMessage> {
    let mut messages = vec![ChatMessage::system(texts::COORDINATOR)];
    for example in texts::coordinator_examples().unwrap_or_default() {
        // "Named in the instruction" as a real request shows it: the example plan's drones and
        // places that its instruction names.
        let names: Vec<String> = CoordinatorReply::parse(&example.reply.to_string())
            .map(|r| {
                r.plan
                    .iter()
                    .flat_map(|c| [Some(c.drone.clone()), c.target_name().map(str::to_owned)])
                    .flatten()
                    .collect()
            })
            .unwrap_or_default();
        let named = render::named_section(&render::named_in(&example.instruction, &names));
        messages.push(ChatMessage::user(format!(
            "## Context\n{}\n## Instruction\n{}\n{named}",
            example.context, example.instruction
        )));
        messages.push(ChatMessage::assistant(example.reply.to_string()));
    }
    messages.push(ChatMessage::user(user));
    messages
}

/// The plan without calls that repeat their drone's previous call in the plan (the 135M model
/// lists `alfa goto(villa)` six times in a row), and the calls dropped. Doing the same work
/// twice in a row changes nothing, and each repeat would cost a Supervisor cycle. Work repeated
/// after other work for that drone (out and back) is kept.
fn without_repeated_work(calls: Vec<Call>) -> (Vec<Call>, Vec<Call>) {
    let mut kept: Vec<Call> = Vec::with_capacity(calls.len());
    let mut dropped = Vec::new();
    for call in calls {
        let previous = kept.iter().rev().find(|c| c.drone == call.drone);
        if previous.is_some_and(|p| same_work(p) == same_work(&call)) {
            dropped.push(call);
        } else {
            kept.push(call);
        }
    }
    (kept, dropped)
}

/// What a call asks of which drone, whatever its task id: a replan that repeats a running call
/// keeps it running instead of starting it again.
fn same_work(call: &Call) -> (String, String) {
    let text = call.to_string();
    let without_task = text
        .split_once(' ')
        .map(|x| x.1.to_owned())
        .unwrap_or_default();
    (call.drone.clone(), without_task)
}

/// The Supervisor's output schema for this cycle: its calls can only name tasks, drones,
/// actions and targets of the calls that could start now, so a constrained model cannot pick
/// anything else (it still chooses which, and may choose none).
/// With `must_act` (nothing of the plan is running) the reply must start at least one call: an
/// empty choice would only wait for a change that cannot come, one model call at a time.
fn startable_schema(startable: &[Call], must_act: bool) -> serde_json::Value {
    let mut drones: Vec<String> = startable.iter().map(|c| c.drone.clone()).collect();
    drones.sort();
    drones.dedup();
    let places: Vec<String> = startable
        .iter()
        .filter_map(|c| c.target_name().map(str::to_owned))
        .collect();
    let mut schema = schema::build(Output::Supervisor, &drones, &places, &[]);
    // Each call is exactly one of the startable calls: task, drone, action and target come as a
    // unit, so a constrained model cannot give one task's id to another drone.
    let alternatives: Vec<serde_json::Value> = startable
        .iter()
        .map(|c| {
            let action = serde_json::to_value(c.action).unwrap_or_default();
            serde_json::json!({
                "type": "object",
                "properties": {
                    "task": { "type": "string", "enum": [c.task] },
                    "drone": { "type": "string", "enum": [c.drone] },
                    "action": { "type": "string", "enum": [action] },
                    "target": { "type": "string", "enum": [c.target] },
                    "xyz": { "type": "null" }
                },
                "required": ["task", "drone", "action", "target", "xyz"],
                "additionalProperties": false
            })
        })
        .collect();
    if let Some(items) = schema.pointer_mut("/properties/actions/items") {
        *items = serde_json::json!({ "anyOf": alternatives });
    }
    if let Some(actions) = schema.pointer_mut("/properties/actions") {
        actions["maxItems"] = serde_json::Value::from(drones.len().max(1));
        if must_act && !startable.is_empty() {
            actions["minItems"] = serde_json::Value::from(1);
        }
    }
    schema
}

/// Keeps the proposed calls that are one of the startable calls (task, drone, action and target
/// as the plan has them; the point of a goto comes from the plan), and says why the others are not.
/// Each drone's first call in a reply; the calls after it for the same drone are its next
/// steps (one action per drone per cycle), which a later cycle issues if they still apply. A
/// small model lists a drone's whole route at once, often under one task id: sending that back
/// costs a model call of minutes and changes nothing. Returns the first calls and the later
/// steps that are other work (a repeat of the first call is just dropped).
fn first_call_per_drone(calls: &[Call]) -> (Vec<Call>, Vec<String>) {
    let mut firsts: Vec<Call> = Vec::new();
    let mut later = Vec::new();
    for call in calls {
        match firsts.iter().find(|c| c.drone == call.drone) {
            None => firsts.push(call.clone()),
            Some(first) if same_work(first) == same_work(call) => {}
            Some(_) => later.push(call.to_string()),
        }
    }
    (firsts, later)
}

fn match_startable(proposed: &[Call], startable: &[Call]) -> (Vec<Call>, Vec<String>) {
    let mut calls = Vec::new();
    let mut rejections = Vec::new();
    for call in proposed {
        let found = startable.iter().find(|c| {
            c.task == call.task
                && c.drone == call.drone
                && c.action == call.action
                && c.target_name() == call.target_name()
        });
        match found {
            Some(c) => calls.push(c.clone()),
            None => {
                let options: Vec<String> = startable.iter().map(|c| c.to_string()).collect();
                rejections.push(format!(
                    "{call}: not a task that can start now (startable: {})",
                    options.join("; ")
                ));
            }
        }
    }
    (calls, rejections)
}

/// The Supervisor's messages: its configuration prompt, the few-shot cycles, then the request.
pub fn supervisor_messages(user: String) -> Vec<ChatMessage> {
    let mut messages = vec![ChatMessage::system(texts::SUPERVISOR)];
    for example in texts::supervisor_examples().unwrap_or_default() {
        messages.push(ChatMessage::user(example.context));
        messages.push(ChatMessage::assistant(example.reply.to_string()));
    }
    messages.push(ChatMessage::user(user));
    messages
}

/// Checks a planned call that does not depend on the live state: the drone exists, the call
/// names something real, and a point is a place a drone may be.
fn check_static(
    call: &Call,
    scenario: &tacos_shared::scenario::Scenario,
    visible: &[TargetObservation],
) -> Result<(), String> {
    if !scenario.drones.iter().any(|d| d.id.as_str() == call.drone) {
        return Err(format!("there is no drone {:?}", call.drone));
    }
    let action = resolve(call, scenario, visible, &[], None)?;
    if let Action::Goto { target } = action {
        scenario
            .world
            .check_point(&target, scenario.limits.drone_radius)
            .map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// Checks calls against the live swarm: resolvable, through the safety gate, to drones that are
/// not busy, one drone per task id, and not repeating a task that is running or done. The calls
/// come one per drone (`first_call_per_drone`).
fn check_live(
    calls: &[Call],
    gate: &SafetyGate,
    link: &GroundLink,
    visible: &[TargetObservation],
    tasks: &[(Call, TaskStatus)],
) -> (Vec<(Call, CheckedAction)>, Vec<String>) {
    let mut accepted: Vec<(Call, CheckedAction)> = Vec::new();
    let mut rejections = Vec::new();
    let view = link.view();
    let now = link.clock().instant();
    let order = nearest_first(calls, gate.scenario(), visible, |d| position_of(&view, d));
    for call in order {
        if let Some((other, _)) = accepted.iter().find(|(c, _)| c.task == call.task) {
            rejections.push(format!(
                "{call}: task {} already goes to {} this cycle",
                call.task, other.drone
            ));
            continue;
        }
        if let Some((_, status)) = tasks.iter().find(|(c, s)| {
            c.task == call.task && matches!(s, TaskStatus::Running | TaskStatus::Done)
        }) {
            let state = if *status == TaskStatus::Done {
                "done"
            } else {
                "running"
            };
            rejections.push(format!("{call}: task {} is already {state}", call.task));
            continue;
        }
        // Busy as the drone reports it, or with a task sent and not yet seen to finish.
        let busy = DroneId::new(&call.drone)
            .ok()
            .and_then(|id| view.get(&id).cloned())
            .is_some_and(|e| e.busy() && e.effective_mode(now) != DroneMode::Unavailable)
            || tasks
                .iter()
                .any(|(c, s)| *s == TaskStatus::Running && c.drone == call.drone);
        if busy {
            rejections.push(format!(
                "{call}: {} is still busy with its current action",
                call.drone
            ));
            continue;
        }
        // Clear of where the other drones are or go, this cycle's accepted gotos included.
        let mut claimed = claimed_points(&view, &call.drone, now);
        claimed.extend(accepted.iter().filter_map(|(_, c)| match c.action() {
            Action::Goto { target } => Some(*target),
            _ => None,
        }));
        let action = match resolve(
            call,
            gate.scenario(),
            visible,
            &claimed,
            position_of(&view, &call.drone),
        ) {
            Ok(a) => a,
            Err(why) => {
                rejections.push(format!("{call}: {why}"));
                continue;
            }
        };
        match gate.check(&view, &call.drone, &action, now) {
            Ok(checked) => accepted.push((call.clone(), checked)),
            Err(r) => rejections.push(format!("{call}: {r}")),
        }
    }
    (accepted, rejections)
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
            serde_json::from_str(&without_repeated_items(reply)).expect("JSON");
        let tasks: Vec<&str> = echoed["plan"]
            .as_array()
            .expect("plan")
            .iter()
            .filter_map(|c| c["task"].as_str())
            .collect();
        assert_eq!(tasks, ["T1", "T2", "T4"]);
        assert_eq!(echoed["reasoning"], "r");
        assert_eq!(without_repeated_items("Sure!"), "Sure!");
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

    fn alternatives(
        schema: &serde_json::Value,
    ) -> Vec<(String, String, String, serde_json::Value)> {
        schema
            .pointer("/properties/actions/items/anyOf")
            .and_then(|a| a.as_array())
            .into_iter()
            .flatten()
            .map(|alt| {
                let one = |f: &str| {
                    alt["properties"][f]["enum"][0]
                        .as_str()
                        .unwrap_or("")
                        .to_owned()
                };
                (
                    one("task"),
                    one("drone"),
                    one("action"),
                    alt["properties"]["target"]["enum"].clone(),
                )
            })
            .collect()
    }

    #[test]
    fn the_monolithic_schema_offers_only_the_calls_valid_now() {
        let callable = [
            Callable {
                task: "A4".into(),
                drone: "alfa".into(),
                actions: vec![ActionName::ArmTakeoff],
            },
            Callable {
                task: "A5".into(),
                drone: "bravo".into(),
                actions: vec![
                    ActionName::Goto,
                    ActionName::StartTracking,
                    ActionName::Land,
                ],
            },
        ];
        let drones = ["alfa".to_owned(), "bravo".to_owned(), "charlie".to_owned()];
        let places = ["car_1".to_owned(), "villa_2".to_owned()];
        let schema = callable_schema(&callable, &drones, &places, &["suspect".to_owned()]);
        let alts = alternatives(&schema);
        let none = serde_json::json!(["none"]);
        assert_eq!(
            alts,
            vec![
                (
                    "A4".into(),
                    "alfa".into(),
                    "arm_takeoff".into(),
                    none.clone()
                ),
                (
                    "A5".into(),
                    "bravo".into(),
                    "goto".into(),
                    serde_json::json!(places)
                ),
                ("A5".into(), "bravo".into(), "goto".into(), none.clone()),
                (
                    "A5".into(),
                    "bravo".into(),
                    "start_tracking".into(),
                    serde_json::json!(["suspect"])
                ),
                ("A5".into(), "bravo".into(), "land".into(), none),
            ]
        );
        // Only the goto without a place takes a point.
        let items = &schema["properties"]["actions"]["items"]["anyOf"];
        assert_eq!(items[2]["properties"]["xyz"]["type"], "array");
        assert_eq!(items[1]["properties"]["xyz"]["type"], "null");
        assert_eq!(schema["properties"]["actions"]["maxItems"], 2);
        assert_eq!(
            schema["required"],
            serde_json::json!(["reasoning", "actions", "done"])
        );
    }

    #[test]
    fn an_effect_that_holds_is_not_offered_again() {
        assert!(effect_holds(ActionName::ArmTakeoff, DroneMode::Flying));
        assert!(!effect_holds(ActionName::ArmTakeoff, DroneMode::Idle));
        assert!(effect_holds(ActionName::Land, DroneMode::Idle));
        assert!(!effect_holds(ActionName::Land, DroneMode::Flying));
        assert!(effect_holds(ActionName::StopTracking, DroneMode::Flying));
        assert!(!effect_holds(ActionName::StopTracking, DroneMode::Tracking));
        assert!(!effect_holds(ActionName::Goto, DroneMode::Flying));
    }

    #[test]
    fn an_idle_plan_must_start_something() {
        let startable = vec![Call {
            task: "T1".into(),
            drone: "alfa".into(),
            action: ActionName::ArmTakeoff,
            target: "none".into(),
            xyz: None,
        }];
        let waiting_allowed = startable_schema(&startable, false);
        assert!(
            waiting_allowed
                .pointer("/properties/actions/minItems")
                .is_none()
        );
        let must_act = startable_schema(&startable, true);
        assert_eq!(
            must_act.pointer("/properties/actions/minItems"),
            Some(&serde_json::json!(1))
        );
        assert_eq!(
            must_act.pointer("/properties/actions/maxItems"),
            Some(&serde_json::json!(1))
        );
        // Nothing startable: no call can be required.
        assert!(
            startable_schema(&[], true)
                .pointer("/properties/actions/minItems")
                .is_none()
        );
    }

    #[test]
    fn work_repeated_in_a_row_is_one_task() {
        let call = |task: &str, drone: &str, action: ActionName, target: &str| Call {
            task: task.into(),
            drone: drone.into(),
            action,
            target: target.into(),
            xyz: None,
        };
        let plan = vec![
            call("T1", "alfa", ActionName::Goto, "villa"),
            call("T2", "bravo", ActionName::Goto, "villa"),
            call("T3", "alfa", ActionName::Goto, "villa"),
            call("T4", "alfa", ActionName::Goto, "small_park"),
            call("T5", "alfa", ActionName::Goto, "villa"),
            call("T6", "alfa", ActionName::Goto, "villa"),
        ];
        let (kept, dropped) = without_repeated_work(plan);
        let tasks = |calls: &[Call]| calls.iter().map(|c| c.task.clone()).collect::<Vec<_>>();
        // Bravo's goto between alfa's two does not separate them; small_park does (out and back).
        assert_eq!(tasks(&kept), ["T1", "T2", "T4", "T5"]);
        assert_eq!(tasks(&dropped), ["T3", "T6"]);
    }

    #[test]
    fn a_reply_gives_each_drone_its_first_call_and_names_the_later_steps() {
        let call = |task: &str, drone: &str, target: &str| Call {
            task: task.into(),
            drone: drone.into(),
            action: ActionName::Goto,
            target: target.into(),
            xyz: None,
        };
        // The 135M model's monolithic reply at 12 drones: one task id, alfa's whole route.
        let reply = vec![
            call("A1", "alfa", "car_1"),
            call("A1", "alfa", "car_2"),
            call("A2", "bravo", "car_4"),
            call("A3", "alfa", "car_1"),
            call("A1", "alfa", "car_3"),
        ];
        let (firsts, later) = first_call_per_drone(&reply);
        assert_eq!(firsts, vec![reply[0].clone(), reply[2].clone()]);
        // The repeat of alfa's first call (under another id) is no later step.
        assert_eq!(later, ["A1 alfa goto(car_2)", "A1 alfa goto(car_3)"]);
    }
}

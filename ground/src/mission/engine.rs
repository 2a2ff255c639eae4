//! The mission engine: Coordinator, Supervisor (or the monolithic model), the repair loop, the
//! pending plan, the two memories, automatic replans, and the bookkeeping of what was sent.

use super::directives::{self, Directive};
use super::input::MissionInputs;
use super::log::{MissionLog, Record};
use super::resolve::resolve;
use crate::link::GroundLink;
use crate::safety::{CheckedAction, SafetyGate};
use crate::swarm::SwarmChange;
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
use tacos_shared::messages::{ActionState, TargetObservation, WorldEvent};
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
}

#[derive(Debug, Clone)]
struct ActivePlan {
    reasoning: String,
    tasks: Vec<PlanTask>,
    /// The Supervisor's memory for this plan; cleared with it.
    memory: Vec<String>,
    cycles: u32,
}

/// The monolithic variant's state: the instructions so far and the executed actions only.
#[derive(Debug, Default)]
struct Monolithic {
    instructions: Vec<String>,
    executed: Vec<String>,
    running: Vec<PlanTask>,
    active: bool,
    cycles: u32,
}

/// Asks models: the backend, the repair loop's bounds, and where calls are recorded.
struct Caller {
    backend: Arc<dyn LlmBackend>,
    log: Arc<MissionLog>,
    updates: mpsc::UnboundedSender<MissionUpdate>,
    max_repairs: u32,
    temperature: f32,
    seed: Option<u64>,
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

/// The result of checking one reply: what may be done, and why the rest may not.
struct Checked<U> {
    accepted: U,
    rejections: Vec<String>,
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
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        let mut last_cycle = Instant::now();
        let mut ticks: u64 = 0;
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
                event = events.recv() => if let Some(event) = event {
                    self.world_event(&event);
                    cycle_due = self.busy();
                },
                _ = tick.tick() => {
                    ticks += 1;
                    if ticks.is_multiple_of(2) {
                        self.log_positions();
                    }
                    cycle_due = self.poll_outcomes() || (self.busy() && last_cycle.elapsed() >= self.cfg.cycle_timeout);
                }
            }
            self.take_override();
            if cycle_due && self.busy() {
                last_cycle = Instant::now();
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

    /// Where every drone is, for `tacos-ground plot` (twice a second).
    fn log_positions(&self) {
        let view = self.link.view();
        for entry in view.drones().filter(|e| e.alive) {
            if let Some(s) = &entry.status {
                self.log.note(Record::Position {
                    drone: entry.id.to_string(),
                    x: s.position.x,
                    y: s.position.y,
                    z: s.position.z,
                    speed: s.velocity.norm(),
                });
            }
        }
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
                self.gate.check(&view, &drone, &action, Instant::now())
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
        if let SwarmChange::Left(d) = &change {
            self.fail_tasks_of(d, "drone lost");
        }
        match self.cfg.mode {
            Mode::Mnl => {
                self.mnl.executed.push(format!("event: {text}"));
                Ok(())
            }
            Mode::Tacos | Mode::Wor => {
                self.history.push(HistoryEntry::Event(text.clone()));
                // Replan only when there is work that the change may affect.
                if self.plan.is_some() {
                    self.log.note(Record::Replan {
                        reason: text.clone(),
                    });
                    self.coordinate(&format!("(automatic replan) {text}: reassign its unfinished subtasks and keep the mission going")).await
                } else {
                    Ok(())
                }
            }
        }
    }

    fn world_event(&mut self, event: &WorldEvent) {
        let text = event.to_string();
        self.events.push(text.clone());
        self.log.note(Record::Event { text: text.clone() });
        self.tell(MissionUpdate::Event(text.clone()));
        match self.cfg.mode {
            Mode::Mnl => self.mnl.executed.push(format!("event: {text}")),
            _ => self.history.push(HistoryEntry::Event(text)),
        }
    }

    fn fail_tasks_of(&mut self, drone: &DroneId, why: &str) {
        let tasks = self
            .plan
            .iter_mut()
            .flat_map(|p| p.tasks.iter_mut())
            .chain(self.mnl.running.iter_mut());
        for t in tasks.filter(|t| {
            t.status == TaskStatus::Running && t.sent.as_ref().is_some_and(|(d, _)| d == drone)
        }) {
            t.status = TaskStatus::Failed(why.to_owned());
        }
    }

    /// Looks for finished actions; true when any task changed state.
    fn poll_outcomes(&mut self) -> bool {
        let mut finished: Vec<(String, String, String)> = Vec::new();
        self.mark_satisfied_tasks(&mut finished);
        {
            let view = self.link.view();
            let tasks = self
                .plan
                .iter_mut()
                .flat_map(|p| p.tasks.iter_mut())
                .chain(self.mnl.running.iter_mut());
            for task in tasks.filter(|t| t.status == TaskStatus::Running) {
                let Some((drone, seq)) = &task.sent else {
                    continue;
                };
                let progress = view
                    .get(drone)
                    .and_then(|e| e.status.as_ref())
                    .and_then(|s| s.action.as_ref());
                let new = match progress {
                    Some(p) if p.seq == *seq => match &p.state {
                        ActionState::Done => Some(TaskStatus::Done),
                        ActionState::Failed(why) => Some(TaskStatus::Failed(why.to_string())),
                        ActionState::Running { .. } => None,
                    },
                    Some(p) if p.seq > *seq => {
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
                    task.status = status;
                }
            }
        }
        for (drone, action, outcome) in &finished {
            self.tell(MissionUpdate::Outcome {
                drone: drone.clone(),
                action: action.clone(),
                outcome: outcome.clone(),
            });
            match self.cfg.mode {
                Mode::Mnl => self.mnl.executed.push(format!("{action}: {outcome}")),
                _ => {
                    if let Some(plan) = self.plan.as_mut() {
                        plan.memory.push(format!("{action}: {outcome}"));
                    }
                }
            }
        }
        if let Some(plan) = self.plan.take() {
            if plan.tasks.iter().all(|t| t.status == TaskStatus::Done) {
                self.finish_plan(plan, "complete");
            } else {
                self.plan = Some(plan);
            }
        }
        self.mnl.running.retain(|t| t.status == TaskStatus::Running);
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
        let view = self.link.view();
        let now = Instant::now();
        let visible = self.targets.borrow().clone();
        let ready = |drone: &str| {
            DroneId::new(drone)
                .ok()
                .and_then(|id| view.get(&id))
                .is_some_and(|e| e.effective_mode(now) != DroneMode::Unavailable && !e.busy())
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
                let Ok(action) = resolve(&call, self.gate.scenario(), &visible) else {
                    continue;
                };
                if self.gate.check(&view, &drone, &action, now).is_ok() {
                    out.push(call);
                }
            }
        }
        out
    }

    /// A task whose effect already holds is done without flying it: a take-off for a drone that
    /// is airborne and idle in the air, a landing or hold for a drone resting on the ground.
    /// Plans from models repeat such calls; sending them would only be refused by the drone.
    fn mark_satisfied_tasks(&mut self, finished: &mut Vec<(String, String, String)>) {
        let Some(plan) = self.plan.as_mut() else {
            return;
        };
        let view = self.link.view();
        let now = Instant::now();
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
            let busy = entry.busy();
            let mode = entry.effective_mode(now);
            let holds = match task.call.action {
                ActionName::ArmTakeoff => mode.is_airborne(),
                ActionName::Land | ActionName::Hold => mode == DroneMode::Idle,
                _ => false,
            };
            if holds && !busy {
                task.status = TaskStatus::Done;
                let what = format!("already {mode}: nothing to do");
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
        let now = Instant::now();
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
            &self.targets.borrow(),
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

    fn enums(&self) -> (Vec<String>, Vec<String>) {
        let s = self.gate.scenario();
        let drones = self.swarm_ids();
        let places = s
            .world
            .landmarks
            .iter()
            .map(|l| l.name.clone())
            .chain(
                s.targets
                    .iter()
                    .filter(|t| t.hidden_at.is_none())
                    .map(|t| t.name.clone()),
            )
            .collect();
        (drones, places)
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
        let user = render::coordinator_request(
            &render::swarm(&self.drone_lines()),
            &self.world_text(),
            &render::plan(&pending),
            &render::history(&self.history),
            instruction,
        );
        let messages = coordinator_messages(user);
        let (drones, places) = self.enums();
        let schema = schema::build(Output::Coordinator, &drones, &places);
        self.tell(MissionUpdate::Thinking {
            layer: "coordinator",
        });
        self.stats.coordinator_calls += 1;
        let scenario = self.gate.scenario().clone();
        let visible = self.targets.borrow().clone();
        let checked = self
            .caller
            .ask(
                &mut self.stats,
                "coordinator",
                messages,
                Output::Coordinator,
                schema,
                self.cfg.coordinator_max_tokens,
                CoordinatorReply::parse,
                |reply: &CoordinatorReply| {
                    let mut rejections = Vec::new();
                    let mut plan = Vec::new();
                    for call in &reply.plan {
                        match check_static(call, &scenario, &visible) {
                            Ok(()) => plan.push(call.clone()),
                            Err(why) => rejections.push(format!("{call}: {why}")),
                        }
                    }
                    if reply.plan.is_empty() {
                        rejections.push("the plan is empty".into());
                    }
                    Checked {
                        accepted: (reply.reasoning.clone(), plan),
                        rejections,
                    }
                },
            )
            .await?;
        let (reasoning, calls) = checked;
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
                },
                None => PlanTask {
                    call,
                    status: TaskStatus::NotStarted,
                    sent: None,
                },
            })
            .collect();
        self.plan = Some(ActivePlan {
            reasoning,
            tasks,
            memory: Vec::new(),
            cycles: 0,
        });
        Ok(())
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
            }
            return Ok(());
        }
        // What could start now. When nothing can, the Supervisor has no decision to make: wait
        // for the swarm (an outcome, a membership change or the cycle timeout wakes us again).
        let startable = self.startable_calls();
        if startable.is_empty() {
            return Ok(());
        }
        let reasoning = (self.cfg.mode == Mode::Tacos).then(|| plan.reasoning.clone());
        let user = render::supervisor_request(
            reasoning.as_deref(),
            &render::plan(&self.plan_lines()),
            &render::swarm(&self.drone_lines()),
            &self.world_text(),
            &plan.memory,
        );
        let messages = supervisor_messages(user);
        let schema = startable_schema(&startable);
        self.tell(MissionUpdate::Thinking {
            layer: "supervisor",
        });
        self.stats.supervisor_calls += 1;
        let (reply_reasoning, claimed_complete, actions) = {
            let (gate, link) = (&self.gate, &self.link);
            let visible = self.targets.borrow().clone();
            let plan_tasks: Vec<(Call, TaskStatus)> = self.plan_lines();
            self.caller
                .ask(
                    &mut self.stats,
                    "supervisor",
                    messages,
                    Output::Supervisor,
                    schema,
                    self.cfg.supervisor_max_tokens,
                    SupervisorReply::parse,
                    |reply: &SupervisorReply| {
                        let (calls, mut rejections) = match_startable(&reply.actions, &startable);
                        let (accepted, live) =
                            check_live(&calls, gate, link, &visible, &plan_tasks);
                        rejections.extend(live);
                        Checked {
                            accepted: (reply.reasoning.clone(), reply.plan_complete, accepted),
                            rejections,
                        }
                    },
                )
                .await?
        };
        let mut sent = Vec::new();
        for (call, checked) in actions {
            let seq = self.send(&checked, Some(call.task.clone())).await?;
            sent.push(call.to_string());
            if let Some(plan) = self.plan.as_mut() {
                plan.memory.push(format!("issued {call}"));
                match plan.tasks.iter_mut().find(|t| t.call.task == call.task) {
                    Some(t) => {
                        t.call = call.clone();
                        t.status = TaskStatus::Running;
                        t.sent = Some((checked.drone().clone(), seq));
                    }
                    None => plan.tasks.push(PlanTask {
                        call,
                        status: TaskStatus::Running,
                        sent: Some((checked.drone().clone(), seq)),
                    }),
                }
            }
        }
        if let Some(plan) = self.plan.as_mut() {
            plan.cycles += 1;
            self.stats.cycles_total += 1;
            self.log.note(Record::SupervisorCycle {
                plan_cycle: plan.cycles,
                actions: sent.clone(),
                plan_complete: claimed_complete,
            });
            let _ = self.updates.send(MissionUpdate::Cycle {
                plan_cycle: plan.cycles,
                reasoning: reply_reasoning,
                actions: sent,
            });
        }
        Ok(())
    }

    async fn monolithic_cycle(&mut self) -> Result<(), MissionError> {
        if self.mnl.cycles >= self.cfg.max_cycles_per_plan {
            self.mnl.active = false;
            self.log.note(Record::Event {
                text: "monolithic model stopped after too many cycles".into(),
            });
            return Ok(());
        }
        let user = render::monolithic_request(
            &self.mnl.instructions,
            &render::swarm(&self.drone_lines()),
            &self.world_text(),
            &self.mnl.executed,
        );
        let messages = vec![
            ChatMessage::system(texts::MONOLITHIC),
            ChatMessage::user(user),
        ];
        let (drones, places) = self.enums();
        let schema = schema::build(Output::Monolithic, &drones, &places);
        self.tell(MissionUpdate::Thinking {
            layer: "monolithic",
        });
        self.stats.supervisor_calls += 1;
        let (reasoning, done, actions) = {
            let (gate, link) = (&self.gate, &self.link);
            let visible = self.targets.borrow().clone();
            let running: Vec<(Call, TaskStatus)> = self
                .mnl
                .running
                .iter()
                .map(|t| (t.call.clone(), t.status.clone()))
                .collect();
            self.caller
                .ask(
                    &mut self.stats,
                    "monolithic",
                    messages,
                    Output::Monolithic,
                    schema,
                    self.cfg.supervisor_max_tokens,
                    MonolithicReply::parse,
                    |reply: &MonolithicReply| {
                        let (accepted, rejections) =
                            check_live(&reply.actions, gate, link, &visible, &running);
                        Checked {
                            accepted: (reply.reasoning.clone(), reply.done, accepted),
                            rejections,
                        }
                    },
                )
                .await?
        };
        let mut sent = Vec::new();
        for (call, checked) in actions {
            let seq = self.send(&checked, Some(call.task.clone())).await?;
            sent.push(call.to_string());
            self.mnl.running.push(PlanTask {
                call,
                status: TaskStatus::Running,
                sent: Some((checked.drone().clone(), seq)),
            });
        }
        self.mnl.cycles += 1;
        self.stats.cycles_total += 1;
        self.log.note(Record::SupervisorCycle {
            plan_cycle: self.mnl.cycles,
            actions: sent.clone(),
            plan_complete: done,
        });
        self.tell(MissionUpdate::Cycle {
            plan_cycle: self.mnl.cycles,
            reasoning,
            actions: sent.clone(),
        });
        if done && sent.is_empty() && self.mnl.running.is_empty() {
            self.mnl.active = false;
            self.stats.cycles_per_plan.push(self.mnl.cycles);
            self.log.note(Record::PlanComplete {
                cycles: self.mnl.cycles,
            });
            self.tell(MissionUpdate::PlanComplete {
                cycles: self.mnl.cycles,
            });
        }
        Ok(())
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
        self.log.note(Record::ActionSent {
            drone: checked.drone().to_string(),
            task,
            seq,
            action: checked.action().to_string(),
        });
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
        schema: serde_json::Value,
        max_tokens: u32,
        parse: fn(&str) -> Result<T, ReplyError>,
        mut check: impl FnMut(&T) -> Checked<U>,
    ) -> Result<U, MissionError> {
        let attempts = self.max_repairs + 1;
        let mut last_problem = String::new();
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
            let reply = match self.backend.chat(&request).await {
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
                    checked.rejections
                }
            };
            last_problem = problems.join("; ");
            messages.push(ChatMessage::assistant(reply.content.clone()));
            messages.push(ChatMessage::user(format!(
                "Your reply was rejected:\n- {}\nAnswer again with the corrected JSON object only.",
                problems.join("\n- ")
            )));
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

/// The Coordinator's messages: its configuration prompt, the few-shot examples as turns, then
/// the request.
pub fn coordinator_messages(user: String) -> Vec<ChatMessage> {
    let mut messages = vec![ChatMessage::system(texts::COORDINATOR)];
    for example in texts::coordinator_examples().unwrap_or_default() {
        messages.push(ChatMessage::user(format!(
            "## Context\n{}\n## Instruction\n{}",
            example.context, example.instruction
        )));
        messages.push(ChatMessage::assistant(example.reply.to_string()));
    }
    messages.push(ChatMessage::user(user));
    messages
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
fn startable_schema(startable: &[Call]) -> serde_json::Value {
    let mut drones: Vec<String> = startable.iter().map(|c| c.drone.clone()).collect();
    drones.sort();
    drones.dedup();
    let places: Vec<String> = startable
        .iter()
        .filter_map(|c| c.target_name().map(str::to_owned))
        .collect();
    let mut schema = schema::build(Output::Supervisor, &drones, &places);
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
    }
    schema
}

/// Keeps the proposed calls that are one of the startable calls (task, drone, action and target
/// as the plan has them; the point of a goto comes from the plan), and says why the others are not.
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
    let action = resolve(call, scenario, visible)?;
    if let Action::Goto { target } = action {
        scenario
            .world
            .check_point(&target, scenario.limits.drone_radius)
            .map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// Checks calls against the live swarm: resolvable, through the safety gate, one per drone, to
/// drones that are not busy, and not repeating a task that is running or done.
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
    let now = Instant::now();
    for call in calls {
        if accepted.iter().any(|(c, _)| c.drone == call.drone) {
            rejections.push(format!(
                "{call}: {} already gets an action this cycle",
                call.drone
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
        let busy = DroneId::new(&call.drone)
            .ok()
            .and_then(|id| view.get(&id).cloned())
            .is_some_and(|e| e.busy() && e.effective_mode(now) != DroneMode::Unavailable);
        if busy {
            rejections.push(format!(
                "{call}: {} is still busy with its current action",
                call.drone
            ));
            continue;
        }
        let action = match resolve(call, gate.scenario(), visible) {
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

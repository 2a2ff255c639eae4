//! The mission engine: Coordinator, Supervisor (or the monolithic model), the repair loop, the
//! pending plan, the two memories, automatic replans, and the bookkeeping of what was sent.
//! This file holds the engine's state and its event loop; its parts are the child modules.

mod approval;
mod caller;
mod coordinator;
mod cycle_call;
mod cycles;
mod early;
mod in_flight;
mod plan_state;

pub use super::core::coordinator_messages;
pub use super::core::supervisor_messages;

use super::addressed;
use super::aids::{Aid, ModelAids};
use super::approval::HeldPlan;
use super::commands::DirectCommands;
use super::config::{MissionConfig, Mode};
use super::core::{ActivePlan, CallQueue, Coordination, PlanBook};
use super::directives;
use super::input::MissionInputs;
use super::log::{MissionLog, Record};
use super::report::{
    EventTopic, MissionError, MissionStats, MissionUpdate, Overtaken, SharedStats,
};
use super::resume::MissionMemory;
use crate::link::GroundLink;
use crate::safety::{CheckedAction, SafetyGate};
use crate::swarm::{SwarmChange, membership_diff};
use crate::task_guard::AbortOnDrop;
use caller::Caller;
use in_flight::{Heard, InFlight};
use plan_state::snapshot_of;
use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;
use tacos_llm::LlmBackend;
use tacos_prompts::render::{HistoryEntry, TaskStatus};
use tacos_shared::DroneId;
use tacos_shared::messages::{TargetObservation, WorldEvent};
use tokio::sync::{mpsc, watch};

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
    /// The plan in force and the monolithic model's work (`mission::core`).
    book: PlanBook,
    stats: SharedStats,
    /// The model call running beside the engine (`in_flight`), if any.
    in_flight: Option<InFlight>,
    /// Which call runs next, what waits for the Coordinator, whether a cycle is due, and the
    /// work epoch (`core::CallQueue`).
    calls: CallQueue,
    /// When the last cycle started (a cycle is due again after `cycle_timeout`).
    last_cycle: std::time::Instant,
    /// Counts the direct commands carried out; a change the engine has not yet seen means a
    /// model's proposal is older than the pilot's command (see `mission::input`).
    overrides: watch::Receiver<u64>,
    /// The direct commands: the engine carries out those among its lines, and keeps their
    /// memory of the last instruction (for `cancel` and `undo`).
    commands: DirectCommands,
    /// A Coordinator plan held for the pilot's approval (`--confirm`).
    held: Option<HeldPlan>,
    /// The drones present as the membership changes the engine took in say; after changes
    /// were missed (a lagging channel) the difference to the view is taken in instead.
    present: BTreeSet<DroneId>,
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

/// Has the backend compute the fixed beginning of the layers' prompts while the pilot types the
/// first instruction: with the embedded model that part (~1,200 tokens of instructions and
/// examples per layer) is what makes a first call slow. A failure only costs that head start.
async fn warm_up(backend: Arc<dyn LlmBackend>, mode: Mode, aids: ModelAids) {
    let prefixes = match mode {
        Mode::Tacos | Mode::Wor => vec![
            super::core::coordinator_fixed_messages(!aids.is_on(Aid::PlanOnly)),
            super::core::supervisor_fixed_messages(),
        ],
        Mode::Mnl => vec![super::core::monolithic_fixed_messages()],
    };
    for messages in prefixes {
        if let Err(e) = backend.warm_up(&messages).await {
            tracing::debug!(error = %e, "warming the model up failed");
            return;
        }
    }
}

impl Mission {
    pub async fn new(
        mut cfg: MissionConfig,
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
            aids: cfg.aids,
            format: super::resume::LOG_FORMAT,
        });
        let stats = SharedStats::default();
        let caller = Caller {
            stats: stats.clone(),
            backend,
            link: link.clone(),
            log: log.clone(),
            updates: updates.clone(),
            max_repairs: cfg.max_repairs,
            aids: cfg.aids,
            temperature: cfg.temperature,
            seed: cfg.seed,
            on_written: None,
        };
        let link_now = link.clock().instant();
        let (commands, overrides) =
            DirectCommands::new(link.clone(), gate.clone(), log.clone(), updates.clone());
        let resume = cfg.resume.take();
        let mut mission = Mission {
            cfg,
            caller,
            gate,
            link,
            log,
            updates,
            targets,
            history: Vec::new(),
            events: Vec::new(),
            book: PlanBook::default(),
            stats,
            in_flight: None,
            calls: CallQueue::default(),
            last_cycle: link_now,
            // The engine's own, until `run_with` brings the pilot's.
            overrides,
            commands,
            present: BTreeSet::new(),
            held: None,
        };
        if let Some(resume) = resume {
            mission.resume(&resume.path, resume.memory);
        }
        Ok(mission)
    }

    pub fn stats(&self) -> MissionStats {
        self.stats.snapshot()
    }

    /// True while a plan (or the monolithic model's work) is under way.
    pub fn busy(&self) -> bool {
        match self.cfg.mode {
            Mode::Mnl => self.book.mnl.active,
            _ => self.book.plan.is_some(),
        }
    }

    fn tell(&self, update: MissionUpdate) {
        let _ = self.updates.send(update);
    }

    /// Logs an event and tells the pilot.
    fn event(&self, topic: EventTopic, text: String) {
        self.log.note(Record::Event { text: text.clone() });
        self.tell(MissionUpdate::Event { topic, text });
    }

    /// Runs the mission until `inputs` closes: pilot lines in, cycles on every change.
    pub async fn run(self, inputs: mpsc::Receiver<String>) -> MissionStats {
        let inputs = MissionInputs {
            lines: inputs,
            overrides: self.overrides.clone(),
            commands: self.commands.clone(),
        };
        self.run_with(inputs).await
    }

    /// As `run`, with the direct commands of a `PilotInput` carried out beside the engine.
    pub async fn run_with(mut self, inputs: MissionInputs) -> MissionStats {
        let MissionInputs {
            lines: mut inputs,
            overrides: mut wake,
            commands,
        } = inputs;
        self.overrides = wake.clone();
        self.commands = commands;
        let mut wake_open = true;
        let mut membership = self.link.membership();
        self.present = self.link.view().present_ids();
        let mut events = match self.link.watch_events().await {
            Ok(rx) => rx,
            Err(e) => {
                self.tell(MissionUpdate::Error(e.to_string()));
                return self.stats();
            }
        };
        // Positions are sampled beside the engine, which waits minutes on a model call while
        // the drones fly on; the guard stops the sampler with the mission.
        let _positions = AbortOnDrop(tokio::spawn(log_positions(
            self.link.clone(),
            self.log.clone(),
        )));
        let _warm_up = AbortOnDrop(tokio::spawn(warm_up(
            self.caller.backend.clone(),
            self.cfg.mode,
            self.cfg.aids,
        )));
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        // After a busy spell, one tick, not a burst of the ones missed.
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        self.last_cycle = self.link.clock().instant();
        loop {
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
                        self.calls.cycle_due(self.busy());
                    }
                    None => {
                        let effects = self.calls.drop_call(Overtaken::SessionClosed);
                        self.apply(effects);
                        break;
                    }
                },
                change = membership.recv() => match change {
                    Ok(change) => {
                        self.membership_changed(change);
                        self.calls.cycle_due(self.busy());
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(missed)) => {
                        // More changes went by than the channel holds: the view says where
                        // they led.
                        tracing::warn!(missed, "membership changes missed; taken from the view");
                        let now_present = self.link.view().present_ids();
                        for change in membership_diff(&self.present, &now_present) {
                            self.membership_changed(change);
                        }
                        self.calls.cycle_due(self.busy());
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => break,
                },
                event = events.recv() => if let Some(event) = event && self.world_event(event) {
                    self.calls.cycle_due(self.busy());
                },
                heard = async {
                    match self.in_flight.as_mut() {
                        Some(flight) => flight.heard().await,
                        None => std::future::pending().await,
                    }
                } => match heard {
                    Heard::Answer(answer) => self.answered(answer).await,
                    Heard::Early(early) => self.send_early(early).await,
                },
                _ = tick.tick() => {
                    let timed_out = self.busy()
                        && self.link.clock().instant().duration_since(self.last_cycle) >= self.cfg.cycle_timeout;
                    let due = self.poll_outcomes() || timed_out;
                    self.calls.cycle_due(due);
                }
            }
            self.take_override();
            self.start_next_call().await;
        }
        self.log.note(Record::MissionEnd {
            outcome: "pilot closed the session".into(),
        });
        self.stats()
    }

    /// After a direct command: the models' plan ends. True when there was one.
    fn take_override(&mut self) -> bool {
        if !self.overrides.has_changed().unwrap_or(false) {
            return false;
        }
        self.overrides.borrow_and_update();
        let effects = self.calls.overridden();
        self.apply(effects);
        if let Some(plan) = self.book.plan.take() {
            self.finish_plan(plan, "interrupted by a direct command");
        }
        if let Some(held) = self.held.take() {
            let text = format!(
                "the plan for {:?} awaiting approval ended: interrupted by a direct command",
                held.instruction
            );
            self.event(EventTopic::PlanEnded, text);
        }
        self.book.mnl.active = false;
        true
    }

    /// A line from the pilot: a direct command, or an instruction for the models.
    pub async fn pilot(&mut self, text: &str) -> Result<(), MissionError> {
        let text = text.trim();
        if text.is_empty() {
            return Ok(());
        }
        let drones = self.snapshot().swarm_ids(self.gate.scenario());
        if let Some(directive) = directives::parse(text, &drones) {
            // The override it raises ends the plan (`take_override`).
            self.commands.execute(text, directive).await;
            return Ok(());
        }
        if let Some(on) = super::approval::switch(text) {
            self.cfg.confirm = on;
            let what = if on {
                "on: every plan waits for your approval"
            } else {
                "off: plans fly once checked"
            };
            self.event(EventTopic::Note, format!("confirm {what}"));
            return Ok(());
        }
        if self.held.is_some()
            && let approval::Answered::Done(result) = self.answer_held(text).await
        {
            return result;
        }
        self.log.note(Record::Pilot {
            text: text.to_owned(),
        });
        let scenario = self.gate.scenario();
        let unknown =
            addressed::unknown_drones(text, &drones, &scenario.slot_ids(), &scenario.place_names());
        if !unknown.is_empty() {
            let refusal = MissionError::UnknownDrones {
                names: unknown,
                swarm: drones,
            };
            self.log.note(Record::Event {
                text: format!("instruction refused: {refusal}"),
            });
            return Err(refusal);
        }
        self.commands.begin_instruction(text);
        match self.cfg.mode {
            Mode::Mnl => {
                // A cycle in flight was asked without this instruction.
                let effects = self.calls.drop_call(Overtaken::NewerWork);
                self.apply(effects);
                self.calls.work_replaced();
                self.book.mnl.instructions.push(text.to_owned());
                self.book.mnl.active = true;
                self.book.mnl.cycles = 0;
                self.book.mnl.claimed_done = false;
                self.book
                    .mnl
                    .tasks
                    .retain(|t| t.status == TaskStatus::Running);
                Ok(())
            }
            Mode::Tacos | Mode::Wor => {
                self.remember(HistoryEntry::Pilot(text.to_owned()));
                self.want_coordination(Coordination::Pilot(text.to_owned()));
                Ok(())
            }
        }
    }

    fn membership_changed(&mut self, change: SwarmChange) {
        match &change {
            SwarmChange::Joined(d) => self.present.insert(d.clone()),
            SwarmChange::Left(d) => self.present.remove(d),
            SwarmChange::Status(_) => false,
        };
        let snap = self.snapshot();
        let effects =
            super::core::membership_changed(&mut self.book, &snap, self.cfg.mode, &change);
        self.apply(effects);
    }

    /// Takes in a world event whose names are the scenario's; one that is not is logged and
    /// left out of every prompt. True when it was taken in.
    fn world_event(&mut self, event: WorldEvent) -> bool {
        let scenario = self.gate.scenario();
        let (mode, book, events) = (self.cfg.mode, &mut self.book, &mut self.events);
        let (taken, effects) = super::core::world_event(event, scenario, mode, book, events);
        if !taken {
            tracing::warn!(?effects, "world event ignored");
        }
        self.apply(effects);
        taken
    }

    /// Adds `entry` to the Coordinator's memory of the mission, and to the log it is resumed
    /// from.
    fn remember(&mut self, entry: HistoryEntry) {
        self.log.note(Record::History {
            entry: entry.clone(),
        });
        self.history.push(entry);
    }

    /// Goes on with a mission the ground station ran before it restarted: its history, world
    /// events and plan in force (with what each task was sent as, so outcomes the drones
    /// report now are matched to them). Before `run`; the first cycle is due at once.
    pub fn resume(&mut self, from: &std::path::Path, memory: MissionMemory) {
        self.log.note(Record::Resumed {
            from: from.display().to_string(),
            memory: memory.clone(),
        });
        let MissionMemory {
            history,
            world_events,
            plan,
        } = memory;
        let text = format!(
            "mission resumed from {}: {} history entries, {}",
            from.display(),
            history.len(),
            match &plan {
                Some(plan) => {
                    let open = plan
                        .tasks
                        .iter()
                        .filter(|t| t.status != TaskStatus::Done)
                        .count();
                    format!("a plan of {} tasks, {open} not done", plan.tasks.len())
                }
                None => "no plan in force".to_owned(),
            }
        );
        self.history = history;
        self.events = world_events;
        self.book.plan = plan.map(ActivePlan::resumed);
        self.calls.set_cycle_due(self.book.plan.is_some());
        self.tell(MissionUpdate::Event {
            topic: EventTopic::Note,
            text,
        });
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
        self.stats.update(|s| s.actions_sent += 1);
        self.commands.moved(checked.drone());
        self.log.note(Record::action_sent(checked, task, seq));
        self.tell(MissionUpdate::Sent {
            drone: checked.drone().to_string(),
            action: checked.action().to_string(),
            seq,
        });
        Ok(seq)
    }
}

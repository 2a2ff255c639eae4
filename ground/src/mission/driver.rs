//! The mission's driver, its only async part: it takes one snapshot of the swarm per step and
//! feeds the pure core (`mission::core`) its inputs — pilot lines, membership changes, world
//! events, ticks, direct commands carried out, model replies, send results — and carries out
//! the effects the core hands back: records, the pilot's updates, model calls run beside the
//! mission (`in_flight`, `caller`), the sends and direct commands it awaits. This file holds the
//! driver's state and its event loop; its parts are the child modules.

mod caller;
mod coordinator;
mod cycle_call;
mod cycles;
mod early;
mod in_flight;
mod plan_state;

pub use super::core::coordinator_messages;
pub use super::core::supervisor_messages;

use super::aids::{Aid, ModelAids};
use super::commands::DirectCommands;
use super::config::{MissionConfig, Mode};
use super::core::{Coordination, Core, Input, Snapshot, trace_step};
use super::directives::Directive;
use super::input::MissionInputs;
use super::log::{MissionLog, Record};
use super::report::{EventTopic, MissionError, MissionStats, MissionUpdate, SharedStats};
use super::resume::MissionMemory;
use crate::link::GroundLink;
use crate::safety::{CheckedAction, SafetyGate};
use crate::task_guard::AbortOnDrop;
use caller::Caller;
use in_flight::{Heard, InFlight};
use plan_state::snapshot_of;
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;
use tacos_llm::{LlmBackend, PromptBeginning};
use tacos_prompts::render::WorldText;
use tacos_shared::messages::TargetObservation;
use tokio::sync::{mpsc, watch};

pub struct Mission {
    cfg: MissionConfig,
    caller: Caller,
    gate: SafetyGate,
    link: Arc<GroundLink>,
    log: Arc<MissionLog>,
    updates: mpsc::UnboundedSender<MissionUpdate>,
    targets: watch::Receiver<Vec<TargetObservation>>,
    /// The plan book, the calls' schedule, the memories and the held plan (`mission::core`).
    core: Core,
    stats: SharedStats,
    /// The model call running beside the engine (`in_flight`), if any.
    in_flight: Option<InFlight>,
    /// Counts the direct commands carried out; a change the engine has not yet seen means a
    /// model's proposal is older than the pilot's command (see `mission::input`).
    overrides: watch::Receiver<u64>,
    /// The direct commands: the engine carries out those among its lines, and keeps their
    /// memory of the last instruction (for `cancel` and `undo`).
    commands: DirectCommands,
    /// What the core asked for that is awaited (`Effect::Direct`, `Effect::Send`), carried out
    /// in order before the next `select!`.
    awaited: VecDeque<Awaited>,
    /// When the trace of the core's steps began, if they are traced (`--trace-steps`).
    trace_began: Option<std::time::Instant>,
}

/// An effect the driver awaits.
enum Awaited {
    Direct {
        text: String,
        directive: Directive,
    },
    /// Its result goes back to the core (`Input::Sent`).
    Send {
        checked: CheckedAction,
        task: String,
    },
    /// The Coordinator's work, fed back on a snapshot with a drone heard (`Input::Coordinate`).
    Coordinate(Coordination),
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
/// first instruction: each layer's instructions and examples (~800–1,350 tokens), then the map
/// that opens every request (~900 on the city). With the embedded model that part is what makes
/// a first call slow. A failure only costs that head start.
async fn warm_up(backend: Arc<dyn LlmBackend>, mode: Mode, aids: ModelAids, world: WorldText) {
    let messages = match mode {
        Mode::Tacos | Mode::Wor => vec![
            super::core::coordinator_fixed_messages(!aids.is_on(Aid::PlanOnly)),
            super::core::supervisor_fixed_messages(),
        ],
        Mode::Mnl => vec![super::core::monolithic_fixed_messages()],
    };
    let user_opening = tacos_prompts::render::request_opening(&world);
    for messages in messages {
        let beginning = PromptBeginning {
            messages,
            user_opening: user_opening.clone(),
        };
        if let Err(e) = backend.warm_up(&beginning).await {
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
        let (commands, overrides) =
            DirectCommands::new(link.clone(), gate.clone(), log.clone(), updates.clone());
        let resume = cfg.resume.take();
        let core = Core::new(&cfg);
        let mut mission = Mission {
            cfg,
            caller,
            gate,
            link,
            log,
            updates,
            targets,
            core,
            stats,
            in_flight: None,
            // The engine's own, until `run_with` brings the pilot's.
            overrides,
            commands,
            awaited: VecDeque::new(),
            trace_began: None,
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
        self.core.busy()
    }

    fn tell(&self, update: MissionUpdate) {
        let _ = self.updates.send(update);
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
        if self.cfg.trace_steps {
            self.log.note(Record::TraceBegun {
                core: self.core.traced(),
            });
            self.trace_began = Some(self.link.clock().instant());
        }
        self.step(Input::Started);
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
            self.core.mode,
            self.core.aids,
            tacos_prompts::render::world(&self.gate.scenario().world, &[], &[]),
        )));
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        // After a busy spell, one tick, not a burst of the ones missed.
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        loop {
            tokio::select! {
                changed = wake.changed(), if wake_open => if changed.is_err() {
                    wake_open = false;
                },
                line = inputs.recv() => match line {
                    Some(text) => {
                        // The pilot's direct command came before this line.
                        self.take_override();
                        self.step(Input::Pilot(text));
                    }
                    None => break,
                },
                change = membership.recv() => match change {
                    Ok(change) => self.step(Input::Membership(change)),
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(missed)) => {
                        // More changes went by than the channel holds: the view says where
                        // they led.
                        tracing::warn!(missed, "membership changes missed; taken from the view");
                        self.step(Input::MembershipMissed);
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => break,
                },
                event = events.recv() => if let Some(event) = event {
                    self.step(Input::World(event));
                },
                heard = async {
                    match self.in_flight.as_mut() {
                        Some(flight) => flight.heard().await,
                        None => std::future::pending().await,
                    }
                } => match heard {
                    Heard::Answer(answer) => self.answered(answer),
                    Heard::Early(early) => self.send_early(early),
                },
                _ = tick.tick() => self.step(Input::Tick),
            }
            self.carry_out_queued().await;
            self.take_override();
            self.start_next_call().await;
        }
        self.step(Input::Closed);
        self.stats()
    }

    /// Carries out what the core's steps asked for that is awaited, in order: a direct command,
    /// or a send whose result is fed back (`Input::Sent`), which may ask for the next.
    async fn carry_out_queued(&mut self) {
        while let Some(awaited) = self.awaited.pop_front() {
            match awaited {
                Awaited::Direct { text, directive } => {
                    self.commands.execute(&text, directive).await;
                }
                Awaited::Send { checked, task } => {
                    let result = self.send(&checked, Some(task)).await;
                    self.step(Input::Sent(result));
                }
                Awaited::Coordinate(work) => self.coordinate(work).await,
            }
        }
    }

    /// Feeds `input` to the core with a snapshot taken now, and carries out its effects.
    fn step(&mut self, input: Input) {
        let snap = self.snapshot();
        self.step_on(input, snap);
    }

    /// Feeds `input` to the core with `snap`, and carries out its effects.
    fn step_on(&mut self, input: Input, snap: Snapshot) {
        if let Some(began) = self.trace_began {
            self.log
                .note(Record::Step(trace_step(&input, &snap, began)));
        }
        let effects = self.core.step(input, &snap, &self.gate);
        self.apply(effects);
    }

    /// After a direct command: the models' plan ends (`Input::Overridden`).
    fn take_override(&mut self) {
        if !self.overrides.has_changed().unwrap_or(false) {
            return;
        }
        self.overrides.borrow_and_update();
        self.step(Input::Overridden);
    }

    /// Goes on with a mission the ground station ran before it restarted: its history, world
    /// events and plan in force (with what each task was sent as, so outcomes the drones
    /// report now are matched to them). Before `run`; the first cycle is due at once.
    pub fn resume(&mut self, from: &std::path::Path, memory: MissionMemory) {
        self.log.note(Record::Resumed {
            from: from.display().to_string(),
            memory: memory.clone(),
        });
        let text = format!(
            "mission resumed from {}: {}",
            from.display(),
            self.core.resume(memory)
        );
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

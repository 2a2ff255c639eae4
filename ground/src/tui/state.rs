//! What the terminal shows, as plain data: the swarm, trails, targets, the world, the chat with
//! the models, the event log, the status bar and the pilot's input line.
//!
//! Pure: every method takes the time it should assume, so the panes can be rendered and tested
//! from a fixed state.

pub use super::input_line::InputLine;
use crate::mission::log::RefusedBy;
use crate::mission::{EventTopic, MissionUpdate};
use crate::swarm::SwarmView;
use crossterm::event::{KeyCode, KeyEvent, KeyEventKind, KeyModifiers};
use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};
use tacos_shared::geometry::is_finite;
use tacos_shared::messages::{ActionState, FailsafeStage, TargetObservation};
use tacos_shared::px4_mode::Px4Mode;
use tacos_shared::scenario::Scenario;
use tacos_shared::world::World;
use tacos_shared::{DroneMode, Vec3};

/// How far back a trail reaches.
pub const TRAIL_SPAN: Duration = Duration::from_secs(60);
/// At most one trail point per drone this often (60 points per minute per drone).
pub const TRAIL_STEP: Duration = Duration::from_secs(1);
/// The chat keeps this many entries, the event log this many lines.
pub const CHAT_CAPACITY: usize = 400;
pub const EVENT_CAPACITY: usize = 1000;
/// Pilot lines remembered for ↑/↓.
pub const HISTORY_CAPACITY: usize = 100;

/// What a key asks the terminal to do.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Command {
    /// A line for the mission (an instruction or a direct command).
    Submit(String),
    Quit,
}

/// One row of the swarm table (and one drone on the map).
#[derive(Debug, Clone, PartialEq)]
pub struct DroneRow {
    pub id: String,
    pub mode: DroneMode,
    pub alive: bool,
    /// None until a status arrived.
    pub position: Option<Vec3>,
    pub velocity: Option<Vec3>,
    /// Task id of the current (or last) action, when it belongs to a plan.
    pub task: Option<String>,
    pub action: Option<String>,
    pub state: Option<ActionState>,
    pub failsafe: Option<FailsafeStage>,
    /// Holding because no neighbour is heard (`DroneStatus::peers_silent`).
    pub peers_silent: bool,
    /// PX4 flies it in this mode, out of offboard (`DroneStatus::autopilot_took_over`).
    pub autopilot_took_over: Option<Px4Mode>,
    /// Seconds since the last status.
    pub link_age: Option<f64>,
}

impl DroneRow {
    fn unseen(id: &str) -> DroneRow {
        DroneRow {
            id: id.to_owned(),
            mode: DroneMode::Unavailable,
            alive: false,
            position: None,
            velocity: None,
            task: None,
            action: None,
            state: None,
            failsafe: None,
            peers_silent: false,
            autopilot_took_over: None,
            link_age: None,
        }
    }

    pub fn speed(&self) -> Option<f64> {
        self.velocity.map(|v| v.norm())
    }
}

/// A named target on the map.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetMark {
    pub name: String,
    pub position: Vec3,
}

/// One entry of the chat with the models.
#[derive(Debug, Clone, PartialEq)]
pub enum ChatEntry {
    Pilot(String),
    Coordinator {
        reasoning: String,
        calls: Vec<String>,
    },
    Supervisor {
        cycle: u32,
        reasoning: String,
        actions: Vec<String>,
    },
    PlanComplete {
        cycles: u32,
    },
    Error(String),
}

/// A reply being written: its layer, its reasoning and its complete calls so far.
#[derive(Debug, Clone, PartialEq)]
pub struct Writing {
    pub layer: String,
    pub reasoning: String,
    pub calls: Vec<String>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EventKind {
    /// A drone lost, a fault, an action that failed.
    Failure,
    /// A new plan replaced a running one, or a plan ended early.
    Replan,
    /// The safety gate refused a call.
    Rejected,
    /// A target was seen.
    Detection,
    /// The pilot's direct command and its outcome.
    Direct,
    /// An action left for a drone.
    Sent,
    /// An action finished.
    Done,
    /// Anything else (a drone joined, …).
    Info,
    Error,
}

#[derive(Debug, Clone, PartialEq)]
pub struct EventLine {
    /// Time since the terminal started.
    pub at: Duration,
    pub kind: EventKind,
    pub text: String,
}

/// The last answered model call.
#[derive(Debug, Clone, PartialEq)]
pub struct CallInfo {
    pub layer: String,
    pub latency: Duration,
    pub prompt_tokens: u32,
    pub completion_tokens: u32,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Status {
    pub backend: String,
    pub last_call: Option<CallInfo>,
    pub calls: u32,
    /// The layer a model call is in flight for, and since when.
    pub thinking: Option<(String, Instant)>,
    /// Plans wait for the pilot's approval (`--confirm`; F2 switches it).
    pub confirm: bool,
}

/// The pane that PgUp/PgDn scroll.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Focus {
    #[default]
    Chat,
    Events,
    Swarm,
}

/// Scroll offsets: the chat and the log count lines up from the newest (0 follows the end);
/// the table counts rows down from the first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Scroll {
    pub chat: usize,
    pub events: usize,
    pub swarm: usize,
}

/// Everything the terminal renders from.
#[derive(Debug, Clone)]
pub struct TerminalState {
    pub scenario_name: String,
    pub world: World,
    /// Drones in table order: the scenario's, then any other that showed up.
    pub drones: Vec<DroneRow>,
    pub trails: BTreeMap<String, VecDeque<(Instant, Vec3)>>,
    pub targets: Vec<TargetMark>,
    pub chat: VecDeque<ChatEntry>,
    /// A model's reply as it is being written, shown below the chat until it is in.
    pub writing: Option<Writing>,
    pub events: VecDeque<EventLine>,
    pub status: Status,
    pub input: InputLine,
    pub focus: Focus,
    pub scroll: Scroll,
    /// When the terminal started (event times count from here) and the latest time it was told.
    pub started: Instant,
    pub now: Instant,
    /// A plan is running (a new plan then is a replan).
    plan_active: bool,
}

impl TerminalState {
    pub fn new(scenario: &Scenario, backend: impl Into<String>, now: Instant) -> TerminalState {
        TerminalState {
            scenario_name: scenario.name.clone(),
            world: scenario.world.clone(),
            drones: scenario
                .drones
                .iter()
                .map(|d| DroneRow::unseen(d.id.as_str()))
                .collect(),
            trails: BTreeMap::new(),
            targets: Vec::new(),
            chat: VecDeque::new(),
            writing: None,
            events: VecDeque::new(),
            status: Status {
                backend: backend.into(),
                last_call: None,
                calls: 0,
                thinking: None,
                confirm: false,
            },
            input: InputLine::default(),
            focus: Focus::Chat,
            scroll: Scroll::default(),
            started: now,
            now,
            plan_active: false,
        }
    }

    /// Moves the clock (the thinking timer, link ages shown as of the last refresh).
    pub fn tick(&mut self, now: Instant) {
        self.now = self.now.max(now);
    }

    /// Seconds the current model call has been in flight.
    pub fn thinking_for(&self) -> Option<(&str, f64)> {
        self.status.thinking.as_ref().map(|(layer, since)| {
            (
                layer.as_str(),
                self.now.saturating_duration_since(*since).as_secs_f64(),
            )
        })
    }

    pub fn airborne(&self) -> usize {
        self.drones.iter().filter(|d| d.mode.is_airborne()).count()
    }

    fn chat_push(&mut self, entry: ChatEntry) {
        self.chat.push_back(entry);
        while self.chat.len() > CHAT_CAPACITY {
            self.chat.pop_front();
        }
    }

    /// Adds a line to the event log.
    pub fn log(&mut self, kind: EventKind, text: impl Into<String>) {
        self.events.push_back(EventLine {
            at: self.now.saturating_duration_since(self.started),
            kind,
            text: text.into(),
        });
        while self.events.len() > EVENT_CAPACITY {
            self.events.pop_front();
        }
    }

    /// Takes in one update of the mission, in the order the engine sent them.
    pub fn apply_update(&mut self, update: &MissionUpdate, now: Instant) {
        self.tick(now);
        // A reply in progress is shown until anything else comes of the call.
        if !matches!(
            update,
            MissionUpdate::Writing { .. }
                | MissionUpdate::Sent { .. }
                | MissionUpdate::Outcome { .. }
                | MissionUpdate::Event { .. }
        ) {
            self.writing = None;
        }
        match update {
            MissionUpdate::Writing {
                layer,
                reasoning,
                calls,
            } => {
                self.writing = Some(Writing {
                    layer: (*layer).to_owned(),
                    reasoning: reasoning.clone(),
                    calls: calls.clone(),
                });
            }
            MissionUpdate::Thinking { layer } => {
                self.status.thinking = Some(((*layer).to_owned(), self.now));
            }
            MissionUpdate::Call {
                layer,
                latency,
                prompt_tokens,
                completion_tokens,
            } => {
                self.status.thinking = None;
                self.status.calls += 1;
                self.status.last_call = Some(CallInfo {
                    layer: (*layer).to_owned(),
                    latency: *latency,
                    prompt_tokens: *prompt_tokens,
                    completion_tokens: *completion_tokens,
                });
            }
            MissionUpdate::Plan { reasoning, calls } => {
                self.status.thinking = None;
                if self.plan_active {
                    self.log(
                        EventKind::Replan,
                        format!("replan: a new plan of {} calls", calls.len()),
                    );
                }
                self.plan_active = true;
                self.chat_push(ChatEntry::Coordinator {
                    reasoning: reasoning.clone(),
                    calls: calls.clone(),
                });
            }
            MissionUpdate::Cycle {
                plan_cycle,
                reasoning,
                actions,
            } => {
                self.status.thinking = None;
                self.chat_push(ChatEntry::Supervisor {
                    cycle: *plan_cycle,
                    reasoning: reasoning.clone(),
                    actions: actions.clone(),
                });
            }
            MissionUpdate::Rejected { layer, refusal, by } => {
                let whose = match by {
                    RefusedBy::Checks => "refused the",
                    RefusedBy::SafetyGate => "the safety gate refused the",
                };
                self.log(EventKind::Rejected, format!("{whose} {layer}'s {refusal}"));
                // The reply goes back to its model with the reasons: a new call is in flight
                // (until the plan or cycle shows it was the last attempt).
                self.status.thinking = Some(((*layer).to_owned(), self.now));
            }
            MissionUpdate::Sent { drone, action, seq } => {
                self.log(
                    EventKind::Sent,
                    format!("sent #{} {action} to {drone}", seq % 100_000),
                );
            }
            MissionUpdate::Outcome {
                drone,
                action,
                outcome,
                failed,
            } => {
                let kind = if *failed {
                    EventKind::Failure
                } else {
                    EventKind::Done
                };
                self.log(kind, format!("{drone}: {action} {outcome}"));
            }
            MissionUpdate::Event { topic, text } => {
                if *topic == EventTopic::PlanEnded {
                    self.plan_active = false;
                }
                self.log(event_kind(*topic), text.clone());
            }
            MissionUpdate::PlanComplete { cycles } => {
                self.plan_active = false;
                self.chat_push(ChatEntry::PlanComplete { cycles: *cycles });
                self.log(
                    EventKind::Done,
                    format!("plan complete after {cycles} cycles"),
                );
            }
            MissionUpdate::CallDropped { layer, by } => {
                self.status.thinking = None;
                self.log(
                    EventKind::Info,
                    format!("{layer}'s call dropped: overtaken by {by}"),
                );
            }
            MissionUpdate::Error(text) => {
                self.status.thinking = None;
                self.chat_push(ChatEntry::Error(text.clone()));
                self.log(EventKind::Error, text.clone());
            }
        }
    }

    /// Copies what the table and the map need from the swarm view, and extends the trails.
    pub fn refresh_swarm(&mut self, view: &SwarmView, now: Instant) {
        self.tick(now);
        for entry in view.drones() {
            let id = entry.id.as_str();
            let index = match self.drones.iter().position(|d| d.id == id) {
                Some(i) => i,
                None => {
                    self.drones.push(DroneRow::unseen(id));
                    self.drones.len() - 1
                }
            };
            let status = entry.status.as_ref();
            let progress = status.and_then(|s| s.action.as_ref());
            self.drones[index] = DroneRow {
                id: id.to_owned(),
                mode: entry.effective_mode(now),
                alive: entry.alive,
                position: status.map(|s| s.position).filter(is_finite),
                velocity: status.map(|s| s.velocity).filter(is_finite),
                task: progress.and_then(|p| p.task_id.clone()),
                action: progress.map(|p| p.action.to_string()),
                state: progress.map(|p| p.state.clone()),
                failsafe: status.and_then(|s| s.failsafe),
                peers_silent: status.is_some_and(|s| s.peers_silent),
                autopilot_took_over: status.and_then(|s| s.autopilot_took_over),
                link_age: entry.link_age(now),
            };
        }
        // A trail point is stamped with its status's arrival, so a silent drone adds none.
        let points: Vec<(String, Instant, Vec3)> = view
            .drones()
            .filter_map(|e| {
                let p = e.status.as_ref().map(|s| s.position).filter(is_finite)?;
                Some((e.id.to_string(), e.last_status_at?, p))
            })
            .collect();
        for (id, at, p) in points {
            self.add_trail_point(&id, p, at);
        }
        self.expire_trails(now);
    }

    /// Adds a trail point unless the drone's last one is younger than [`TRAIL_STEP`].
    pub fn add_trail_point(&mut self, id: &str, p: Vec3, now: Instant) {
        let trail = self.trails.entry(id.to_owned()).or_default();
        let due = trail
            .back()
            .is_none_or(|(t, _)| now.saturating_duration_since(*t) >= TRAIL_STEP);
        if due {
            trail.push_back((now, p));
        }
    }

    /// Drops trail points older than [`TRAIL_SPAN`].
    pub fn expire_trails(&mut self, now: Instant) {
        for trail in self.trails.values_mut() {
            while trail
                .front()
                .is_some_and(|(t, _)| now.saturating_duration_since(*t) > TRAIL_SPAN)
            {
                trail.pop_front();
            }
        }
        self.trails.retain(|_, t| !t.is_empty());
    }

    pub fn set_targets(&mut self, targets: &[TargetObservation]) {
        self.targets = targets
            .iter()
            .filter(|t| is_finite(&t.position))
            .map(|t| TargetMark {
                name: t.name.clone(),
                position: t.position,
            })
            .collect();
    }

    /// A key from the pilot.
    pub fn key(&mut self, key: KeyEvent) -> Option<Command> {
        if key.kind == KeyEventKind::Release {
            return None;
        }
        let ctrl = key.modifiers.contains(KeyModifiers::CONTROL);
        match key.code {
            KeyCode::Char('c') | KeyCode::Char('d') if ctrl => return Some(Command::Quit),
            KeyCode::Esc => return Some(Command::Quit),
            KeyCode::F(2) => {
                self.status.confirm = !self.status.confirm;
                let line = if self.status.confirm {
                    "confirm on"
                } else {
                    "confirm off"
                };
                return Some(Command::Submit(line.into()));
            }
            KeyCode::Enter => {
                if matches!(self.input.text().trim(), ":q" | ":quit") {
                    self.input.take();
                    return Some(Command::Quit);
                }
                let line = self.input.take()?;
                self.chat_push(ChatEntry::Pilot(line.clone()));
                self.scroll.chat = 0;
                return Some(Command::Submit(line));
            }
            KeyCode::Char('a') if ctrl => self.input.home(),
            KeyCode::Char('e') if ctrl => self.input.end(),
            KeyCode::Char('u') if ctrl => self.input.kill_before(),
            KeyCode::Char('k') if ctrl => self.input.kill_after(),
            KeyCode::Char('w') if ctrl => self.input.delete_word(),
            KeyCode::Char(c) if !ctrl && !key.modifiers.contains(KeyModifiers::ALT) => {
                self.input.insert(c)
            }
            KeyCode::Backspace => self.input.backspace(),
            KeyCode::Delete => self.input.delete(),
            KeyCode::Left => self.input.left(),
            KeyCode::Right => self.input.right(),
            KeyCode::Home => self.input.home(),
            KeyCode::End => self.input.end(),
            KeyCode::Up => self.input.older(),
            KeyCode::Down => self.input.newer(),
            KeyCode::Tab => {
                self.focus = match self.focus {
                    Focus::Chat => Focus::Events,
                    Focus::Events => Focus::Swarm,
                    Focus::Swarm => Focus::Chat,
                }
            }
            KeyCode::PageUp => self.scroll_by(5, true),
            KeyCode::PageDown => self.scroll_by(5, false),
            _ => {}
        }
        None
    }

    /// Scrolls the focused pane: `back` towards older lines (or earlier rows).
    /// Offsets are clamped when rendering.
    fn scroll_by(&mut self, n: usize, back: bool) {
        let (offset, limit) = match self.focus {
            Focus::Chat => (&mut self.scroll.chat, 10_000),
            Focus::Events => (&mut self.scroll.events, self.events.len()),
            Focus::Swarm => (&mut self.scroll.swarm, self.drones.len()),
        };
        let grow = match self.focus {
            Focus::Swarm => !back,
            _ => back,
        };
        *offset = if grow {
            (*offset + n).min(limit)
        } else {
            offset.saturating_sub(n)
        };
    }
}

/// How an engine event is shown.
fn event_kind(topic: EventTopic) -> EventKind {
    match topic {
        EventTopic::Direct => EventKind::Direct,
        EventTopic::Detection => EventKind::Detection,
        EventTopic::Failure => EventKind::Failure,
        EventTopic::PlanEnded => EventKind::Replan,
        EventTopic::Joined | EventTopic::Note => EventKind::Info,
    }
}

//! A mission's steps as the log keeps them (`--trace-steps`): each `Input` the core was fed,
//! with the step's `Snapshot`, in a form that can be written and read back, so a mission can
//! be fed again to a fresh core (`mission::replay`) and is seen to make the same decisions.
//!
//! Times are kept relative: the snapshot's time as nanoseconds since the trace began, a
//! drone's last status and departure as their age at the snapshot (signed: a status can be
//! stamped just after the view was read). A replay puts them back on any base instant. A
//! checked action is kept as what the gate judged (the drone, the action, the drone's state
//! as seen) and made again by the gate (`SafetyGate::recheck`) when replayed, so nothing read
//! back from a file becomes a sendable action around the gate. Errors are kept in their words
//! (`MissionError::Recorded`).

use super::calls::Coordination;
use super::cycle_reply::CycleChoice;
use super::snapshot::Snapshot;
use super::state::{Bounds, Core};
use super::step::Input;
use crate::mission::aids::ModelAids;
use crate::mission::config::Mode;
use crate::mission::report::MissionError;
use crate::safety::{CheckedAction, DroneSeen, SafetyGate};
use crate::swarm::{DroneEntry, SwarmChange, SwarmView};
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant};
use tacos_prompts::Call;
use tacos_shared::DroneId;
use tacos_shared::action::Action;
use tacos_shared::messages::{DroneStatus, TargetObservation, WorldEvent};

/// What a core is made from: a replay makes its fresh core the same.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TracedCore {
    pub mode: Mode,
    pub aids: ModelAids,
    pub confirm: bool,
    pub bounds: Bounds,
}

/// One step: the input and the snapshot it was seen on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TracedStep {
    pub input: TracedInput,
    pub snapshot: TracedSnapshot,
}

/// `Input`, written down.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "input", rename_all = "snake_case")]
pub enum TracedInput {
    Started,
    Pilot {
        text: String,
    },
    Membership {
        change: SwarmChange,
    },
    MembershipMissed,
    World {
        event: WorldEvent,
    },
    Tick,
    Overridden,
    CoordinatorReply {
        instruction: String,
        grounded: Vec<String>,
        answer: Result<(String, Vec<Call>, Option<String>), String>,
    },
    EarlyCall {
        call: Call,
        checked: TracedAction,
        after: Duration,
    },
    CycleReply {
        answer: Result<TracedChoice, String>,
    },
    Sent {
        result: Result<u64, String>,
    },
    CallDue,
    Coordinate {
        work: Coordination,
    },
    CallLost {
        layer: String,
        reason: String,
    },
    Closed,
}

/// A checked action as the gate judged it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TracedAction {
    pub drone: String,
    pub action: Action,
    pub seen: DroneSeen,
}

/// `CycleChoice`, written down.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TracedChoice {
    pub reasoning: String,
    pub claim: bool,
    pub all_passed: bool,
    pub accepted: Vec<(Call, TracedAction)>,
    pub later: Vec<String>,
}

/// `Snapshot`, written down (times relative, see the module's comment).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TracedSnapshot {
    /// Nanoseconds since the trace began.
    pub at_ns: u64,
    pub drones: Vec<TracedDrone>,
    pub targets: Vec<TargetObservation>,
    pub ground: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TracedDrone {
    pub id: DroneId,
    pub alive: bool,
    pub status: Option<DroneStatus>,
    /// How long before the snapshot the last status came, in nanoseconds.
    pub status_age_ns: Option<i64>,
    /// How long before the snapshot the drone's token went.
    pub gone_age_ns: Option<i64>,
}

/// Why a trace could not be fed back.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TraceError {
    #[error("the trace holds a time {0} ns from its step that this clock cannot reach")]
    TimeOutOfReach(i64),
    #[error("the trace names a model layer {0:?} this ground station does not have")]
    UnknownLayer(String),
    #[error("the gate refuses {action} for {drone} on the state recorded: {reason}")]
    Refused {
        drone: String,
        action: String,
        reason: String,
    },
}

impl Core {
    /// What this core was made from, for a trace's first record.
    pub(crate) fn traced(&self) -> TracedCore {
        TracedCore {
            mode: self.mode,
            aids: self.aids,
            confirm: self.confirm,
            bounds: self.bounds.clone(),
        }
    }

    /// A fresh core made as a traced one was.
    pub(crate) fn from_trace(traced: &TracedCore) -> Core {
        let mut core = Core::new(&crate::mission::config::MissionConfig {
            mode: traced.mode,
            aids: traced.aids,
            confirm: traced.confirm,
            ..Default::default()
        });
        core.bounds = traced.bounds.clone();
        core
    }
}

/// `input` seen on `snap`, written down; `began` is when the trace began.
pub(crate) fn trace_step(input: &Input, snap: &Snapshot, began: Instant) -> TracedStep {
    TracedStep {
        input: trace_input(input),
        snapshot: trace_snapshot(snap, began),
    }
}

fn trace_action(checked: &CheckedAction) -> TracedAction {
    TracedAction {
        drone: checked.drone().to_string(),
        action: checked.action().clone(),
        seen: checked.seen(),
    }
}

fn trace_input(input: &Input) -> TracedInput {
    match input {
        Input::Started => TracedInput::Started,
        Input::Pilot(text) => TracedInput::Pilot { text: text.clone() },
        Input::Membership(change) => TracedInput::Membership {
            change: change.clone(),
        },
        Input::MembershipMissed => TracedInput::MembershipMissed,
        Input::World(event) => TracedInput::World {
            event: event.clone(),
        },
        Input::Tick => TracedInput::Tick,
        Input::Overridden => TracedInput::Overridden,
        Input::CoordinatorReply {
            instruction,
            grounded,
            answer,
        } => TracedInput::CoordinatorReply {
            instruction: instruction.clone(),
            grounded: grounded.clone(),
            answer: match answer {
                Ok(reply) => Ok(reply.clone()),
                Err(e) => Err(e.to_string()),
            },
        },
        Input::EarlyCall {
            call,
            checked,
            after,
        } => TracedInput::EarlyCall {
            call: call.clone(),
            checked: trace_action(checked),
            after: *after,
        },
        Input::CycleReply(answer) => TracedInput::CycleReply {
            answer: match answer {
                Ok(choice) => Ok(TracedChoice {
                    reasoning: choice.reasoning.clone(),
                    claim: choice.claim,
                    all_passed: choice.all_passed,
                    accepted: (choice.accepted.iter())
                        .map(|(call, checked)| (call.clone(), trace_action(checked)))
                        .collect(),
                    later: choice.later.clone(),
                }),
                Err(e) => Err(e.to_string()),
            },
        },
        Input::Sent(result) => TracedInput::Sent {
            result: result.as_ref().copied().map_err(ToString::to_string),
        },
        Input::CallDue => TracedInput::CallDue,
        Input::Coordinate(work) => TracedInput::Coordinate { work: work.clone() },
        Input::CallLost { layer, reason } => TracedInput::CallLost {
            layer: (*layer).to_owned(),
            reason: reason.clone(),
        },
        Input::Closed => TracedInput::Closed,
    }
}

/// `later - earlier` in signed nanoseconds (saturating at about 292 years).
fn signed_ns(later: Instant, earlier: Instant) -> i64 {
    match later.checked_duration_since(earlier) {
        Some(d) => i64::try_from(d.as_nanos()).unwrap_or(i64::MAX),
        None => -i64::try_from(earlier.duration_since(later).as_nanos()).unwrap_or(i64::MAX),
    }
}

/// `at` moved back by `ns` (forward when negative), if the clock reaches that far.
fn before(at: Instant, ns: i64) -> Result<Instant, TraceError> {
    let d = Duration::from_nanos(ns.unsigned_abs());
    let moved = if ns >= 0 {
        at.checked_sub(d)
    } else {
        at.checked_add(d)
    };
    moved.ok_or(TraceError::TimeOutOfReach(ns))
}

fn trace_snapshot(snap: &Snapshot, began: Instant) -> TracedSnapshot {
    let at_ns =
        u64::try_from(snap.now.saturating_duration_since(began).as_nanos()).unwrap_or(u64::MAX);
    TracedSnapshot {
        at_ns,
        drones: (snap.swarm.drones())
            .map(|e| TracedDrone {
                id: e.id.clone(),
                alive: e.alive,
                status: e.status.clone(),
                status_age_ns: e.last_status_at.map(|t| signed_ns(snap.now, t)),
                gone_age_ns: e.gone_at.map(|t| signed_ns(snap.now, t)),
            })
            .collect(),
        targets: snap.targets.clone(),
        ground: snap.ground,
    }
}

/// The model layers a call can be of, by name.
fn layer_named(name: &str) -> Result<&'static str, TraceError> {
    ["coordinator", "supervisor", "monolithic"]
        .into_iter()
        .find(|l| *l == name)
        .ok_or_else(|| TraceError::UnknownLayer(name.to_owned()))
}

fn checked_again(traced: &TracedAction, gate: &SafetyGate) -> Result<CheckedAction, TraceError> {
    gate.recheck(&traced.drone, traced.seen, &traced.action)
        .map_err(|why| TraceError::Refused {
            drone: traced.drone.clone(),
            action: traced.action.to_string(),
            reason: why.to_string(),
        })
}

impl TracedStep {
    /// The input and snapshot again, with the trace's beginning put at `base` (which must
    /// leave room for the ages it holds: a base well after any real instant does).
    pub(crate) fn replayed(
        &self,
        gate: &SafetyGate,
        base: Instant,
    ) -> Result<(Input, Snapshot), TraceError> {
        let recorded = |e: &String| MissionError::Recorded(e.clone());
        let input = match &self.input {
            TracedInput::Started => Input::Started,
            TracedInput::Pilot { text } => Input::Pilot(text.clone()),
            TracedInput::Membership { change } => Input::Membership(change.clone()),
            TracedInput::MembershipMissed => Input::MembershipMissed,
            TracedInput::World { event } => Input::World(event.clone()),
            TracedInput::Tick => Input::Tick,
            TracedInput::Overridden => Input::Overridden,
            TracedInput::CoordinatorReply {
                instruction,
                grounded,
                answer,
            } => Input::CoordinatorReply {
                instruction: instruction.clone(),
                grounded: grounded.clone(),
                answer: answer.clone().map_err(|e| recorded(&e)),
            },
            TracedInput::EarlyCall {
                call,
                checked,
                after,
            } => Input::EarlyCall {
                call: call.clone(),
                checked: checked_again(checked, gate)?,
                after: *after,
            },
            TracedInput::CycleReply { answer } => Input::CycleReply(match answer {
                Ok(choice) => Ok(CycleChoice {
                    reasoning: choice.reasoning.clone(),
                    claim: choice.claim,
                    all_passed: choice.all_passed,
                    accepted: (choice.accepted.iter())
                        .map(|(call, checked)| Ok((call.clone(), checked_again(checked, gate)?)))
                        .collect::<Result<_, TraceError>>()?,
                    later: choice.later.clone(),
                }),
                Err(e) => Err(recorded(e)),
            }),
            TracedInput::Sent { result } => Input::Sent(result.clone().map_err(|e| recorded(&e))),
            TracedInput::CallDue => Input::CallDue,
            TracedInput::Coordinate { work } => Input::Coordinate(work.clone()),
            TracedInput::CallLost { layer, reason } => Input::CallLost {
                layer: layer_named(layer)?,
                reason: reason.clone(),
            },
            TracedInput::Closed => Input::Closed,
        };
        let at_ns = i64::try_from(self.snapshot.at_ns).unwrap_or(i64::MAX);
        let now = before(base, -at_ns)?;
        let drones = (self.snapshot.drones.iter())
            .map(|d| {
                Ok(DroneEntry {
                    id: d.id.clone(),
                    alive: d.alive,
                    status: d.status.clone(),
                    last_status_at: d.status_age_ns.map(|ns| before(now, ns)).transpose()?,
                    gone_at: d.gone_age_ns.map(|ns| before(now, ns)).transpose()?,
                })
            })
            .collect::<Result<Vec<_>, TraceError>>()?;
        let swarm = SwarmView::from_entries(drones);
        let snap = Snapshot {
            swarm,
            targets: self.snapshot.targets.clone(),
            now,
            ground: self.snapshot.ground,
        };
        Ok((input, snap))
    }
}

//! A traced mission (`--trace-steps`) fed again to a fresh core: every step's input and
//! snapshot from the log, in order, and the core's sends compared with the log's — the drone,
//! the action, the plan task and the sequence number of each. A core that decided differently
//! from the same inputs (a rule that read a clock, a hidden state, an order that changed) is
//! seen here. `tacos-ground replay --check LOG` runs it.

use super::core::{Core, Effect, TraceError, TracedInput};
use super::log::{Line, Record};
use crate::safety::SafetyGate;
use std::time::{Duration, Instant};
use tacos_shared::action::Action;

/// One action the mission's core had sent.
#[derive(Debug, Clone, PartialEq)]
pub struct SentAction {
    pub drone: String,
    pub action: Action,
    pub task: String,
    pub seq: u64,
}

impl std::fmt::Display for SentAction {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "#{} {} {} (task {})",
            self.seq, self.drone, self.action, self.task
        )
    }
}

/// What a replay found: the steps fed, and the sends of the replay and of the log.
#[derive(Debug, Clone, PartialEq)]
pub struct Replayed {
    pub steps: usize,
    pub replayed: Vec<SentAction>,
    pub logged: Vec<SentAction>,
}

impl Replayed {
    /// Where the replay's sends first differ from the log's, if they do.
    pub fn first_difference(&self) -> Option<String> {
        let (r, l) = (&self.replayed, &self.logged);
        if let Some(i) = (0..r.len().min(l.len())).find(|&i| r[i] != l[i]) {
            return Some(format!(
                "send {}: the replay sent {}, the log has {}",
                i + 1,
                r[i],
                l[i]
            ));
        }
        match r.len().cmp(&l.len()) {
            std::cmp::Ordering::Equal => None,
            std::cmp::Ordering::Greater => Some(format!(
                "the replay sent {} more than the log has, first {}",
                r.len() - l.len(),
                r[l.len()]
            )),
            std::cmp::Ordering::Less => Some(format!(
                "the log has {} more sends than the replay, first {}",
                l.len() - r.len(),
                l[r.len()]
            )),
        }
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReplayError {
    #[error(
        "the log has no trace of the core's steps: run the mission with --trace-steps to keep one"
    )]
    NoTrace,
    #[error("step {step} of the trace: {source}")]
    Step { step: usize, source: TraceError },
}

/// Feeds the traced steps of `mission` (one mission's lines, `log::last_mission`) to a fresh
/// core judged by `gate` (the mission's map), and collects its sends beside the log's.
pub fn replay(mission: &[Line], gate: &SafetyGate) -> Result<Replayed, ReplayError> {
    let mut core: Option<Core> = None;
    let mut resumed = None;
    // A base well after any instant the trace's ages reach back to.
    let base = Instant::now() + Duration::from_secs(365 * 24 * 3600);
    let mut steps = 0;
    let mut replayed = Vec::new();
    let mut logged = Vec::new();
    // The send the core asked for last, until its result comes back (one at a time).
    let mut sending: Option<(String, Action, String)> = None;
    // A send logged after the trace's last step belongs to a step the trace does not hold yet
    // (the log was read while the mission ran): it is left out.
    let last_step = mission
        .iter()
        .rposition(|l| matches!(l.record, Record::Step(_)));
    for (at, line) in mission.iter().enumerate() {
        match &line.record {
            Record::Resumed { memory, .. } => resumed = Some(memory.clone()),
            Record::TraceBegun { core: traced } => {
                let mut fresh = Core::from_trace(traced);
                if let Some(memory) = resumed.take() {
                    fresh.resume(memory);
                }
                core = Some(fresh);
            }
            Record::Step(step) => {
                let Some(core) = core.as_mut() else {
                    return Err(ReplayError::NoTrace);
                };
                steps += 1;
                let (input, snap) =
                    step.replayed(gate, base)
                        .map_err(|source| ReplayError::Step {
                            step: steps,
                            source,
                        })?;
                if let TracedInput::Sent { result } = &step.input {
                    let went = sending.take();
                    if let (Ok(seq), Some((drone, action, task))) = (result, went) {
                        replayed.push(SentAction {
                            drone,
                            action,
                            task,
                            seq: *seq,
                        });
                    }
                }
                for effect in core.step(input, &snap, gate) {
                    if let Effect::Send { checked, task } = effect {
                        sending =
                            Some((checked.drone().to_string(), checked.action().clone(), task));
                    }
                }
            }
            Record::ActionSent {
                drone,
                task: Some(task),
                seq,
                checked: Some(check),
                ..
            } if core.is_some() && last_step.is_some_and(|last| at < last) => {
                logged.push(SentAction {
                    drone: drone.clone(),
                    action: check.action.clone(),
                    task: task.clone(),
                    seq: *seq,
                })
            }
            _ => {}
        }
    }
    if core.is_none() {
        return Err(ReplayError::NoTrace);
    }
    Ok(Replayed {
        steps,
        replayed,
        logged,
    })
}

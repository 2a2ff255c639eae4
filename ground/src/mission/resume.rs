//! What a mission remembers, in the form it is logged, and its rebuilding from a mission log
//! after the ground station restarted: the Coordinator's history, the world events taken in,
//! and the plan in force (P̂) with each task's state, the action it was sent as and how often
//! it failed (the Supervisor's memory of the plan). Pure: records in, memory out.
//!
//! The engine writes a typed record whenever this memory changes ([`Record::History`],
//! [`Record::WorldEvent`], [`Record::PlanAdopted`], the sends and outcomes of its tasks, the
//! plan's end), and a resumed mission starts its part of the log with [`Record::Resumed`] and
//! the memory it went on from, so a log resumed several times rebuilds the same way.

use super::log::{Line, Record, last_mission};
use serde::{Deserialize, Serialize};
use tacos_prompts::Call;
use tacos_prompts::render::{HistoryEntry, TaskProgress, TaskStatus};
use tacos_shared::DroneId;

/// The format of the mission log written now. 1: a mission can be resumed from it (the records
/// above exist, and an outcome says why it failed); logs without the field are format 0.
pub const LOG_FORMAT: u32 = 1;

/// One task of the plan in force.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanTask {
    pub call: Call,
    pub status: TaskStatus,
    /// The drone and sequence number it was last sent as.
    pub sent: Option<(DroneId, u64)>,
    /// Times this task has failed; the plan is given up at `max_task_failures`.
    pub failures: u32,
}

impl PlanTask {
    /// Where it stands, as the Supervisor's prompt shows it.
    pub fn progress(&self) -> TaskProgress {
        TaskProgress {
            call: self.call.clone(),
            status: self.status.clone(),
            failures: self.failures,
        }
    }
}

/// The plan in force, as it can be saved.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SavedPlan {
    pub reasoning: String,
    pub tasks: Vec<PlanTask>,
    /// Supervisor cycles run for it.
    pub cycles: u32,
}

/// What a mission of the Coordinator and Supervisor remembers.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MissionMemory {
    pub history: Vec<HistoryEntry>,
    pub world_events: Vec<String>,
    pub plan: Option<SavedPlan>,
}

/// A mission log read back for resuming.
#[derive(Debug, Clone, PartialEq)]
pub struct Resumable {
    /// The mode and map the mission ran with (a resumed mission keeps them).
    pub mode: String,
    pub scenario: String,
    /// The drones it started with.
    pub drones: Vec<String>,
    pub memory: MissionMemory,
    /// How the mission ended, when it did (the pilot closed it); none after a crash.
    pub ended: Option<String>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ResumeError {
    #[error("the log holds no mission (no mission_start record)")]
    NoMission,
    #[error(
        "the log was written in format {found} (before missions could be resumed; format {LOG_FORMAT} is needed)"
    )]
    TooOld { found: u32 },
    #[error(
        "a {mode} mission cannot be resumed: only the Coordinator's and Supervisor's (tacos, wor) keep a plan"
    )]
    Monolithic { mode: String },
}

/// Rebuilds the memory of the last mission in `lines` (a reused log holds several).
pub fn rebuild(lines: &[Line]) -> Result<Resumable, ResumeError> {
    let lines = last_mission(lines);
    let (mode, scenario, drones) = match lines.first().map(|l| &l.record) {
        Some(Record::MissionStart {
            mode,
            scenario,
            format,
            drones,
            ..
        }) => {
            if *format < LOG_FORMAT {
                return Err(ResumeError::TooOld { found: *format });
            }
            if mode == "mnl" {
                return Err(ResumeError::Monolithic { mode: mode.clone() });
            }
            (mode.clone(), scenario.clone(), drones.clone())
        }
        _ => return Err(ResumeError::NoMission),
    };
    let mut memory = MissionMemory::default();
    let mut ended = None;
    for line in &lines[1..] {
        memory.take_in(&line.record);
        if let Record::MissionEnd { outcome } = &line.record {
            ended = Some(outcome.clone());
        }
    }
    Ok(Resumable {
        mode,
        scenario,
        drones,
        memory,
        ended,
    })
}

impl MissionMemory {
    /// Applies one record of the log; records that do not change the memory are passed over.
    fn take_in(&mut self, record: &Record) {
        match record {
            Record::Resumed { memory, .. } => *self = memory.clone(),
            Record::History { entry } => self.history.push(entry.clone()),
            Record::WorldEvent { text } => self.world_events.push(text.clone()),
            Record::PlanAdopted { reasoning, tasks } => {
                self.plan = Some(SavedPlan {
                    reasoning: reasoning.clone(),
                    tasks: tasks.clone(),
                    cycles: 0,
                });
            }
            Record::ActionSent {
                drone,
                task: Some(task),
                seq,
                ..
            } => {
                if let (Some(plan), Ok(drone)) = (self.plan.as_mut(), DroneId::new(drone)) {
                    plan.sent(task, drone, *seq);
                }
            }
            Record::ActionOutcome {
                drone,
                task: Some(_),
                seq,
                failure,
                ..
            } => {
                if let Some(plan) = self.plan.as_mut() {
                    plan.finished(drone, *seq, failure.as_deref());
                }
            }
            Record::SupervisorCycle { .. } => {
                if let Some(plan) = self.plan.as_mut() {
                    plan.cycles += 1;
                }
            }
            Record::PlanComplete { .. } | Record::PlanEnded { .. } => self.plan = None,
            _ => {}
        }
    }
}

impl SavedPlan {
    /// Task `task` was sent to `drone` as `seq` (a failed task may go to another drone). The
    /// Supervisor is offered the plan's tasks only, so a task id the plan does not hold is
    /// passed over.
    fn sent(&mut self, task: &str, drone: DroneId, seq: u64) {
        let Some(t) = self.tasks.iter_mut().find(|t| t.call.task == task) else {
            return;
        };
        t.call.drone = drone.to_string();
        t.status = TaskStatus::Running;
        t.sent = Some((drone, seq));
    }

    /// The action `seq` of `drone` ended: done, or failed for `failure`.
    fn finished(&mut self, drone: &str, seq: u64, failure: Option<&str>) {
        let Some(t) = self.tasks.iter_mut().find(|t| {
            t.sent
                .as_ref()
                .is_some_and(|(d, s)| d.as_str() == drone && *s == seq)
        }) else {
            return;
        };
        t.status = match failure {
            Some(why) => {
                t.failures += 1;
                TaskStatus::Failed(why.to_owned())
            }
            None => TaskStatus::Done,
        };
    }
}

#[cfg(test)]
mod tests;

//! The mission log: every model request and reply (with latency and tokens), every action sent
//! and its outcome, every event and replan, as append-only JSON lines (see [`crate::jsonl`]).
//! Each record reaches the kernel when it is written; the records a mission is rebuilt from
//! (plans, actions sent, direct commands, its start and end) are synced to the disk as well, so
//! a power cut loses at most some positions and model traffic. A reused path gets the new
//! mission after the old one, from its own `mission_start` line.

mod summary;

pub use summary::{Tally, timeline};

use super::aids::{Aid, ModelAids};
use super::core::{TracedCore, TracedStep};
use super::resume::{MissionMemory, PlanTask};
use crate::jsonl;
use crate::safety::{CheckedAction, DroneSeen};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use tacos_bus::clock::Clock;
use tacos_prompts::render::HistoryEntry;
use tacos_shared::action::Action;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Record {
    /// The core's steps are traced from here on (`--trace-steps`): what the core was made from.
    TraceBegun {
        core: TracedCore,
    },
    /// One step of the core: its input and snapshot (`core::trace`), before the step's effects.
    Step(TracedStep),
    MissionStart {
        mode: String,
        backend: String,
        scenario: String,
        drones: Vec<String>,
        /// The small-model aids that were on; logs from before they were switches had them all.
        #[serde(default)]
        aids: ModelAids,
        /// The log's format (`resume::LOG_FORMAT`); 0 in logs from before it was recorded.
        #[serde(default)]
        format: u32,
    },
    Pilot {
        text: String,
    },
    Direct {
        text: String,
        outcome: String,
    },
    LlmRequest {
        layer: String,
        attempt: u32,
        messages: serde_json::Value,
    },
    LlmReply {
        layer: String,
        attempt: u32,
        content: String,
        reasoning: Option<String>,
        latency_ms: u64,
        prompt_tokens: u32,
        completion_tokens: u32,
    },
    LlmError {
        layer: String,
        attempt: u32,
        error: String,
    },
    Plan {
        reasoning: String,
        plan: serde_json::Value,
    },
    /// A call of a model's reply was refused (the record's name is historical: most refusals
    /// are the engine's checks', `by` says whose).
    GateRejected {
        layer: String,
        call: String,
        reason: String,
        /// Logs from before it was recorded: the checks.
        #[serde(default)]
        by: RefusedBy,
    },
    ActionSent {
        drone: String,
        task: Option<String>,
        seq: u64,
        /// As the pilot reads it.
        action: String,
        /// The action as sent and what the gate saw of the drone when it let it through: the
        /// audit runs the gate again on these (`eval::criteria::unchecked_sends`). Missing in
        /// logs from before it was recorded.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        checked: Option<SentCheck>,
    },
    ActionOutcome {
        drone: String,
        task: Option<String>,
        seq: u64,
        /// As the pilot reads it.
        outcome: String,
        /// Why a plan's task failed; none when it was done.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        failure: Option<String>,
    },
    SupervisorCycle {
        plan_cycle: u32,
        actions: Vec<String>,
        plan_complete: bool,
    },
    PlanComplete {
        cycles: u32,
    },
    Replan {
        reason: String,
    },
    Event {
        text: String,
    },
    /// A small-model aid changed what the engine did (`mission::aids`).
    AidFired {
        aid: Aid,
        detail: String,
    },
    /// Where a drone was (world ENU), for plots; logged at a low rate.
    Position {
        drone: String,
        x: f64,
        y: f64,
        z: f64,
        speed: f64,
    },
    MissionEnd {
        outcome: String,
    },
    /// The Coordinator's memory of the mission grew by `entry`.
    History {
        entry: HistoryEntry,
    },
    /// A world event taken in (a detection, an injected fault), as the prompts show it.
    WorldEvent {
        text: String,
    },
    /// A plan went in force: its tasks as adopted (a task the previous plan had running and
    /// this one repeats keeps running).
    PlanAdopted {
        reasoning: String,
        tasks: Vec<PlanTask>,
    },
    /// The plan in force ended without completing: given up, interrupted, replaced.
    PlanEnded {
        how: String,
    },
    /// The mission went on from the log `from` after the ground station restarted, with this
    /// memory (`mission::resume`).
    Resumed {
        from: String,
        memory: MissionMemory,
    },
}

/// Who refused a model's call.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RefusedBy {
    /// The engine's checks: the reply's form, the plan's rules, the live state (busy, done).
    #[default]
    Checks,
    /// The safety gate, on the action the call resolved to.
    SafetyGate,
}

impl std::fmt::Display for RefusedBy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            RefusedBy::Checks => "the checks",
            RefusedBy::SafetyGate => "the safety gate",
        })
    }
}

/// The typed half of [`Record::ActionSent`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SentCheck {
    pub action: Action,
    pub seen: DroneSeen,
}

impl Record {
    /// The record of an action that passed the gate and was sent as `seq`.
    pub fn action_sent(checked: &CheckedAction, task: Option<String>, seq: u64) -> Record {
        Record::ActionSent {
            drone: checked.drone().to_string(),
            task,
            seq,
            action: checked.action().to_string(),
            checked: Some(SentCheck {
                action: checked.action().clone(),
                seen: checked.seen(),
            }),
        }
    }
}

/// One line of the log: seconds since the mission started, and the record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Line {
    pub t: f64,
    #[serde(flatten)]
    pub record: Record,
}

impl Record {
    /// The records a mission is rebuilt from: worth a wait for the disk.
    fn must_persist(&self) -> bool {
        matches!(
            self,
            Record::MissionStart { .. }
                | Record::Pilot { .. }
                | Record::Direct { .. }
                | Record::Plan { .. }
                | Record::ActionSent { .. }
                | Record::PlanComplete { .. }
                | Record::Replan { .. }
                | Record::MissionEnd { .. }
                | Record::History { .. }
                | Record::WorldEvent { .. }
                | Record::PlanAdopted { .. }
                | Record::PlanEnded { .. }
                | Record::Resumed { .. }
        )
    }
}

#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("mission log {path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

pub struct MissionLog {
    file: Mutex<File>,
    path: PathBuf,
    /// Times in the log are seconds of this clock since `start_s`: the simulator's in a
    /// simulated run, so that speeds drawn from the positions stay true at any pace.
    clock: Clock,
    start_s: f64,
}

impl MissionLog {
    /// Creates the log at `path`, or appends to it after repairing a torn last line.
    pub fn create(path: &Path) -> Result<MissionLog, LogError> {
        let (file, repair) = jsonl::open_append(path).map_err(|source| LogError::Io {
            path: path.display().to_string(),
            source,
        })?;
        if let Some(repair) = repair {
            tracing::warn!(path = %path.display(), ?repair, "mission log had a torn last line");
        }
        let clock = Clock::wall();
        Ok(MissionLog {
            file: Mutex::new(file),
            path: path.to_owned(),
            start_s: clock.now(),
            clock,
        })
    }

    /// The same log, timed by `clock` from now on (the ground link's clock).
    pub fn timed_by(mut self, clock: &Clock) -> MissionLog {
        self.start_s = clock.now();
        self.clock = clock.clone();
        self
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn elapsed(&self) -> f64 {
        self.clock.now() - self.start_s
    }

    /// Appends one record (synced to the disk when it is one a mission is rebuilt from). A
    /// failing disk is reported, never a panic.
    /// Records that a small-model aid changed what the engine did (`mission::aids`).
    pub fn aid_fired(&self, aid: Aid, detail: String) {
        tracing::debug!(%aid, %detail, "small-model aid fired");
        self.note(Record::AidFired { aid, detail });
    }

    pub fn write(&self, record: Record) -> Result<(), LogError> {
        self.write_all(vec![record])
    }

    /// Appends several records with one sync for all of them (when any is one a mission is
    /// rebuilt from): a sync takes milliseconds, and `land all` logs a send per drone.
    pub fn write_all(&self, records: Vec<Record>) -> Result<(), LogError> {
        let io = |source| LogError::Io {
            path: self.path.display().to_string(),
            source,
        };
        let sync = records.iter().any(Record::must_persist);
        let t = self.elapsed();
        let mut file = self.file.lock().unwrap_or_else(|p| p.into_inner());
        for record in records {
            jsonl::append(&mut file, &Line { t, record }, false).map_err(io)?;
        }
        if sync {
            file.sync_data().map_err(io)?;
        }
        Ok(())
    }

    /// Like [`write`](Self::write), but a failure is only reported through tracing: the mission
    /// goes on when the disk is full.
    pub fn note(&self, record: Record) {
        self.note_all(vec![record]);
    }

    /// [`write_all`](Self::write_all), a failure only reported through tracing.
    pub fn note_all(&self, records: Vec<Record>) {
        if let Err(e) = self.write_all(records) {
            tracing::error!(error = %e, "mission log write failed");
        }
    }
}

/// Reads a whole log. Lines that are not records (a tail cut short by a crash, a partial write
/// on a full disk) are skipped, each with a warning; [`read_checked`] returns them.
pub fn read(path: &Path) -> Result<Vec<Line>, LogError> {
    let contents = read_checked(path)?;
    for s in &contents.skipped {
        tracing::warn!(path = %path.display(), line = s.line, reason = %s.reason, "mission log line skipped");
    }
    Ok(contents.records)
}

/// The records of a log and the lines that were not records.
pub fn read_checked(path: &Path) -> Result<jsonl::Contents<Line>, LogError> {
    jsonl::read(path).map_err(|source| LogError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// The lines of the last mission in a log that holds several (a reused `--log` path): from its
/// last `mission_start` on; all of them when there is none.
pub fn last_mission(lines: &[Line]) -> &[Line] {
    let start = lines
        .iter()
        .rposition(|l| matches!(l.record, Record::MissionStart { .. }))
        .unwrap_or(0);
    &lines[start..]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_reused_path_after_a_crash_reads_as_two_missions() {
        let dir = std::env::temp_dir().join(format!("tacos-log-reuse-{}", std::process::id()));
        let path = dir.join("mission.jsonl");
        let _ = std::fs::remove_dir_all(&dir);
        let start = |backend: &str| Record::MissionStart {
            mode: "tacos".into(),
            backend: backend.into(),
            scenario: "city".into(),
            drones: vec!["alfa".into()],
            aids: ModelAids::small(),
            format: crate::mission::resume::LOG_FORMAT,
        };
        let first = MissionLog::create(&path).expect("create");
        first.write(start("first")).expect("write");
        drop(first);
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .expect("open");
        std::io::Write::write_all(&mut f, b"{\"t\":3.0,\"kind\":\"pil").expect("append");
        let second = MissionLog::create(&path).expect("reopen");
        second.write(start("second")).expect("write");
        second
            .write(Record::Pilot {
                text: "alfa, take off".into(),
            })
            .expect("write");
        let all = read_checked(&path).expect("read");
        assert!(
            all.skipped.is_empty(),
            "the torn line was repaired: {:?}",
            all.skipped
        );
        assert_eq!(all.records.len(), 3);
        let last = last_mission(&all.records);
        assert_eq!(last.len(), 2);
        assert_eq!(last[0].record, start("second"));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn records_survive_a_crash_mid_line() {
        let dir = std::env::temp_dir().join(format!("tacos-log-{}", std::process::id()));
        let path = dir.join("mission.jsonl");
        let _ = std::fs::remove_file(&path);
        let log = MissionLog::create(&path).expect("create");
        log.write(Record::Pilot {
            text: "all drones take off".into(),
        })
        .expect("write");
        // Several at once, with one sync (a direct command's sends and the command).
        log.write_all(vec![
            Record::ActionSent {
                drone: "alfa".into(),
                task: Some("T1".into()),
                seq: 9,
                action: "arm_takeoff()".into(),
                checked: None,
            },
            Record::Direct {
                text: "hold all".into(),
                outcome: "hold() sent to alfa".into(),
            },
        ])
        .expect("write");
        drop(log);
        // A crash in the middle of the next record.
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .expect("open");
        std::io::Write::write_all(&mut f, b"{\"t\":3.0,\"kind\":\"pil").expect("append");
        let lines = read(&path).expect("read");
        assert_eq!(lines.len(), 3);
        assert!(matches!(lines[2].record, Record::Direct { .. }));
        assert_eq!(
            lines[0].record,
            Record::Pilot {
                text: "all drones take off".into()
            }
        );
        let tally = Tally::of(&lines);
        assert_eq!((tally.model_actions, tally.direct_actions), (1, 0));
        let text = timeline(&lines);
        assert!(
            text.contains("pilot: all drones take off")
                && text.contains("sent #9 arm_takeoff() to alfa"),
            "{text}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}

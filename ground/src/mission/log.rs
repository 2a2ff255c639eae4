//! The mission log: every model request and reply (with latency and tokens), every action sent
//! and its outcome, every event and replan, as append-only JSON lines (see [`crate::jsonl`]).
//! Each record reaches the kernel when it is written; the records a mission is rebuilt from
//! (plans, actions sent, direct commands, its start and end) are synced to the disk as well, so
//! a power cut loses at most some positions and model traffic. A reused path gets the new
//! mission after the old one, from its own `mission_start` line.

use super::aids::{Aid, ModelAids};
use crate::jsonl;
use crate::safety::{CheckedAction, DroneSeen};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use tacos_bus::clock::Clock;
use tacos_shared::action::Action;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Record {
    MissionStart {
        mode: String,
        backend: String,
        scenario: String,
        drones: Vec<String>,
        /// The small-model aids that were on; logs from before they were switches had them all.
        #[serde(default)]
        aids: ModelAids,
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
        outcome: String,
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

/// What a mission did, counted from its records: a run's closing summary, which therefore
/// agrees with the log however the run ended (a model call still in flight included).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Tally {
    /// Requests to a model (repair rounds included).
    pub model_calls: usize,
    pub supervisor_cycles: usize,
    /// Actions sent for a model's plan or cycle (they carry a task).
    pub model_actions: usize,
    /// Actions sent for the pilot's direct commands.
    pub direct_actions: usize,
    /// Calls of the models' replies that the engine's checks refused.
    pub rejections: usize,
    /// … and that the safety gate refused.
    pub gate_refusals: usize,
    /// Times a small-model aid changed what the engine did.
    pub aids_fired: usize,
}

impl Tally {
    pub fn of(lines: &[Line]) -> Tally {
        let mut t = Tally::default();
        for line in lines {
            match &line.record {
                Record::LlmRequest { .. } => t.model_calls += 1,
                Record::SupervisorCycle { .. } => t.supervisor_cycles += 1,
                Record::ActionSent { task: Some(_), .. } => t.model_actions += 1,
                Record::ActionSent { task: None, .. } => t.direct_actions += 1,
                Record::GateRejected {
                    by: RefusedBy::Checks,
                    ..
                } => t.rejections += 1,
                Record::GateRejected {
                    by: RefusedBy::SafetyGate,
                    ..
                } => t.gate_refusals += 1,
                Record::AidFired { .. } => t.aids_fired += 1,
                _ => {}
            }
        }
        t
    }
}

impl std::fmt::Display for Tally {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} model calls, {} supervisor cycles, {} actions sent by the models, {} by direct commands, {} calls refused by the checks and {} by the safety gate, {} small-model aids fired",
            self.model_calls,
            self.supervisor_cycles,
            self.model_actions,
            self.direct_actions,
            self.rejections,
            self.gate_refusals,
            self.aids_fired
        )
    }
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

/// The mission's timeline as text, one line per record (positions left out).
pub fn timeline(lines: &[Line]) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    for l in lines {
        let text = match &l.record {
            Record::MissionStart {
                mode,
                backend,
                scenario,
                drones,
                aids,
            } => {
                format!(
                    "mission start: mode {mode}, {backend}, map {scenario}, drones {}, aids {aids}",
                    drones.join(", ")
                )
            }
            Record::Pilot { text } => format!("pilot: {text}"),
            Record::Direct { text, outcome } => format!("direct command {text:?}: {outcome}"),
            Record::LlmRequest { layer, attempt, .. } => {
                format!("{layer}: request (attempt {attempt})")
            }
            Record::LlmReply {
                layer,
                latency_ms,
                prompt_tokens,
                completion_tokens,
                ..
            } => {
                format!(
                    "{layer}: reply in {latency_ms} ms ({prompt_tokens} prompt + {completion_tokens} completion tokens)"
                )
            }
            Record::LlmError { layer, error, .. } => format!("{layer}: error: {error}"),
            Record::Plan { reasoning, plan } => format!("plan: {reasoning} {plan}"),
            Record::GateRejected {
                layer,
                call,
                reason,
                by,
            } => {
                let why = if reason.is_empty() {
                    String::new()
                } else {
                    format!(": {reason}")
                };
                format!("{by} refused the {layer}'s {call}{why}")
            }
            Record::ActionSent {
                drone, seq, action, ..
            } => format!("sent #{seq} {action} to {drone}"),
            Record::ActionOutcome {
                drone,
                seq,
                outcome,
                ..
            } => format!("{drone} #{seq}: {outcome}"),
            Record::SupervisorCycle {
                plan_cycle,
                actions,
                plan_complete,
            } => {
                format!(
                    "supervisor cycle {plan_cycle}: [{}]{}",
                    actions.join("; "),
                    if *plan_complete { " plan complete" } else { "" }
                )
            }
            Record::PlanComplete { cycles } => {
                format!("plan complete after {cycles} supervisor cycles")
            }
            Record::Replan { reason } => format!("replan: {reason}"),
            Record::Event { text } => format!("event: {text}"),
            Record::AidFired { aid, detail } => format!("aid {aid}: {detail}"),
            Record::Position { .. } => continue,
            Record::MissionEnd { outcome } => format!("mission end: {outcome}"),
        };
        let _ = writeln!(out, "[{:>7.1}s] {text}", l.t);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refusals_are_counted_by_who_refused() {
        let line = |t: f64, record: Record| Line { t, record };
        let refused = |by| Record::GateRejected {
            layer: "supervisor".into(),
            call: "T1 alfa goto(car_1): why".into(),
            reason: String::new(),
            by,
        };
        // A record from before `by` was written reads as the checks'.
        let old: Line = serde_json::from_str(
            r#"{"t": 3.0, "kind": "gate_rejected", "layer": "coordinator", "call": "T2 bravo land()", "reason": ""}"#,
        )
        .expect("an old record reads");
        let lines = [
            line(1.0, refused(RefusedBy::Checks)),
            line(2.0, refused(RefusedBy::SafetyGate)),
            old,
        ];
        let tally = Tally::of(&lines);
        assert_eq!((tally.rejections, tally.gate_refusals), (2, 1));
        assert!(timeline(&lines).contains("the safety gate refused the supervisor's T1 alfa"));
    }

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

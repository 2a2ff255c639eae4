//! The mission log: every model request and reply (with latency and tokens), every action sent
//! and its outcome, every event and replan, as append-only JSON lines. Each record is written
//! and flushed on its own, so a crash loses nothing that was logged.

use serde::{Deserialize, Serialize};
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use tacos_bus::clock::Clock;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Record {
    MissionStart {
        mode: String,
        backend: String,
        scenario: String,
        drones: Vec<String>,
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
    GateRejected {
        layer: String,
        call: String,
        reason: String,
    },
    ActionSent {
        drone: String,
        task: Option<String>,
        seq: u64,
        action: String,
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

/// One line of the log: seconds since the mission started, and the record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Line {
    pub t: f64,
    #[serde(flatten)]
    pub record: Record,
}

#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("mission log {path}: {reason}")]
    Io { path: String, reason: String },
    #[error("mission log {path}, line {line}: {reason}")]
    Parse {
        path: String,
        line: usize,
        reason: String,
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
    /// Creates (or appends to) the log at `path`.
    pub fn create(path: &Path) -> Result<MissionLog, LogError> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| LogError::Io {
                path: dir.display().to_string(),
                reason: e.to_string(),
            })?;
        }
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(|e| LogError::Io {
                path: path.display().to_string(),
                reason: e.to_string(),
            })?;
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

    /// Appends one record and flushes it. A failing disk is reported, never a panic.
    pub fn write(&self, record: Record) -> Result<(), LogError> {
        let line = Line {
            t: self.elapsed(),
            record,
        };
        let mut text = serde_json::to_string(&line).map_err(|e| LogError::Io {
            path: self.path.display().to_string(),
            reason: e.to_string(),
        })?;
        text.push('\n');
        let mut file = self.file.lock().unwrap_or_else(|p| p.into_inner());
        file.write_all(text.as_bytes())
            .and_then(|_| file.flush())
            .map_err(|e| LogError::Io {
                path: self.path.display().to_string(),
                reason: e.to_string(),
            })
    }

    /// Like [`write`](Self::write), but a failure is only reported through tracing: the mission
    /// goes on when the disk is full.
    pub fn note(&self, record: Record) {
        if let Err(e) = self.write(record) {
            tracing::error!(error = %e, "mission log write failed");
        }
    }
}

/// Reads a whole log. A last line cut short by a crash is skipped; any other bad line is an error.
pub fn read(path: &Path) -> Result<Vec<Line>, LogError> {
    let file = File::open(path).map_err(|e| LogError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    })?;
    let lines: Vec<String> = BufReader::new(file)
        .lines()
        .collect::<Result<_, _>>()
        .map_err(|e| LogError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
    let last = lines.len();
    let mut out = Vec::new();
    for (i, text) in lines.iter().enumerate() {
        if text.trim().is_empty() {
            continue;
        }
        match serde_json::from_str::<Line>(text) {
            Ok(line) => out.push(line),
            Err(_) if i + 1 == last => break,
            Err(e) => {
                return Err(LogError::Parse {
                    path: path.display().to_string(),
                    line: i + 1,
                    reason: e.to_string(),
                });
            }
        }
    }
    Ok(out)
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
            } => {
                format!(
                    "mission start: mode {mode}, {backend}, map {scenario}, drones {}",
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
            } => format!("safety gate rejected {call} from {layer}: {reason}"),
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
    fn records_survive_a_crash_mid_line() {
        let dir = std::env::temp_dir().join(format!("tacos-log-{}", std::process::id()));
        let path = dir.join("mission.jsonl");
        let _ = std::fs::remove_file(&path);
        let log = MissionLog::create(&path).expect("create");
        log.write(Record::Pilot {
            text: "all drones take off".into(),
        })
        .expect("write");
        log.write(Record::ActionSent {
            drone: "alfa".into(),
            task: Some("T1".into()),
            seq: 9,
            action: "arm_takeoff()".into(),
        })
        .expect("write");
        drop(log);
        // A crash in the middle of the next record.
        let mut f = OpenOptions::new().append(true).open(&path).expect("open");
        f.write_all(b"{\"t\":3.0,\"kind\":\"pil").expect("append");
        let lines = read(&path).expect("read");
        assert_eq!(lines.len(), 2);
        assert_eq!(
            lines[0].record,
            Record::Pilot {
                text: "all drones take off".into()
            }
        );
        let text = timeline(&lines);
        assert!(
            text.contains("pilot: all drones take off")
                && text.contains("sent #9 arm_takeoff() to alfa"),
            "{text}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}

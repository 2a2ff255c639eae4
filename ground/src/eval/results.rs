//! Run records (one JSON line per finished run, appended and flushed as each run ends, so an
//! interrupted evaluation resumes where it stopped), their statistics per (mode, swarm size),
//! and the table as Markdown and CSV.

use crate::jsonl;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashSet};
use std::fmt::Write as _;
use std::fs::File;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    Success,
    Failure,
    /// The run could not be carried out (a process died, the swarm did not come up): it says
    /// nothing about the model, is left out of the statistics and is run again on resume.
    Error,
}

/// One finished run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunRecord {
    pub task: String,
    pub mode: String,
    pub drones: usize,
    pub run: u32,
    /// The seed given to every model request of the run.
    pub seed: u64,
    pub backend: String,
    /// The small-model aids that were on (`mission::aids`); runs recorded before they were
    /// switches had them all.
    #[serde(default = "all_aids")]
    pub aids: String,
    pub status: Status,
    pub reason: String,
    /// Wall-clock seconds the run took, set-up and shut-down included.
    pub elapsed_s: f64,
    /// Simulated seconds per wall second between model calls (`--sim-speed`); records written
    /// before the speed was recorded ran at 1.
    #[serde(default = "real_time")]
    pub sim_speed: f64,
    /// Mission time (the simulator's clock) from the first pilot line to the verdict; `None`
    /// when the run broke before its mission started.
    #[serde(default)]
    pub mission_s: Option<f64>,
    /// Supervisor (or monolithic) cycles.
    pub cycles: u32,
    pub model_calls: u32,
    pub replies: u32,
    pub latency_ms_total: u64,
    pub prompt_tokens: u64,
    pub completion_tokens: u64,
    pub gate_rejections: u32,
    pub actions_sent: u32,
    pub separation_breaches: u64,
    pub obstacle_breaches: u64,
    pub detected_by: Option<String>,
    /// The drone failed on purpose, and when (seconds from the first pilot line).
    pub fault: Option<String>,
    pub log: String,
}

fn real_time() -> f64 {
    1.0
}

fn all_aids() -> String {
    crate::mission::ModelAids::small().to_string()
}

impl RunRecord {
    pub fn key(&self) -> RunKey {
        RunKey {
            mode: self.mode.clone(),
            drones: self.drones,
            run: self.run,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct RunKey {
    pub mode: String,
    pub drones: usize,
    pub run: u32,
}

#[derive(Debug, thiserror::Error)]
pub enum ResultsError {
    #[error("{path}: {reason}")]
    Io { path: String, reason: String },
    #[error("{path} holds runs of {held}; this evaluation is {wanted}: use another --out")]
    Mismatch {
        path: String,
        /// What the file's runs are: task, model and aids.
        held: String,
        wanted: String,
    },
}

fn io(path: &Path, e: impl std::fmt::Display) -> ResultsError {
    ResultsError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    }
}

/// The append-only file of run records (`runs.jsonl` in the output directory).
pub struct RunsFile {
    path: PathBuf,
    file: File,
}

impl RunsFile {
    /// Opens (or creates) the file; a last line cut short by an interruption is repaired, so
    /// the next record starts on a line of its own.
    pub fn open(path: &Path) -> Result<RunsFile, ResultsError> {
        let (file, repair) = jsonl::open_append(path).map_err(|e| io(path, e))?;
        if let Some(repair) = repair {
            tracing::warn!(path = %path.display(), ?repair, "runs file had a torn last line");
        }
        Ok(RunsFile {
            path: path.to_owned(),
            file,
        })
    }

    /// Appends one record and syncs it to the disk.
    pub fn append(&mut self, record: &RunRecord) -> Result<(), ResultsError> {
        jsonl::append(&mut self.file, record, true).map_err(|e| io(&self.path, e))
    }
}

/// Reads the records so far (none when the file does not exist). A line that is not a record
/// (cut short by an interruption) is skipped with a warning: its run is carried out again.
pub fn read_runs(path: &Path) -> Result<Vec<RunRecord>, ResultsError> {
    let contents = match jsonl::read::<RunRecord>(path) {
        Ok(c) => c,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io(path, e)),
    };
    for s in &contents.skipped {
        tracing::warn!(path = %path.display(), line = s.line, reason = %s.reason, "runs file line skipped");
    }
    Ok(contents.records)
}

/// The runs already carried out (success or failure; errors are run again). Records of another
/// task, model or aids are refused: mixing them would make the table meaningless.
pub fn done_runs(
    path: &Path,
    records: &[RunRecord],
    task: &str,
    backend: &str,
    aids: &str,
) -> Result<HashSet<RunKey>, ResultsError> {
    if let Some(other) = records
        .iter()
        .find(|r| r.task != task || r.backend != backend || r.aids != aids)
    {
        let what = |task: &str, backend: &str, aids: &str| {
            format!("task {task:?} with {backend:?} (aids {aids})")
        };
        return Err(ResultsError::Mismatch {
            path: path.display().to_string(),
            held: what(&other.task, &other.backend, &other.aids),
            wanted: what(task, backend, aids),
        });
    }
    Ok(records
        .iter()
        .filter(|r| r.status != Status::Error)
        .map(RunRecord::key)
        .collect())
}

/// The 95 % Wilson score interval of a success proportion (`successes` of `n`); (0, 1) for n = 0.
pub fn wilson_interval(successes: u32, n: u32) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    const Z: f64 = 1.959_963_984_540_054;
    let n = f64::from(n);
    let p = f64::from(successes) / n;
    let z2 = Z * Z;
    let centre = p + z2 / (2.0 * n);
    let spread = Z * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt();
    let denominator = 1.0 + z2 / n;
    (
        ((centre - spread) / denominator).max(0.0),
        ((centre + spread) / denominator).min(1.0),
    )
}

/// The figures of one (mode, swarm size) cell.
#[derive(Debug, Clone, PartialEq)]
pub struct Cell {
    pub mode: String,
    pub drones: usize,
    /// Runs that count (errors left out).
    pub runs: u32,
    pub successes: u32,
    pub errors: u32,
    pub rate: f64,
    pub interval: (f64, f64),
    /// Mean Supervisor cycles over successful runs only, as the paper computes L.
    pub mean_cycles: Option<f64>,
    pub mean_model_calls: f64,
    /// Mean latency of one model reply, over every reply of the cell.
    pub mean_latency_s: Option<f64>,
    pub mean_tokens: f64,
    /// Mean wall-clock seconds per run.
    pub mean_wall_s: f64,
    /// Mean mission (simulated) seconds per run, over runs whose mission started.
    pub mean_mission_s: Option<f64>,
}

/// One cell per (mode, swarm size) present in `records`, in the order of `modes` then size.
pub fn cells(records: &[RunRecord], modes: &[String]) -> Vec<Cell> {
    let mut groups: BTreeMap<(usize, usize), Vec<&RunRecord>> = BTreeMap::new();
    for r in records {
        let order = modes
            .iter()
            .position(|m| *m == r.mode)
            .unwrap_or(modes.len());
        groups.entry((order, r.drones)).or_default().push(r);
    }
    groups
        .into_values()
        .map(|rs| {
            let counted: Vec<&&RunRecord> =
                rs.iter().filter(|r| r.status != Status::Error).collect();
            let wins: Vec<&&&RunRecord> = counted
                .iter()
                .filter(|r| r.status == Status::Success)
                .collect();
            let runs = counted.len() as u32;
            let successes = wins.len() as u32;
            let replies: u64 = counted.iter().map(|r| u64::from(r.replies)).sum();
            let latency: u64 = counted.iter().map(|r| r.latency_ms_total).sum();
            let per_run = |f: &dyn Fn(&RunRecord) -> f64| {
                if runs == 0 {
                    0.0
                } else {
                    counted.iter().map(|r| f(r)).sum::<f64>() / f64::from(runs)
                }
            };
            Cell {
                mode: rs[0].mode.clone(),
                drones: rs[0].drones,
                runs,
                successes,
                errors: rs.len() as u32 - runs,
                rate: if runs == 0 {
                    0.0
                } else {
                    f64::from(successes) / f64::from(runs)
                },
                interval: wilson_interval(successes, runs),
                mean_cycles: (successes > 0).then(|| {
                    wins.iter().map(|r| f64::from(r.cycles)).sum::<f64>() / f64::from(successes)
                }),
                mean_model_calls: per_run(&|r| f64::from(r.model_calls)),
                mean_latency_s: (replies > 0).then(|| latency as f64 / 1000.0 / replies as f64),
                mean_tokens: per_run(&|r| (r.prompt_tokens + r.completion_tokens) as f64),
                mean_wall_s: per_run(&|r| r.elapsed_s),
                mean_mission_s: mean(counted.iter().filter_map(|r| r.mission_s)),
            }
        })
        .collect()
}

fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0u32), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / f64::from(n))
}

/// The simulation speeds the records ran at, for the table's heading ("2×", "1×, 2×").
fn speeds(records: &[RunRecord]) -> String {
    let mut seen: Vec<f64> = Vec::new();
    for r in records {
        if !seen.iter().any(|s| (s - r.sim_speed).abs() < 1e-9) {
            seen.push(r.sim_speed);
        }
    }
    seen.sort_by(f64::total_cmp);
    seen.iter()
        .map(|s| format!("{s}×"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "–".to_owned(), |v| format!("{v:.digits$}"))
}

/// The table as Markdown; `records` are the runs behind `cells` (for the simulation speed).
pub fn markdown(task: &str, backend: &str, cells: &[Cell], records: &[RunRecord]) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "# {task}: {backend}\n");
    if !records.is_empty() {
        let _ = writeln!(
            out,
            "Simulation speed between model calls: {} (model calls run at real time). Wall time is per run, set-up included; mission time is the simulator's, from the first pilot line.\n",
            speeds(records)
        );
    }
    let _ = writeln!(
        out,
        "| mode | drones | runs | success | success rate (95 % Wilson) | mean L (successes) | model calls / run | mean call latency (s) | tokens / run | wall (s) / run | mission (s) / run | errors |"
    );
    let _ = writeln!(
        out,
        "| --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
    );
    for c in cells {
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} | {:.0} % [{:.0}, {:.0}] | {} | {:.1} | {} | {:.0} | {:.0} | {} | {} |",
            c.mode,
            c.drones,
            c.runs,
            c.successes,
            100.0 * c.rate,
            100.0 * c.interval.0,
            100.0 * c.interval.1,
            opt(c.mean_cycles, 2),
            c.mean_model_calls,
            opt(c.mean_latency_s, 1),
            c.mean_tokens,
            c.mean_wall_s,
            opt(c.mean_mission_s, 0),
            c.errors
        );
    }
    out
}

/// The table as CSV (rates as fractions, empty where undefined).
pub fn csv(cells: &[Cell]) -> String {
    let mut out = String::from(
        "mode,drones,runs,successes,success_rate,wilson_low,wilson_high,mean_l,mean_model_calls,mean_call_latency_s,mean_tokens,mean_wall_s,mean_mission_s,errors\n",
    );
    let empty = |v: Option<f64>| v.map_or_else(String::new, |v| format!("{v:.4}"));
    for c in cells {
        let _ = writeln!(
            out,
            "{},{},{},{},{:.4},{:.4},{:.4},{},{:.2},{},{:.1},{:.1},{},{}",
            c.mode,
            c.drones,
            c.runs,
            c.successes,
            c.rate,
            c.interval.0,
            c.interval.1,
            empty(c.mean_cycles),
            c.mean_model_calls,
            empty(c.mean_latency_s),
            c.mean_tokens,
            c.mean_wall_s,
            empty(c.mean_mission_s),
            c.errors
        );
    }
    out
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn record(
        mode: &str,
        drones: usize,
        run: u32,
        status: Status,
        cycles: u32,
    ) -> RunRecord {
        RunRecord {
            task: "find-suspect".into(),
            mode: mode.into(),
            drones,
            run,
            seed: 1,
            backend: "m".into(),
            aids: "small".into(),
            status,
            reason: String::new(),
            elapsed_s: 1.0,
            sim_speed: 2.0,
            mission_s: Some(1.5),
            cycles,
            model_calls: 4,
            replies: 4,
            latency_ms_total: 8000,
            prompt_tokens: 900,
            completion_tokens: 100,
            gate_rejections: 0,
            actions_sent: 3,
            separation_breaches: 0,
            obstacle_breaches: 0,
            detected_by: None,
            fault: None,
            log: "x.jsonl".into(),
        }
    }

    #[test]
    fn wilson_matches_known_values() {
        // Reference values (Wilson 1927; e.g. Newcombe 1998, table I).
        let (lo, hi) = wilson_interval(81, 263);
        assert!(
            (lo - 0.2553).abs() < 5e-4 && (hi - 0.3662).abs() < 5e-4,
            "{lo} {hi}"
        );
        let (lo, hi) = wilson_interval(0, 10);
        assert!(lo == 0.0 && (hi - 0.2775).abs() < 5e-4, "{lo} {hi}");
        let (lo, hi) = wilson_interval(10, 10);
        assert!(
            (lo - 0.7225).abs() < 5e-4 && (hi - 1.0).abs() < 1e-12,
            "{lo} {hi}"
        );
        assert_eq!(wilson_interval(0, 0), (0.0, 1.0));
    }

    #[test]
    fn l_is_averaged_over_successes_only_and_errors_are_left_out() {
        let records = vec![
            record("tacos", 6, 0, Status::Success, 3),
            record("tacos", 6, 1, Status::Success, 5),
            record("tacos", 6, 2, Status::Failure, 30),
            record("tacos", 6, 3, Status::Error, 0),
            record("mnl", 6, 0, Status::Failure, 9),
        ];
        let cells = cells(&records, &["tacos".into(), "mnl".into()]);
        assert_eq!(cells.len(), 2);
        let t = &cells[0];
        assert_eq!(
            (t.mode.as_str(), t.runs, t.successes, t.errors),
            ("tacos", 3, 2, 1)
        );
        assert_eq!(t.mean_cycles, Some(4.0));
        assert!((t.rate - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(t.mean_latency_s, Some(2.0));
        assert_eq!(t.mean_tokens, 1000.0);
        assert_eq!((t.mean_wall_s, t.mean_mission_s), (1.0, Some(1.5)));
        let m = &cells[1];
        assert_eq!(
            (m.mode.as_str(), m.successes, m.mean_cycles),
            ("mnl", 0, None)
        );
        let md = markdown("find-suspect", "m", &cells, &records);
        assert!(
            md.contains("| tacos | 6 | 3 | 2 | 67 % [") && md.contains("| 4.00 |"),
            "{md}"
        );
        assert!(
            md.contains("Simulation speed between model calls: 2×"),
            "{md}"
        );
        let csv = csv(&cells);
        assert!(
            csv.lines()
                .nth(2)
                .is_some_and(|l| l.starts_with("mnl,6,1,0,0.0000,") && l.contains(",,")),
            "{csv}"
        );
    }

    #[test]
    fn resume_skips_finished_runs_reruns_errors_and_survives_a_cut_line() {
        let dir = std::env::temp_dir().join(format!("tacos-eval-resume-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let path = dir.join("runs.jsonl");
        assert!(read_runs(&path).expect("no file yet").is_empty());
        let mut file = RunsFile::open(&path).expect("open");
        file.append(&record("tacos", 6, 0, Status::Success, 3))
            .expect("append");
        file.append(&record("tacos", 6, 1, Status::Error, 0))
            .expect("append");
        drop(file);
        // An interruption in the middle of the next record.
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .expect("open");
        std::io::Write::write_all(&mut f, b"{\"task\":\"find-su").expect("append");
        drop(f);
        let records = read_runs(&path).expect("read");
        assert_eq!(records.len(), 2);
        let done =
            done_runs(&path, &records, "find-suspect", "m", "small").expect("same evaluation");
        let key = |run| RunKey {
            mode: "tacos".into(),
            drones: 6,
            run,
        };
        assert!(done.contains(&key(0)) && !done.contains(&key(1)));
        assert!(matches!(
            done_runs(&path, &records, "find-suspect", "another model", "small"),
            Err(ResultsError::Mismatch { .. })
        ));
        // Resuming appends after the last whole record.
        let mut file = RunsFile::open(&path).expect("reopen");
        file.append(&record("tacos", 6, 1, Status::Failure, 7))
            .expect("append");
        let records = read_runs(&path).expect("read again");
        assert_eq!(records.len(), 3);
        let done =
            done_runs(&path, &records, "find-suspect", "m", "small").expect("same evaluation");
        assert!(done.contains(&key(1)));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn records_from_before_the_speed_was_recorded_read_as_real_time() {
        let mut value =
            serde_json::to_value(record("tacos", 6, 0, Status::Success, 3)).expect("to json");
        let fields = value.as_object_mut().expect("an object");
        fields.remove("sim_speed");
        fields.remove("mission_s");
        let old: RunRecord = serde_json::from_value(value).expect("an old record still reads");
        assert_eq!((old.sim_speed, old.mission_s), (1.0, None));
    }
}

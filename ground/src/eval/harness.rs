//! `tacos-ground eval`: every (mode, swarm size, run) of a task, with a progress display, each
//! finished run appended to `runs.jsonl` at once (so the same output directory resumes), and the
//! table (`results.md`, `results.csv`) and chart (`results.svg`) rewritten after every run.

use super::results::{self, RunRecord, RunsFile, Status};
use super::run::{RunPlan, run_once};
use super::task::TaskSpec;
use super::{EvalError, chart};
use crate::mission::{Mode, ModelAids};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tacos_llm::LlmBackend;
use tacos_shared::scenario::Scenario;
use tokio::sync::Mutex;
use tokio::task::JoinSet;

#[derive(Clone)]
pub struct EvalOptions {
    pub task: TaskSpec,
    pub scenario: Scenario,
    pub modes: Vec<Mode>,
    pub drones: Vec<usize>,
    pub runs: u32,
    pub out: PathBuf,
    /// Runs carried out at the same time, each with its own swarm.
    pub jobs: usize,
    pub temperature: f32,
    /// Every run's seed is derived from this, the mode, the swarm size and the run number.
    pub base_seed: u64,
    /// Overrides the task's time limit.
    pub time_limit: Option<Duration>,
    pub cycle_timeout: Duration,
    /// Simulated seconds per wall second while no model call is in flight.
    pub sim_speed: f64,
    pub backend: Arc<dyn LlmBackend>,
    /// The small-model aids of every run.
    pub aids: ModelAids,
    /// Print progress on standard output.
    pub verbose: bool,
}

/// What an evaluation carried out.
#[derive(Debug, Clone)]
pub struct EvalSummary {
    pub ran: usize,
    pub skipped: usize,
    pub errors: usize,
    pub records: Vec<RunRecord>,
    pub cells: Vec<results::Cell>,
}

/// The seed of one run: a SplitMix64 mix of its coordinates, so a resumed run gets the same one.
pub fn run_seed(base: u64, mode: Mode, drones: usize, run: u32) -> u64 {
    let mode_n = match mode {
        Mode::Tacos => 1u64,
        Mode::Wor => 2,
        Mode::Mnl => 3,
    };
    let mut z = base
        ^ mode_n.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (drones as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9)
        ^ u64::from(run).wrapping_mul(0x94D0_49BB_1331_11EB);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    (z ^ (z >> 31)) & ((1 << 53) - 1)
}

/// The order runs are carried out in: run 0 of every cell, then run 1 of every cell, …, so an
/// evaluation stopped half-way still covers every cell evenly.
pub fn schedule(modes: &[Mode], drones: &[usize], runs: u32) -> Vec<(Mode, usize, u32)> {
    let mut out = Vec::new();
    for run in 0..runs {
        for &n in drones {
            for &mode in modes {
                out.push((mode, n, run));
            }
        }
    }
    out
}

fn bar(done: usize, total: usize) -> String {
    let width = 24;
    let filled = (done * width).checked_div(total).unwrap_or(width);
    format!(
        "[{}{}] {done}/{total}",
        "#".repeat(filled),
        "-".repeat(width - filled)
    )
}

/// The successes so far per mode, in `modes`' order: "tacos 3/5, wor 1/4" (runs that errored
/// are not in `records`).
fn successes_by_mode(records: &[RunRecord], modes: &[Mode]) -> String {
    modes
        .iter()
        .map(|m| {
            let of_mode = records.iter().filter(|r| r.mode == m.as_str());
            let (won, all) = of_mode.fold((0, 0), |(won, all), r| {
                (won + usize::from(r.status == Status::Success), all + 1)
            });
            format!("{} {won}/{all}", m.as_str())
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// The time the `remaining` runs should take at the pace of the `ran` runs of this session so
/// far (`elapsed`), `jobs` at a time as they were; `None` before the first run ends.
fn time_left(elapsed: Duration, ran: usize, remaining: usize) -> Option<Duration> {
    (ran > 0).then(|| elapsed.mul_f64(remaining as f64 / ran as f64))
}

/// Writes `results.md`, `results.csv` and `results.svg` from every record so far.
pub fn write_tables(
    opts: &EvalOptions,
    records: &[RunRecord],
) -> Result<Vec<results::Cell>, EvalError> {
    let modes: Vec<String> = opts.modes.iter().map(|m| m.as_str().to_owned()).collect();
    let cells = results::cells(records, &modes);
    let backend = opts.backend.describe();
    let write = |name: &str, text: String| {
        let path = opts.out.join(name);
        std::fs::write(&path, text).map_err(|e| EvalError::Write {
            path: path.display().to_string(),
            reason: e.to_string(),
        })
    };
    write(
        "results.md",
        results::markdown(&opts.task.name, &backend, &cells, records),
    )?;
    write("results.csv", results::csv(&cells))?;
    write(
        "results.svg",
        chart::svg(&format!("{} — {backend}", opts.task.name), &cells, &modes),
    )?;
    Ok(cells)
}

/// Runs the evaluation until every run is done or `interrupt` resolves (runs under way are then
/// stopped and left for the next resume).
pub async fn evaluate(
    opts: EvalOptions,
    interrupt: impl std::future::Future<Output = ()>,
) -> Result<EvalSummary, EvalError> {
    let mut hiding_place = None;
    for &n in &opts.drones {
        hiding_place = opts.task.validate(&opts.scenario, n)?;
    }
    std::fs::create_dir_all(opts.out.join("logs")).map_err(|e| EvalError::Write {
        path: opts.out.display().to_string(),
        reason: e.to_string(),
    })?;
    let runs_path = opts.out.join("runs.jsonl");
    let mut records = results::read_runs(&runs_path)?;
    let backend = opts.backend.describe();
    let done = results::done_runs(
        &runs_path,
        &records,
        &opts.task.name,
        &backend,
        &opts.aids.to_string(),
    )?;
    // Errors are run again; their records are kept in the file but not in the table.
    records.retain(|r| r.status != Status::Error);
    let mut file = RunsFile::open(&runs_path)?;
    let todo: Vec<(Mode, usize, u32)> = schedule(&opts.modes, &opts.drones, opts.runs)
        .into_iter()
        .filter(|(m, n, r)| {
            !done.contains(&results::RunKey {
                mode: m.as_str().to_owned(),
                drones: *n,
                run: *r,
            })
        })
        .collect();
    let total = schedule(&opts.modes, &opts.drones, opts.runs).len();
    let skipped = total - todo.len();
    let say = |text: String| {
        if opts.verbose {
            println!("{text}");
        }
    };
    say(format!(
        "task {} with {backend}: {total} runs, {skipped} already done in {}, {} to go",
        opts.task.name,
        opts.out.display(),
        todo.len()
    ));
    let time_limit = opts
        .time_limit
        .unwrap_or(Duration::from_secs_f64(opts.task.time_limit_s));
    let start_lock = Arc::new(Mutex::new(()));
    let started = Instant::now();
    let mut queue = todo.into_iter();
    let mut running: JoinSet<RunRecord> = JoinSet::new();
    let (mut ran, mut errors, mut finished) = (0usize, 0usize, skipped);
    let spawn_next = |running: &mut JoinSet<RunRecord>, queue: &mut std::vec::IntoIter<_>| {
        let Some((mode, drones, run)) = queue.next() else {
            return false;
        };
        let plan = RunPlan {
            task: opts.task.clone(),
            scenario: opts.scenario.clone(),
            hiding_place: hiding_place.clone(),
            mode,
            drones,
            run,
            seed: run_seed(opts.base_seed, mode, drones, run),
            temperature: opts.temperature,
            time_limit,
            backend: opts.backend.clone(),
            aids: opts.aids,
            log_path: opts.out.join("logs").join(format!(
                "{}-{}-n{drones}-r{run}.jsonl",
                opts.task.name,
                mode.as_str()
            )),
            cycle_timeout: opts.cycle_timeout,
            sim_speed: opts.sim_speed,
        };
        if opts.verbose {
            println!(
                "  start {} n={drones} run {run} (seed {})",
                mode.as_str(),
                plan.seed
            );
        }
        running.spawn(run_once(plan, start_lock.clone()));
        true
    };
    for _ in 0..opts.jobs.max(1) {
        if !spawn_next(&mut running, &mut queue) {
            break;
        }
    }
    tokio::pin!(interrupt);
    loop {
        let joined = tokio::select! {
            j = running.join_next() => j,
            _ = &mut interrupt => {
                running.abort_all();
                say("interrupted: runs under way are dropped and will be run again on resume".into());
                break;
            }
        };
        let Some(joined) = joined else { break };
        let record = joined.map_err(|e| EvalError::Run(e.to_string()))?;
        file.append(&record)?;
        ran += 1;
        finished += 1;
        if record.status == Status::Error {
            errors += 1;
        } else {
            records.push(record.clone());
        }
        let left = time_left(started.elapsed(), ran, total - finished)
            .map_or_else(|| "?".into(), |d| format!("{:.0} s", d.as_secs_f64()));
        say(format!(
            "{} {} n={} run {}: {:?} in {:.0} s ({:.0} s of mission), L={}, {} model calls — {}  ({:.0} s so far, about {left} left; successes {})",
            bar(finished, total),
            record.mode,
            record.drones,
            record.run,
            record.status,
            record.elapsed_s,
            record.mission_s.unwrap_or(0.0),
            record.cycles,
            record.model_calls,
            record.reason,
            started.elapsed().as_secs_f64(),
            successes_by_mode(&records, &opts.modes),
        ));
        write_tables(&opts, &records)?;
        spawn_next(&mut running, &mut queue);
    }
    let cells = write_tables(&opts, &records)?;
    Ok(EvalSummary {
        ran,
        skipped,
        errors,
        records,
        cells,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn progress_says_the_successes_per_mode_and_the_time_left() {
        use crate::eval::results::tests::record;
        let records = [
            record("tacos", 6, 0, Status::Success, 3),
            record("mnl", 6, 0, Status::Failure, 9),
            record("tacos", 6, 1, Status::Failure, 4),
            record("tacos", 6, 2, Status::Success, 2),
        ];
        assert_eq!(
            successes_by_mode(&records, &[Mode::Tacos, Mode::Wor, Mode::Mnl]),
            "tacos 2/3, wor 0/0, mnl 0/1"
        );
        assert_eq!(time_left(Duration::from_secs(100), 0, 8), None);
        assert_eq!(
            time_left(Duration::from_secs(100), 4, 6),
            Some(Duration::from_secs(150))
        );
    }

    #[test]
    fn seeds_are_stable_and_distinct() {
        let a = run_seed(1, Mode::Tacos, 6, 0);
        assert_eq!(a, run_seed(1, Mode::Tacos, 6, 0));
        let all: std::collections::HashSet<u64> =
            schedule(&[Mode::Tacos, Mode::Wor, Mode::Mnl], &[6, 12, 20], 50)
                .into_iter()
                .map(|(m, n, r)| run_seed(1, m, n, r))
                .collect();
        assert_eq!(all.len(), 450);
        assert_ne!(a, run_seed(2, Mode::Tacos, 6, 0));
    }

    #[test]
    fn the_schedule_covers_every_cell_run_by_run() {
        let s = schedule(&[Mode::Tacos, Mode::Mnl], &[6, 12], 2);
        assert_eq!(s.len(), 8);
        assert_eq!(
            &s[..4],
            &[
                (Mode::Tacos, 6, 0),
                (Mode::Mnl, 6, 0),
                (Mode::Tacos, 12, 0),
                (Mode::Mnl, 12, 0)
            ]
        );
        assert!(s[4..].iter().all(|(_, _, r)| *r == 1));
    }
}

//! `tacos-ground eval`: the paper's ablation on simulated swarms.

use super::LlmArgs;
use crate::eval::{EvalOptions, TaskSpec, evaluate};
use crate::mission::{MissionConfig, Mode, ModelAids};
use anyhow::bail;
use std::path::PathBuf;
use std::time::Duration;

/// Run the paper's ablation: every mode × swarm size × run of a task, on simulated swarms.
///
/// Each finished run is appended to OUT/runs.jsonl at once; running again with the same
/// OUT resumes. Writes OUT/results.md, OUT/results.csv and OUT/results.svg.
#[derive(Debug, Clone, clap::Args)]
pub struct EvalArgs {
    /// A built-in task (take-off, find-suspect) or a task file.
    #[arg(long, default_value = "find-suspect")]
    pub task: String,
    /// Comma-separated modes.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "tacos,wor,mnl"
    )]
    pub modes: Vec<Mode>,
    /// Comma-separated swarm sizes (default: the task's).
    #[arg(long, value_delimiter = ',')]
    pub drones: Vec<usize>,
    /// Runs per mode and swarm size.
    #[arg(long, default_value_t = 50)]
    pub runs: u32,
    /// Output directory (resumed when it holds runs of the same task and model).
    #[arg(long)]
    pub out: PathBuf,
    /// Runs carried out at once, each on its own swarm (ids and ports).
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Sampling temperature of every model request.
    #[arg(long, default_value_t = 0.7)]
    pub temperature: f32,
    /// Every run's seed is derived from this and the run's mode, size and number.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Seconds per run, overriding the task file's time limit.
    #[arg(long)]
    pub time_limit: Option<f64>,
    /// Simulated seconds per wall second while no model call is in flight; a call in flight
    /// always runs at real time, so the models see what a real flight would show them.
    #[arg(long, default_value_t = 2.0, value_parser = super::sim_speed)]
    pub sim_speed: f64,
    #[command(flatten)]
    pub llm: LlmArgs,
    /// The small-model aids of every run: `small` (all on), `none`, or aids by name
    /// (see `tacos-ground demo --help`). Runs with other aids are refused in the same OUT.
    #[arg(long, default_value = "small")]
    pub aids: ModelAids,
}

impl EvalArgs {
    pub async fn run(self) -> anyhow::Result<()> {
        let task = TaskSpec::load(&self.task)?;
        let time_limit = match self.time_limit {
            Some(s) if s.is_finite() && s > 0.0 => Some(Duration::from_secs_f64(s)),
            Some(s) => bail!("--time-limit must be a positive number of seconds, got {s}"),
            None => None,
        };
        let opts = EvalOptions {
            scenario: tacos_bus::load_scenario(&task.scenario)?,
            drones: if self.drones.is_empty() {
                task.drones.clone()
            } else {
                self.drones
            },
            task,
            modes: self.modes,
            runs: self.runs,
            out: self.out,
            jobs: self.jobs,
            temperature: self.temperature,
            base_seed: self.seed,
            time_limit,
            cycle_timeout: MissionConfig::default().cycle_timeout,
            sim_speed: self.sim_speed,
            backend: self.llm.backend()?,
            aids: self.aids,
            verbose: true,
        };
        let summary = evaluate(opts.clone(), super::ctrl_c()).await?;
        println!(
            "{} runs carried out ({} errors, run again on resume), {} already done; table in {}",
            summary.ran,
            summary.errors,
            summary.skipped,
            opts.out.join("results.md").display()
        );
        Ok(())
    }
}

//! `tacos-ground demo`: a simulated swarm started on this machine and flown by the fixed
//! pattern, the pilot's terminal, `--say` lines or a script.

use super::LlmArgs;
use crate::demo::{DemoOptions, DemoPlan, run_demo};
use crate::launch::AutopilotArgs;
use crate::mission::log::{Tally, last_mission, read};
use crate::mission::{MissionConfig, Mode, ModelAids};
use crate::pilot::SessionOptions;
use crate::script::{Script, ScriptOptions};
use anyhow::Context;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tacos_shared::scenario::Scenario;

/// What `--no-llm` flies.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Pattern {
    /// Take off, fly to points, land.
    Fixed,
    /// Take off, circle the business district, swap to the antipodal points through the
    /// skyscrapers, land; fails on any separation or obstacle breach.
    Swap,
}

/// Start a simulated swarm on this machine and fly it.
#[derive(Debug, Clone, clap::Args)]
pub struct DemoArgs {
    /// Number of drones (up to the map's slots: 20 in the city, 3 in the lab); default 6,
    /// or every slot of a smaller map.
    #[arg(long)]
    pub drones: Option<usize>,
    /// Built-in map (city, lab) or a scenario file.
    #[arg(long = "map", alias = "scenario", default_value = "city")]
    pub map: String,
    /// Fly the fixed pattern without any language model.
    #[arg(long)]
    pub no_llm: bool,
    /// The pattern flown with --no-llm.
    #[arg(long, value_enum, default_value_t = Pattern::Fixed)]
    pub pattern: Pattern,
    /// No interactive pilot input: carry out the --say lines and exit.
    #[arg(long)]
    pub no_terminal: bool,
    /// A pilot line, carried out before anything else (repeatable, in order).
    #[arg(long)]
    pub say: Vec<String>,
    /// Run a pilot script headless (see the README for its format); exits non-zero
    /// naming the first step that fails.
    #[arg(long, conflicts_with_all = ["say", "no_llm"])]
    pub script: Option<PathBuf>,
    /// tacos (full), wor (Supervisor without the Coordinator's reasoning), mnl (one model).
    #[arg(long, value_enum, default_value_t = Mode::Tacos)]
    pub mode: Mode,
    #[command(flatten)]
    pub llm: LlmArgs,
    /// The small-model aids: `small` (all on: what the 135M embedded model needs, and the
    /// default), `none` (the engine's principled rules only), or a comma-separated list of
    /// aids to turn on, `-name` turning one off after a preset (`small,-implied-takeoffs`).
    /// Aids: place-scope, follow-words, repair-grammar, implied-takeoffs, plan-length-cap,
    /// compact-repair-echo, keep-partial-plan, plan-only, whole-swarm, replan-keeps-pending.
    /// The mission log records
    /// which were on and
    /// each time one fired.
    #[arg(long, default_value = "small")]
    pub aids: ModelAids,
    /// Hold every Coordinator plan for the pilot: it is shown call by call with what the
    /// checks say, and flies once the pilot answers `approve` (or `drop <task>`, or
    /// `reject <why>`, which goes back to the Coordinator). Direct commands never wait.
    /// `confirm on` / `confirm off` switch it during a mission. Not with `--mode mnl`, which
    /// has no plan to hold.
    #[arg(long, conflicts_with = "no_llm")]
    pub confirm: bool,
    /// Write every step of the mission's core to the log, with what it was fed and the
    /// swarm it saw (a few kB per step), so `tacos-ground replay --check LOG` can feed the
    /// mission to a fresh core and compare what it sends with what was sent.
    #[arg(long)]
    pub trace_steps: bool,
    /// The mission log (JSON lines); default: missions-out/<time>-<mode>.jsonl
    #[arg(long)]
    pub log: Option<PathBuf>,
    /// Simulated seconds per wall second while no model call is in flight (a call in
    /// flight always runs at real time). Above 1 needs spare CPU: the planners run that
    /// much more often.
    #[arg(long, default_value_t = 1.0, value_parser = super::sim_speed)]
    pub sim_speed: f64,
    #[command(flatten)]
    pub autopilot: AutopilotArgs,
}

impl DemoArgs {
    pub async fn run(self) -> anyhow::Result<()> {
        let scenario = tacos_bus::load_scenario(&self.map)?;
        let drones = self.drones.unwrap_or(6.min(scenario.drones.len()));
        // A script is read and checked against the map before anything starts.
        let script = match &self.script {
            Some(path) => {
                let ids: Vec<String> = scenario
                    .drones
                    .iter()
                    .take(drones)
                    .map(|d| d.id.to_string())
                    .collect();
                Some(read_script(path, &scenario, &ids)?)
            }
            None => None,
        };
        let opts = DemoOptions {
            scenario_arg: self.map.clone(),
            scenario,
            drones,
            sim_speed: self.sim_speed,
            autopilot: self.autopilot.kind()?,
            verbose: true,
        };
        if self.no_llm {
            let (plan, what) = match self.pattern {
                Pattern::Fixed => (
                    DemoPlan::Fixed,
                    "all drones took off, reached their points and landed",
                ),
                Pattern::Swap => (
                    DemoPlan::Swap,
                    "all drones swapped to their antipodal points through the skyscrapers and landed, with no breach",
                ),
            };
            run_demo(opts, plan, super::ctrl_c()).await?;
            println!("demo finished: {what}");
            return Ok(());
        }
        let backend = self.llm.backend()?;
        let log_path = self.log.clone().unwrap_or_else(|| default_log(self.mode));
        println!(
            "model: {}; mission log: {}",
            backend.describe(),
            log_path.display()
        );
        if self.confirm && self.mode == Mode::Mnl {
            anyhow::bail!("--confirm holds Coordinator plans, and --mode mnl has none");
        }
        let mission = MissionConfig {
            mode: self.mode,
            aids: self.aids,
            confirm: self.confirm,
            trace_steps: self.trace_steps,
            ..MissionConfig::default()
        };
        let plan = match script {
            Some(script) => DemoPlan::Script {
                backend,
                script,
                options: ScriptOptions {
                    mission,
                    log_path: log_path.clone(),
                    verbose: true,
                    // Set by the demo when the drones fly on PX4 SITL.
                    vehicle_deaths: None,
                },
            },
            None => DemoPlan::Llm {
                backend,
                session: SessionOptions {
                    mission,
                    say: self.say,
                    interactive: !self.no_terminal,
                    log_path: log_path.clone(),
                    line_timeout: Duration::from_secs(600),
                    verbose: true,
                },
            },
        };
        // The summary comes from the log, so a run that failed gets one too.
        let result = run_demo(opts, plan, super::ctrl_c()).await;
        print_summary(&log_path);
        result?;
        Ok(())
    }
}

/// Reads a pilot script and checks it against the map and the swarm's `drones`.
pub(super) fn read_script(
    path: &Path,
    scenario: &Scenario,
    drones: &[String],
) -> anyhow::Result<Script> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    crate::script::parse(&text)
        .and_then(|s| s.check(scenario, drones).map(|()| s))
        .with_context(|| format!("script {}", path.display()))
}

/// `missions-out/<unix seconds>-<mode>.jsonl`.
pub(super) fn default_log(mode: Mode) -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    PathBuf::from("missions-out").join(format!("{secs}-{}.jsonl", mode.as_str()))
}

/// The run's summary, counted from its mission log: what happened, however the run ended.
pub(super) fn print_summary(log: &Path) {
    match read(log) {
        Ok(lines) => println!(
            "demo finished: {}; mission log {}",
            Tally::of(last_mission(&lines)),
            log.display()
        ),
        Err(e) => println!("demo finished; its mission log could not be read: {e}"),
    }
}

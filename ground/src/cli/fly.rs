//! `tacos-ground fly`: the ground station of a swarm that is already up (real drones, or a
//! swarm started by other hosts), flown with the language-model layers: the pilot's terminal,
//! `--say` lines or a script. `--resume LOG` goes on with the mission a ground station that
//! stopped (a crash, a restart) left in its log.

use super::LlmArgs;
use super::demo::{default_log, print_summary, read_script};
use crate::link::GroundLink;
use crate::mission::log::read;
use crate::mission::resume::{Resumable, rebuild};
use crate::mission::{MissionConfig, Mode, ModelAids, ResumeFrom};
use crate::pilot::{SessionOptions, run_session};
use crate::safety::SafetyGate;
use crate::script::{ScriptOptions, run_script};
use anyhow::Context;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tacos_bus::BusArgs;
use tacos_shared::DroneId;
use tacos_shared::scenario::Scenario;

/// Fly a swarm that is already up with the language-model layers.
#[derive(Debug, Clone, clap::Args)]
pub struct FlyArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Built-in map (city, lab) or a scenario file: the one the drones were started with.
    #[arg(long = "map", alias = "scenario", default_value = "city")]
    pub map: String,
    /// The drones to fly (comma-separated); default: every drone of the map, or of the
    /// resumed mission, that is heard within --wait-for-drones.
    #[arg(long, value_delimiter = ',')]
    pub drones: Vec<String>,
    /// Seconds to wait for the drones to be heard before the mission starts.
    #[arg(long, default_value_t = 10.0)]
    pub wait_for_drones: f64,
    /// tacos (full), wor (Supervisor without the Coordinator's reasoning), mnl (one model).
    /// A resumed mission keeps the mode it ran with.
    #[arg(long, value_enum, default_value_t = Mode::Tacos)]
    pub mode: Mode,
    #[command(flatten)]
    pub llm: LlmArgs,
    /// The small-model aids (see `demo --help`).
    #[arg(long, default_value = "small")]
    pub aids: ModelAids,
    /// Hold every Coordinator plan for the pilot's approval (see `demo --help`).
    #[arg(long)]
    pub confirm: bool,
    /// Write every step of the mission's core to the log, with what it was fed and the
    /// swarm it saw (a few kB per step), so `tacos-ground replay --check LOG` can feed the
    /// mission to a fresh core and compare what it sends with what was sent.
    #[arg(long)]
    pub trace_steps: bool,
    /// No interactive pilot input: carry out the --say lines (and a resumed plan) and exit.
    #[arg(long)]
    pub no_terminal: bool,
    /// A pilot line, carried out before anything else (repeatable, in order).
    #[arg(long)]
    pub say: Vec<String>,
    /// Run a pilot script headless; exits non-zero naming the first step that fails.
    #[arg(long, conflicts_with = "say")]
    pub script: Option<PathBuf>,
    /// The mission log (JSON lines); default: the resumed log, else
    /// missions-out/<time>-<mode>.jsonl
    #[arg(long)]
    pub log: Option<PathBuf>,
    /// Go on with the mission in this log (the Coordinator's history, the world events and the
    /// plan in force with each task's state): after the ground station stopped mid-mission.
    /// The drones follow the new ground station once the old one has been silent for their
    /// hold time (3 s); they hold after that time and land after 30 s without any.
    #[arg(long, value_name = "LOG")]
    pub resume: Option<PathBuf>,
}

impl FlyArgs {
    pub async fn run(self) -> anyhow::Result<()> {
        let scenario = tacos_bus::load_scenario(&self.map)?;
        let resumed = match &self.resume {
            Some(path) => Some((path.clone(), resumable(path, &scenario)?)),
            None => None,
        };
        let mode = match &resumed {
            Some((_, r)) => r
                .mode
                .parse::<Mode>()
                .map_err(|e| anyhow::anyhow!("the resumed log's mode: {e}"))?,
            None => self.mode,
        };
        if self.confirm && mode == Mode::Mnl {
            anyhow::bail!("--confirm holds Coordinator plans, and --mode mnl has none");
        }
        let wanted = self.wanted_drones(&scenario, resumed.as_ref().map(|(_, r)| r))?;
        let backend = self.llm.backend()?;
        let log_path = self
            .log
            .clone()
            .or_else(|| resumed.as_ref().map(|(path, _)| path.clone()))
            .unwrap_or_else(|| default_log(mode));
        let link = Arc::new(GroundLink::connect(&self.bus).await?);
        let heard = heard_drones(&link, &wanted, &self.bus, self.wait_for_drones).await?;
        println!(
            "swarm {}: flying {}; model: {}; mission log: {}",
            self.bus.swarm,
            heard.join(", "),
            backend.describe(),
            log_path.display()
        );
        let script = match &self.script {
            Some(path) => Some(read_script(path, &scenario, &heard)?),
            None => None,
        };
        let mission = MissionConfig {
            mode,
            aids: self.aids,
            confirm: self.confirm,
            trace_steps: self.trace_steps,
            resume: resumed.map(|(path, r)| ResumeFrom {
                path,
                memory: r.memory,
            }),
            ..MissionConfig::default()
        };
        let gate = SafetyGate::new(scenario);
        let result = match script {
            Some(script) => {
                let options = ScriptOptions {
                    mission,
                    log_path: log_path.clone(),
                    verbose: true,
                    vehicle_deaths: None,
                };
                tokio::select! {
                    r = run_script(link, gate, backend, &script, options) => r.map(|_| ()).map_err(anyhow::Error::from),
                    _ = super::ctrl_c() => Err(anyhow::anyhow!("interrupted")),
                }
            }
            None => {
                let session = SessionOptions {
                    mission,
                    say: self.say.clone(),
                    interactive: !self.no_terminal,
                    log_path: log_path.clone(),
                    line_timeout: Duration::from_secs(600),
                    verbose: true,
                };
                tokio::select! {
                    r = run_session(link, gate, backend, session) => r.map(|_| ()).map_err(anyhow::Error::from),
                    _ = super::ctrl_c() => Err(anyhow::anyhow!("interrupted")),
                }
            }
        };
        print_summary(&log_path);
        result
    }

    /// The drones to wait for: `--drones`, else the resumed mission's, else the map's.
    fn wanted_drones(
        &self,
        scenario: &Scenario,
        resumed: Option<&Resumable>,
    ) -> anyhow::Result<Vec<DroneId>> {
        let names: Vec<String> = if !self.drones.is_empty() {
            self.drones.clone()
        } else if let Some(r) = resumed.filter(|r| !r.drones.is_empty()) {
            r.drones.clone()
        } else {
            scenario.drones.iter().map(|d| d.id.to_string()).collect()
        };
        names
            .iter()
            .map(|name| {
                let id = DroneId::new(name).map_err(|e| anyhow::anyhow!("{name:?}: {e}"))?;
                match scenario.drone(&id) {
                    Some(_) => Ok(id),
                    None => anyhow::bail!("{name} is not a drone of the map {}", scenario.name),
                }
            })
            .collect()
    }
}

/// The mission in the log at `path`, checked against the map flown now.
fn resumable(path: &std::path::Path, scenario: &Scenario) -> anyhow::Result<Resumable> {
    let lines = read(path)?;
    let resumable = rebuild(&lines).with_context(|| format!("resuming {}", path.display()))?;
    if resumable.scenario != scenario.name {
        anyhow::bail!(
            "resuming {}: its mission flew the map {}, not {} (give it with --map)",
            path.display(),
            resumable.scenario,
            scenario.name
        );
    }
    if let Some(how) = &resumable.ended {
        println!(
            "{}: its mission had ended ({how}); going on with its history",
            path.display()
        );
    }
    Ok(resumable)
}

/// Waits up to `wait_s` for every drone of `wanted` to be heard with its autopilot linked, and
/// returns those heard: at least one, or an error that says where the ground listened.
async fn heard_drones(
    link: &GroundLink,
    wanted: &[DroneId],
    bus: &BusArgs,
    wait_s: f64,
) -> anyhow::Result<Vec<String>> {
    let wait = Duration::from_secs_f64(wait_s.max(0.0));
    let linked = |s: &tacos_shared::messages::DroneStatus| s.autopilot_link;
    let all = link.wait_for_drones(wanted, wait, linked).await;
    // Those the wait would count (alive, and `linked`).
    let heard: Vec<String> = {
        let view = link.view();
        wanted
            .iter()
            .filter(|id| {
                view.get(id)
                    .is_some_and(|e| e.alive && e.status.as_ref().is_some_and(linked))
            })
            .map(|id| id.to_string())
            .collect()
    };
    if heard.is_empty() {
        anyhow::bail!(
            "no drone of swarm {} heard within {wait:?} (check --swarm and the network: --zenoh-config or --zenoh-connect)",
            bus.swarm
        );
    }
    if let Err(e) = all {
        println!("going on without the drones not heard: {e}");
    }
    Ok(heard)
}

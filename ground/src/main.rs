//! `tacos-ground`: the ground station binary.

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tacos_bus::BusArgs;
use tacos_embedded::{EmbeddedBackend, EmbeddedOptions};
use tacos_ground::demo::{DemoOptions, DemoPlan, run_demo};
use tacos_ground::link::{GroundLink, GroundRole};
use tacos_ground::mission::{MissionConfig, Mode};
use tacos_ground::pilot::SessionOptions;
use tacos_ground::safety::SafetyGate;
use tacos_ground::script::ScriptOptions;
use tacos_ground::send::SendWaits;
use tacos_llm::{LlmBackend, OpenAiBackend, OpenAiConfig};
use tacos_shared::action::Action;

#[derive(Debug, Parser)]
#[command(version, about = "TACOS ground station: fly a PX4 swarm")]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Live table of the swarm: mode, position, speed, current action, link age.
    Swarm {
        #[command(flatten)]
        bus: BusArgs,
        /// Refresh period in milliseconds.
        #[arg(long, default_value_t = 500)]
        period_ms: u64,
        /// Print this many tables then exit (0 = until Ctrl-C).
        #[arg(long, default_value_t = 0)]
        count: u64,
        /// Act as the ground station in control: beat the heartbeat that keeps the drones out
        /// of their ground-silence failsafe. A drone follows one ground station at a time, so
        /// while this beats a `send` from another process is refused (it says so). Without it
        /// the table only watches, and drones with no ground in control hold after 3 s and
        /// land after 30 s.
        #[arg(long)]
        in_control: bool,
    },
    /// Send one action to one drone and wait for its outcome.
    ///
    /// Actions: arm_takeoff | goto X Y Z | start_tracking TARGET | stop_tracking | land | hold
    Send {
        #[command(flatten)]
        bus: BusArgs,
        /// Built-in scenario (city, lab) or scenario file: what the safety gate checks against.
        #[arg(long, default_value = "city")]
        scenario: String,
        /// Seconds to wait for the outcome.
        #[arg(long, default_value_t = 120.0)]
        timeout: f64,
        /// Seconds to wait for the drone to be heard before giving up on it: a drone rejoining
        /// a ground that has just (re)started takes a few seconds to reconnect.
        #[arg(long, default_value_t = 20.0)]
        wait_for_drone: f64,
        drone: String,
        #[arg(num_args = 1.., allow_hyphen_values = true)]
        action: Vec<String>,
    },
    /// Start a simulated swarm on this machine and fly it.
    Demo {
        /// Number of drones (up to the map's slots: 20 in the city, 3 in the lab); default 6,
        /// or every slot of a smaller map.
        #[arg(long)]
        drones: Option<usize>,
        /// Built-in map (city, lab) or a scenario file.
        #[arg(long = "map", alias = "scenario", default_value = "city")]
        map: String,
        /// Fly the fixed pattern without any language model.
        #[arg(long)]
        no_llm: bool,
        /// The pattern flown with --no-llm: `fixed` (take off, fly to points, land) or `swap`
        /// (take off, circle the business district, swap to the antipodal points through the
        /// skyscrapers, land; fails on any separation or obstacle breach).
        #[arg(long, default_value = "fixed")]
        pattern: String,
        /// No interactive pilot input: carry out the --say lines and exit.
        #[arg(long)]
        no_terminal: bool,
        /// A pilot line, carried out before anything else (repeatable, in order).
        #[arg(long)]
        say: Vec<String>,
        /// Run a pilot script headless (see the README for its format); exits non-zero
        /// naming the first step that fails.
        #[arg(long, conflicts_with_all = ["say", "no_llm"])]
        script: Option<PathBuf>,
        /// tacos (full), wor (Supervisor without the Coordinator's reasoning), mnl (one model).
        #[arg(long, default_value = "tacos")]
        mode: Mode,
        #[command(flatten)]
        llm: LlmArgs,
        /// The mission log (JSON lines); default: missions-out/<time>-<mode>.jsonl
        #[arg(long)]
        log: Option<PathBuf>,
        /// Simulated seconds per wall second while no model call is in flight (a call in
        /// flight always runs at real time). Above 1 needs spare CPU: the planners run that
        /// much more often.
        #[arg(long, default_value_t = 1.0, value_parser = sim_speed)]
        sim_speed: f64,
        #[command(flatten)]
        autopilot: tacos_ground::launch::AutopilotArgs,
    },
    /// Run the paper's ablation: every mode × swarm size × run of a task, on simulated swarms.
    ///
    /// Each finished run is appended to OUT/runs.jsonl at once; running again with the same
    /// OUT resumes. Writes OUT/results.md, OUT/results.csv and OUT/results.svg.
    Eval {
        /// A built-in task (take-off, find-suspect) or a task file.
        #[arg(long, default_value = "find-suspect")]
        task: String,
        /// Comma-separated modes.
        #[arg(long, value_delimiter = ',', default_value = "tacos,wor,mnl")]
        modes: Vec<Mode>,
        /// Comma-separated swarm sizes (default: the task's).
        #[arg(long, value_delimiter = ',')]
        drones: Vec<usize>,
        /// Runs per mode and swarm size.
        #[arg(long, default_value_t = 50)]
        runs: u32,
        /// Output directory (resumed when it holds runs of the same task and model).
        #[arg(long)]
        out: PathBuf,
        /// Runs carried out at once, each on its own swarm (ids and ports).
        #[arg(long, default_value_t = 1)]
        jobs: usize,
        /// Sampling temperature of every model request.
        #[arg(long, default_value_t = 0.7)]
        temperature: f32,
        /// Every run's seed is derived from this and the run's mode, size and number.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Seconds per run, overriding the task file's time limit.
        #[arg(long)]
        time_limit: Option<f64>,
        /// Simulated seconds per wall second while no model call is in flight; a call in flight
        /// always runs at real time, so the models see what a real flight would show them.
        #[arg(long, default_value_t = 2.0, value_parser = sim_speed)]
        sim_speed: f64,
        #[command(flatten)]
        llm: LlmArgs,
    },
    /// Print a mission log's timeline.
    Replay { log: PathBuf },
    /// Draw a mission's trajectories over the map, coloured by speed (SVG).
    Plot {
        log: PathBuf,
        /// Output file: .svg, or .png (the same picture rasterised at twice its size).
        #[arg(short, long, default_value = "mission.svg")]
        output: PathBuf,
        /// The map, when not the one the log names (city, lab or a scenario file).
        #[arg(long)]
        map: Option<String>,
    },
}

/// Which language model to use: a server, or the embedded model by default.
#[derive(Debug, Clone, clap::Args)]
struct LlmArgs {
    /// Base URL of an OpenAI-compatible server (Ollama, vLLM, llama.cpp server, a cloud API),
    /// e.g. http://127.0.0.1:11434/v1. Without it the embedded offline model is used.
    #[arg(long, env = "TACOS_LLM_URL")]
    llm_url: Option<String>,
    /// The model name on that server.
    #[arg(long, env = "TACOS_LLM_MODEL")]
    model: Option<String>,
    /// Seconds to wait for one model reply.
    #[arg(long, default_value_t = 120.0)]
    llm_timeout: f64,
}

impl LlmArgs {
    fn backend(&self) -> anyhow::Result<Arc<dyn LlmBackend>> {
        match &self.llm_url {
            Some(url) => {
                let model = self
                    .model
                    .clone()
                    .context("--llm-url needs --model (or TACOS_LLM_MODEL)")?;
                let mut config = OpenAiConfig::new(url.clone(), model)
                    .with_timeout(Duration::from_secs_f64(self.llm_timeout));
                if let Some(key) = std::env::var("TACOS_LLM_API_KEY")
                    .ok()
                    .or_else(|| std::env::var("OPENAI_API_KEY").ok())
                    .filter(|k| !k.is_empty())
                {
                    config = config.with_api_key(key);
                }
                Ok(Arc::new(OpenAiBackend::new(config)?))
            }
            // The embedded model: fetched on first use (pip), loaded on the first call.
            None => Ok(Arc::new(EmbeddedBackend::lazy(EmbeddedOptions::from_env()))),
        }
    }
}

fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // The whole chain of causes on one line, without a backtrace.
            eprintln!("{}: {e:#}", env!("CARGO_BIN_NAME"));
            std::process::ExitCode::FAILURE
        }
    }
}

fn run() -> anyhow::Result<()> {
    // candle's quantized kernels spin a thread pool per matrix product; on a small companion or
    // a loaded 2-core machine one thread is several times faster. Set before any thread starts.
    if std::env::var_os("CANDLE_NUM_THREADS").is_none() {
        // SAFETY: nothing else runs yet: no threads have been started in this process.
        unsafe { std::env::set_var("CANDLE_NUM_THREADS", "1") };
    }
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(async move {
        match cli.command {
            Cmd::Swarm {
                bus,
                period_ms,
                count,
                in_control,
            } => swarm(bus, period_ms, count, in_control).await,
            Cmd::Send {
                bus,
                scenario,
                timeout,
                wait_for_drone,
                drone,
                action,
            } => {
                let waits = SendWaits {
                    drone: Duration::from_secs_f64(wait_for_drone.max(0.0)),
                    outcome: Duration::from_secs_f64(timeout.max(0.0)),
                };
                send(bus, &scenario, waits, &drone, &action).await
            }
            Cmd::Demo {
                drones,
                map,
                no_llm,
                pattern,
                no_terminal,
                say,
                script,
                mode,
                llm,
                log,
                sim_speed,
                autopilot,
            } => {
                demo(DemoArgs {
                    autopilot,
                    drones,
                    map,
                    no_llm,
                    pattern,
                    no_terminal,
                    say,
                    script,
                    mode,
                    llm,
                    log,
                    sim_speed,
                })
                .await
            }
            Cmd::Plot { log, output, map } => plot(&log, &output, map.as_deref()),
            Cmd::Eval {
                task,
                modes,
                drones,
                runs,
                out,
                jobs,
                temperature,
                seed,
                time_limit,
                sim_speed,
                llm,
            } => {
                let task = tacos_ground::eval::TaskSpec::load(&task)?;
                let time_limit = match time_limit {
                    Some(s) if s.is_finite() && s > 0.0 => Some(Duration::from_secs_f64(s)),
                    Some(s) => bail!("--time-limit must be a positive number of seconds, got {s}"),
                    None => None,
                };
                let opts = tacos_ground::eval::EvalOptions {
                    scenario: tacos_bus::load_scenario(&task.scenario)?,
                    drones: if drones.is_empty() { task.drones.clone() } else { drones },
                    task,
                    modes,
                    runs,
                    out,
                    jobs,
                    temperature,
                    base_seed: seed,
                    time_limit,
                    cycle_timeout: MissionConfig::default().cycle_timeout,
                    sim_speed,
                    backend: llm.backend()?,
                    verbose: true,
                };
                let interrupt = async {
                    let _ = tokio::signal::ctrl_c().await;
                };
                let summary = tacos_ground::eval::evaluate(opts.clone(), interrupt).await?;
                println!(
                    "{} runs carried out ({} errors, run again on resume), {} already done; table in {}",
                    summary.ran,
                    summary.errors,
                    summary.skipped,
                    opts.out.join("results.md").display()
                );
                Ok(())
            }
            Cmd::Replay { log } => {
                let lines = tacos_ground::mission::log::read(&log)?;
                let mission = tacos_ground::mission::log::last_mission(&lines);
                print!("{}", tacos_ground::mission::log::timeline(mission));
                Ok(())
            }
        }
    })
}

async fn swarm(bus: BusArgs, period_ms: u64, count: u64, in_control: bool) -> anyhow::Result<()> {
    let role = if in_control {
        GroundRole::InControl
    } else {
        GroundRole::Monitor
    };
    let link = GroundLink::connect_as(&bus, role).await?;
    let mut tick = tokio::time::interval(Duration::from_millis(period_ms.max(50)));
    let mut printed = 0;
    let interactive = count == 0;
    loop {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => return Ok(()),
            _ = tick.tick() => {}
        }
        let text = tacos_ground::table::render(&link.view(), link.clock().instant());
        if interactive {
            // Clear the screen and home the cursor, like `watch`.
            print!("\x1b[2J\x1b[H");
        }
        println!("swarm {}\n{text}", bus.swarm);
        printed += 1;
        if count > 0 && printed >= count {
            return Ok(());
        }
    }
}

async fn send(
    bus: BusArgs,
    scenario: &str,
    waits: SendWaits,
    drone: &str,
    words: &[String],
) -> anyhow::Result<()> {
    let words: Vec<&str> = words.iter().map(String::as_str).collect();
    let action = Action::parse_words(&words).map_err(anyhow::Error::msg)?;
    let id = tacos_shared::DroneId::new(drone).map_err(|e| anyhow::anyhow!("{drone:?}: {e}"))?;
    let gate = SafetyGate::new(tacos_bus::load_scenario(scenario)?);
    let link = GroundLink::connect(&bus).await?;
    // Progress on stdout, waits on stderr, as before: scripts read the outcome from stdout.
    let say = |line: String| {
        if line.starts_with("waiting") {
            eprintln!("{line}");
        } else {
            println!("{line}");
        }
    };
    tacos_ground::send::send(&link, &gate, waits, &id, &action, say).await?;
    Ok(())
}

fn plot(log: &std::path::Path, output: &std::path::Path, map: Option<&str>) -> anyhow::Result<()> {
    use tacos_ground::mission::log::{Record, last_mission, read};
    let all = read(log)?;
    let lines = last_mission(&all);
    let named = lines.iter().find_map(|l| match &l.record {
        Record::MissionStart { scenario, .. } => Some(scenario.clone()),
        _ => None,
    });
    let map = map
        .map(str::to_owned)
        .or(named)
        .context("the log names no map: give --map")?;
    let scenario = tacos_bus::load_scenario(&map)?;
    let svg = tacos_ground::plot::svg(lines, &scenario);
    let bytes = match output.extension().and_then(|e| e.to_str()) {
        Some("svg") => svg.into_bytes(),
        Some("png") => tacos_ground::plot::png(&svg, 2.0)?,
        _ => bail!("name the output *.svg or *.png"),
    };
    std::fs::write(output, bytes).with_context(|| format!("writing {}", output.display()))?;
    println!("wrote {}", output.display());
    Ok(())
}

struct DemoArgs {
    autopilot: tacos_ground::launch::AutopilotArgs,
    drones: Option<usize>,
    map: String,
    no_llm: bool,
    pattern: String,
    no_terminal: bool,
    say: Vec<String>,
    script: Option<PathBuf>,
    mode: Mode,
    llm: LlmArgs,
    log: Option<PathBuf>,
    sim_speed: f64,
}

/// `--sim-speed`: a positive number no larger than 20.
fn sim_speed(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && s > 0.0 && s <= 20.0 => Ok(s),
        _ => Err(format!("must be a number in (0, 20], got {text}")),
    }
}

async fn demo(args: DemoArgs) -> anyhow::Result<()> {
    let scenario = tacos_bus::load_scenario(&args.map)?;
    let drones = args.drones.unwrap_or(6.min(scenario.drones.len()));
    // A script is read and checked against the map before anything starts.
    let script = match &args.script {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let script = tacos_ground::script::parse(&text)
                .and_then(|s| {
                    let drones: Vec<String> = scenario
                        .drones
                        .iter()
                        .take(drones)
                        .map(|d| d.id.to_string())
                        .collect();
                    s.check(&scenario, &drones).map(|()| s)
                })
                .with_context(|| format!("script {}", path.display()))?;
            Some(script)
        }
        None => None,
    };
    let opts = DemoOptions {
        scenario_arg: args.map.clone(),
        scenario,
        drones,
        sim_speed: args.sim_speed,
        autopilot: args.autopilot.kind()?,
        verbose: true,
    };
    let interrupt = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    if args.no_llm {
        let (plan, what) = match args.pattern.as_str() {
            "fixed" => (
                DemoPlan::Fixed,
                "all drones took off, reached their points and landed",
            ),
            "swap" => (
                DemoPlan::Swap,
                "all drones swapped to their antipodal points through the skyscrapers and landed, with no breach",
            ),
            other => bail!("unknown pattern {other:?} (available: fixed, swap)"),
        };
        run_demo(opts, plan, interrupt).await?;
        println!("demo finished: {what}");
        return Ok(());
    }
    let backend = args.llm.backend()?;
    let log_path = args.log.clone().unwrap_or_else(|| {
        let secs = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        PathBuf::from("missions-out").join(format!("{secs}-{}.jsonl", args.mode.as_str()))
    });
    println!(
        "model: {}; mission log: {}",
        backend.describe(),
        log_path.display()
    );
    let mission = MissionConfig {
        mode: args.mode,
        ..MissionConfig::default()
    };
    if let Some(script) = script {
        let options = ScriptOptions {
            mission,
            log_path: log_path.clone(),
            verbose: true,
        };
        let plan = DemoPlan::Script {
            backend,
            script,
            options,
        };
        // The summary comes from the log, so a script that failed gets one too.
        let result = run_demo(opts, plan, interrupt).await;
        print_summary(&log_path);
        result?;
        return Ok(());
    }
    let session = SessionOptions {
        mission,
        say: args.say.clone(),
        interactive: !args.no_terminal,
        log_path: log_path.clone(),
        line_timeout: Duration::from_secs(600),
        verbose: true,
    };
    let result = run_demo(opts, DemoPlan::Llm { backend, session }, interrupt).await;
    print_summary(&log_path);
    result?;
    Ok(())
}

/// The run's summary, counted from its mission log: what happened, however the run ended.
fn print_summary(log: &std::path::Path) {
    use tacos_ground::mission::log::{Tally, last_mission, read};
    match read(log) {
        Ok(lines) => println!(
            "demo finished: {}; mission log {}",
            Tally::of(last_mission(&lines)),
            log.display()
        ),
        Err(e) => println!("demo finished; its mission log could not be read: {e}"),
    }
}

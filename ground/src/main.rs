//! `tacos-ground`: the ground station binary.

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};
use std::time::{Duration, Instant};
use tacos_bus::BusArgs;
use tacos_ground::demo::{DemoOptions, run_fixed_pattern};
use tacos_ground::link::GroundLink;
use tacos_ground::safety::SafetyGate;
use tacos_shared::action::Action;
use tacos_shared::messages::ActionState;

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
        drone: String,
        #[arg(num_args = 1.., allow_hyphen_values = true)]
        action: Vec<String>,
    },
    /// Start a simulated swarm on this machine and fly it.
    Demo {
        /// Number of drones.
        #[arg(long, default_value_t = 3)]
        drones: usize,
        /// Built-in map (city, lab) or a scenario file.
        #[arg(long = "map", alias = "scenario", default_value = "city")]
        map: String,
        /// Fly the fixed pattern without any language model.
        #[arg(long)]
        no_llm: bool,
        /// The pattern flown with --no-llm.
        #[arg(long, default_value = "fixed")]
        pattern: String,
    },
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
            } => swarm(bus, period_ms, count).await,
            Cmd::Send {
                bus,
                scenario,
                timeout,
                drone,
                action,
            } => send(bus, &scenario, timeout, &drone, &action).await,
            Cmd::Demo {
                drones,
                map,
                no_llm,
                pattern,
            } => demo(drones, &map, no_llm, &pattern).await,
        }
    })
}

async fn swarm(bus: BusArgs, period_ms: u64, count: u64) -> anyhow::Result<()> {
    let link = GroundLink::connect(&bus).await?;
    let mut tick = tokio::time::interval(Duration::from_millis(period_ms.max(50)));
    let mut printed = 0;
    let interactive = count == 0;
    loop {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => return Ok(()),
            _ = tick.tick() => {}
        }
        let text = tacos_ground::table::render(&link.view(), Instant::now());
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
    timeout: f64,
    drone: &str,
    words: &[String],
) -> anyhow::Result<()> {
    let words: Vec<&str> = words.iter().map(String::as_str).collect();
    let action = Action::parse_words(&words).map_err(anyhow::Error::msg)?;
    let gate = SafetyGate::new(tacos_bus::load_scenario(scenario)?);
    let link = GroundLink::connect(&bus).await?;
    // Give the swarm view a moment to hear from the drone before judging it unknown.
    if let Ok(id) = tacos_shared::DroneId::new(drone) {
        let _ = link
            .wait_for_drones(std::slice::from_ref(&id), Duration::from_secs(3), |_| true)
            .await;
    }
    let checked = {
        let view = link.view();
        gate.check(&view, drone, &action, Instant::now())
    }
    .map_err(|r| anyhow::anyhow!("refused by the safety gate: {r}"))?;
    let seq = link.send(&checked, None).await?;
    println!("sent #{seq} {action} to {drone}");
    match link
        .wait_outcome(checked.drone(), seq, Duration::from_secs_f64(timeout))
        .await?
    {
        ActionState::Done => {
            println!("{drone}: {action} done");
            Ok(())
        }
        ActionState::Failed(why) => bail!("{drone}: {action} failed: {why}"),
        ActionState::Running { .. } => bail!("{drone}: {action} did not finish"),
    }
}

async fn demo(drones: usize, map: &str, no_llm: bool, pattern: &str) -> anyhow::Result<()> {
    if !no_llm {
        bail!("the LLM layers are not part of this build yet: run the fixed pattern with --no-llm");
    }
    if pattern != "fixed" {
        bail!("unknown pattern {pattern:?} (available: fixed)");
    }
    let scenario = tacos_bus::load_scenario(map)?;
    let opts = DemoOptions {
        scenario_arg: map.to_owned(),
        scenario,
        drones,
        verbose: true,
    };
    run_fixed_pattern(opts, async {
        let _ = tokio::signal::ctrl_c().await;
    })
    .await?;
    println!("demo finished: all drones took off, reached their points and landed");
    Ok(())
}

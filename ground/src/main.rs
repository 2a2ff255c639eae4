//! `tacos-ground`: the ground station binary. It parses the command line and hands each
//! subcommand to the library (`tacos_ground::cli`), where its arguments and its work live.

use anyhow::Context;
use clap::{Parser, Subcommand};
use tacos_ground::cli::{
    DemoArgs, EvalArgs, FlyArgs, LlmArgs, PlotArgs, ReplayArgs, SendArgs, SwarmArgs,
};

#[derive(Debug, Parser)]
#[command(version, about = "TACOS ground station: fly a PX4 swarm")]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Live table of the swarm: mode, position, speed, current action, link age.
    Swarm(SwarmArgs),
    /// Send one action to one drone and wait for its outcome.
    ///
    /// Actions: arm_takeoff | goto X Y Z | start_tracking TARGET | stop_tracking | land | hold
    Send(SendArgs),
    /// Start a simulated swarm on this machine and fly it.
    Demo(DemoArgs),
    /// Fly a swarm that is already up (real drones) with the language-model layers; with
    /// --resume LOG, go on with the mission a stopped ground station left in its log.
    Fly(FlyArgs),
    /// Run the paper's ablation: every mode × swarm size × run of a task, on simulated swarms.
    ///
    /// Each finished run is appended to OUT/runs.jsonl at once; running again with the same
    /// OUT resumes. Writes OUT/results.md, OUT/results.csv and OUT/results.svg.
    Eval(EvalArgs),
    /// Print a mission log's timeline.
    Replay(ReplayArgs),
    /// Draw a mission's trajectories over the map, coloured by speed (SVG).
    Plot(PlotArgs),
}

impl Cmd {
    /// The language-model arguments of the subcommands that run the model.
    fn llm(&self) -> Option<&LlmArgs> {
        match self {
            Cmd::Demo(args) => Some(&args.llm),
            Cmd::Fly(args) => Some(&args.llm),
            Cmd::Eval(args) => Some(&args.llm),
            Cmd::Swarm(_) | Cmd::Send(_) | Cmd::Replay(_) | Cmd::Plot(_) => None,
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
    let cli = Cli::parse();
    // candle reads its thread count once, when its pool starts: set before any thread starts.
    if std::env::var_os("CANDLE_NUM_THREADS").is_none()
        && cli
            .command
            .llm()
            .is_some_and(LlmArgs::wants_one_candle_thread)
    {
        // SAFETY: nothing else runs yet: no threads have been started in this process.
        unsafe { std::env::set_var("CANDLE_NUM_THREADS", "1") };
    }
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(async move {
        match cli.command {
            Cmd::Swarm(args) => args.run().await,
            Cmd::Send(args) => args.run().await,
            Cmd::Demo(args) => args.run().await,
            Cmd::Fly(args) => args.run().await,
            Cmd::Eval(args) => args.run().await,
            Cmd::Replay(args) => args.run(),
            Cmd::Plot(args) => args.run(),
        }
    })
}

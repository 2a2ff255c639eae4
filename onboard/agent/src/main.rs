//! `tacos-onboard`: one drone's autonomy process (see the library for what it does).

use anyhow::Context;
use clap::Parser;
use tacos_bus::BusArgs;
use tacos_onboard::OnboardConfig;
use tacos_shared::DroneId;

#[derive(Debug, Parser)]
#[command(version, about = "TACOS onboard autonomy for one drone")]
struct Args {
    #[command(flatten)]
    bus: BusArgs,
    /// This drone's id.
    #[arg(long)]
    drone: DroneId,
    /// Built-in scenario (city, lab) or a scenario TOML file: the world and flight limits.
    #[arg(long, default_value = "city")]
    scenario: String,
    /// Seconds of ground silence before holding.
    #[arg(long, default_value_t = 3.0)]
    failsafe_hold_s: f64,
    /// Seconds of ground silence before landing.
    #[arg(long, default_value_t = 30.0)]
    failsafe_land_s: f64,
    /// Seconds without hearing any of its neighbours (two or more known) before an airborne
    /// drone holds where it is: cut off from its peers, but not from the ground.
    #[arg(long, default_value_t = 3.0)]
    peers_silent_hold_s: f64,
    /// Refuse an action (land and hold aside) that arrives this many seconds later than the
    /// ground station's heartbeats take: the network held it, and the ground has moved on.
    #[arg(long, default_value_t = 2.0)]
    max_action_late_s: f64,
}

/// zenoh's threads in this process unless `ZENOH_RUNTIME` says otherwise: every zenoh runtime
/// handed over to one single-threaded one. A drone's traffic (its neighbours' paths, actions,
/// heartbeats: a few hundred messages a second) does not need zenoh's default six threads, and
/// with them a sample read on one thread was woken from another: in the 20-drone swap on two
/// cores this nearly halved the onboards' context switches and took 4–7 % off their CPU (issue
/// 19 item 3). Set `ZENOH_RUNTIME` to choose otherwise (zenoh's own syntax and defaults).
const ZENOH_RUNTIME: &str = "(app: (worker_threads: 1), rx: (handover: app), tx: (handover: app), \
     acc: (handover: app), net: (handover: app))";

fn main() -> std::process::ExitCode {
    if std::env::var_os("ZENOH_RUNTIME").is_none() {
        // SAFETY: the first thing this process does, while it has one thread: nothing can read
        // the environment at the same time. zenoh reads the variable when it first starts.
        unsafe { std::env::set_var("ZENOH_RUNTIME", ZENOH_RUNTIME) };
    }
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
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    let scenario = tacos_bus::load_scenario(&args.scenario)?;
    let mut cfg = OnboardConfig::new(args.bus, args.drone, scenario);
    cfg.failsafe_hold_s = args.failsafe_hold_s;
    cfg.failsafe_land_s = args.failsafe_land_s;
    anyhow::ensure!(
        args.peers_silent_hold_s > 0.0,
        "--peers-silent-hold-s must be above 0 (got {})",
        args.peers_silent_hold_s
    );
    cfg.peers_silent_hold_s = args.peers_silent_hold_s;
    anyhow::ensure!(
        args.max_action_late_s > 0.0,
        "--max-action-late-s must be above 0 (got {})",
        args.max_action_late_s
    );
    cfg.max_action_late_s = args.max_action_late_s;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(tacos_onboard::run(cfg, shutdown_signal()))?;
    Ok(())
}

async fn shutdown_signal() {
    use tokio::signal::unix::{SignalKind, signal};
    match signal(SignalKind::terminate()) {
        Ok(mut term) => {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
        }
        Err(_) => {
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}

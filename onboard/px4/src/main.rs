//! `tacos-px4`: arguments, logging, signals, then one call into the library.

use anyhow::Context;
use clap::Parser;
use std::io::IsTerminal;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use tacos_px4::{MavlinkLink, WriterConfig, parse_home};
use tacos_shared::frames::Home;
use tacos_shared::{DroneId, SwarmId};
use tracing_subscriber::EnvFilter;

/// MAVLink writer for one drone: streams offboard setpoints to PX4 and runs its commands.
#[derive(Debug, Parser)]
#[command(name = "tacos-px4", version)]
struct Args {
    /// Swarm id (iceoryx2 services are per swarm and drone).
    #[arg(long)]
    swarm: SwarmId,
    /// Drone id, e.g. alfa.
    #[arg(long)]
    drone: DroneId,
    /// The vehicle's home (its NED origin) in world ENU metres: X,Y,Z.
    #[arg(long, value_parser = parse_home, allow_hyphen_values = true)]
    home: Home,
    /// udpin:ADDR (bind ADDR, answer the autopilot's address) or udpout:ADDR (send to ADDR).
    #[arg(long, default_value = "udpin:127.0.0.1:14540")]
    mavlink: MavlinkLink,
    /// SET_POSITION_TARGET_LOCAL_NED rate, Hz (20..=500).
    #[arg(long, default_value_t = 50.0)]
    stream_rate_hz: f64,
    /// No setpoint from the planner for this long → stream a hold at the last one.
    #[arg(long, default_value_t = 500)]
    onboard_timeout_ms: u64,
    /// Our MAVLink system id.
    #[arg(long, default_value_t = 245)]
    sysid: u32,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .init();

    let config = WriterConfig::new(
        args.swarm,
        args.drone,
        args.home,
        args.mavlink,
        args.stream_rate_hz,
        args.onboard_timeout_ms,
        args.sysid,
    )?;

    // SIGINT/SIGTERM set the flag the loops poll; a second one exits at once.
    let shutdown = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(signal, 1, Arc::clone(&shutdown))
            .context("installing a signal handler")?;
        signal_hook::flag::register(signal, Arc::clone(&shutdown))
            .context("installing a signal handler")?;
    }

    let span = tracing::info_span!("px4", drone = %config.drone, swarm = %config.swarm);
    let _guard = span.enter();
    let summary = tacos_px4::run(&config, &shutdown).context("MAVLink writer")?;
    tracing::info!(?summary, "stopped");
    Ok(())
}

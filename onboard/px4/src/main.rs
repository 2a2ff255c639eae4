//! `tacos-px4`: arguments, logging, signals, then one call into the library.

use anyhow::Context;
use clap::Parser;
use std::io::IsTerminal;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use tacos_px4::config::{parse_geofence, parse_param};
use tacos_px4::params::ParamWant;
use tacos_px4::setup::Geofence;
use tacos_px4::{MavlinkIds, MavlinkLink, WriterConfig, parse_home};
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
    /// udpin:ADDR (bind ADDR, answer the autopilot's address), udpout:ADDR (send to ADDR;
    /// for PX4 SITL instance i, udpout:127.0.0.1:14580+i with a fixed --mavlink-local) or
    /// serial:DEVICE:BAUD (a flight controller's port, e.g. serial:/dev/ttyACM0:921600).
    #[arg(long, default_value = "udpin:127.0.0.1:14540")]
    mavlink: MavlinkLink,
    /// The local address an udpout link sends from. PX4 answers only the first address that
    /// talked to it: a writer restarted on a new port would hear nothing.
    #[arg(long)]
    mavlink_local: Option<SocketAddr>,
    /// The autopilot's MAVLink system id (PX4's MAV_SYS_ID; SITL instance i has i+1). Messages
    /// of any other system are ignored.
    #[arg(long, default_value_t = 1)]
    autopilot_sysid: u32,
    /// SET_POSITION_TARGET_LOCAL_NED rate, Hz (20..=500).
    #[arg(long, default_value_t = 50.0)]
    stream_rate_hz: f64,
    /// No setpoint from the planner for this long → stream a hold at the last one.
    #[arg(long, default_value_t = 500)]
    onboard_timeout_ms: u64,
    /// No setpoint from the planner for this many seconds while the vehicle flies → land it
    /// (an onboard that crashed and did not come back).
    #[arg(long, default_value_t = tacos_px4::config::DEFAULT_ONBOARD_LAND_AFTER.as_secs_f64())]
    onboard_land_after_s: f64,
    /// The map's box, MINX,MINY,MINZ,MAXX,MAXY,MAXZ (world ENU metres; the launcher passes the
    /// scenario's bounds), uploaded as PX4's geofence grown by --fence-margin-m. Breach: hold.
    #[arg(long, value_parser = parse_geofence, allow_hyphen_values = true)]
    geofence: Option<Geofence>,
    /// How far outside the map's box the geofence sits (sides and ceiling), metres: the fence
    /// is the backstop for when TACOS fails to keep a drone inside the box, and must not trip
    /// on a drone it holds inside it while the position estimate wanders.
    #[arg(long, default_value_t = tacos_px4::setup::DEFAULT_FENCE_MARGIN_M)]
    fence_margin_m: f64,
    /// A PX4 parameter to set at connect, NAME=VALUE (repeatable; on top of the failsafe
    /// defaults: COM_OBL_RC_ACT=5, COM_OF_LOSS_T=1, NAV_DLL_ACT=0, COM_RCL_EXCEPT=4).
    #[arg(long = "px4-param", value_parser = parse_param)]
    px4_params: Vec<ParamWant>,
    /// Do not read or set parameters or the geofence, and arm without them: only for an
    /// autopilot configured by hand that lacks the parameter or mission protocol.
    #[arg(long)]
    no_autopilot_setup: bool,
    /// Our MAVLink system id (component 191); by default the autopilot's, as PX4 expects of its
    /// onboard computer.
    #[arg(long)]
    sysid: Option<u32>,
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
        MavlinkIds {
            link: args.mavlink,
            local: args.mavlink_local,
            autopilot_sysid: args.autopilot_sysid,
            sysid: args.sysid,
        },
        args.stream_rate_hz,
        args.onboard_timeout_ms,
    )?;

    let mut config = config;
    anyhow::ensure!(
        args.onboard_land_after_s.is_finite() && args.onboard_land_after_s >= 1.0,
        "--onboard-land-after-s must be at least 1 (got {})",
        args.onboard_land_after_s
    );
    config.onboard_land_after = std::time::Duration::from_secs_f64(args.onboard_land_after_s);
    anyhow::ensure!(
        args.fence_margin_m.is_finite() && args.fence_margin_m >= 0.0,
        "--fence-margin-m must be zero or more (got {})",
        args.fence_margin_m
    );
    config.geofence = args.geofence.map(|g| g.grown(args.fence_margin_m));
    config.autopilot_setup = !args.no_autopilot_setup;
    for want in args.px4_params {
        config.params.retain(|p| p.name != want.name);
        config.params.push(want);
    }

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

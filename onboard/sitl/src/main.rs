//! `tacos-sitl`: PX4 SITL stand-in and world simulator. See the library for what it does.

use anyhow::Context;
use clap::Parser;
use std::process::ExitCode;
use tacos_bus::{BusArgs, load_scenario};
use tacos_sitl::SitlConfig;
use tacos_sitl::config::{
    DEFAULT_MAVLINK_BASE_PORT, DEFAULT_SITL_BASE_PORT, ObservePx4, Px4Options,
};
use tacos_sitl::geo::{
    DEFAULT_ORIGIN_AMSL_M, DEFAULT_ORIGIN_LAT_DEG, DEFAULT_ORIGIN_LON_DEG, GeoOrigin,
};
use tacos_sitl::streams::LinkProfile;
use tacos_sitl::vehicle::DEFAULT_READINESS_DELAY;
use tracing_subscriber::EnvFilter;

/// Simulates N PX4 vehicles (MAVLink over UDP, ports like PX4 SITL) and the world around them.
#[derive(Debug, Parser)]
#[command(name = "tacos-sitl", version)]
struct Cli {
    /// A built-in scenario (`city`, `lab`) or the path of a scenario TOML file.
    #[arg(long)]
    scenario: String,
    /// How many vehicles: the scenario's first N drone slots.
    #[arg(long)]
    drones: usize,
    /// Vehicle i sends MAVLink to 127.0.0.1:(this + i) (where the writer listens).
    #[arg(long, default_value_t = DEFAULT_MAVLINK_BASE_PORT)]
    mavlink_base_port: u16,
    /// Vehicle i binds 127.0.0.1:(this + i).
    #[arg(long, default_value_t = DEFAULT_SITL_BASE_PORT)]
    sitl_base_port: u16,
    /// Simulated seconds per wall-clock second while no model call is in flight (the ground
    /// says so on `sim/pace`); the other processes must then follow `sim/clock` (`--sim-clock`).
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Simulated seconds after start before the vehicles can arm (HEARTBEAT.system_status
    /// UNINIT and "Preflight Fail" until then, like PX4 while its estimator settles).
    #[arg(long, default_value_t = DEFAULT_READINESS_DELAY)]
    readiness_delay: f64,
    /// Latitude of world (0, 0, 0), degrees (PX4 SIH's default origin).
    #[arg(long, default_value_t = DEFAULT_ORIGIN_LAT_DEG, allow_negative_numbers = true)]
    origin_lat: f64,
    /// Longitude of world (0, 0, 0), degrees.
    #[arg(long, default_value_t = DEFAULT_ORIGIN_LON_DEG, allow_negative_numbers = true)]
    origin_lon: f64,
    /// Altitude of world (0, 0, 0), metres above mean sea level: PX4 reports altitudes and
    /// reads take-off altitudes AMSL.
    #[arg(long, default_value_t = DEFAULT_ORIGIN_AMSL_M, allow_negative_numbers = true)]
    origin_amsl: f64,
    /// Default stream rates of each vehicle's link: `onboard` (PX4 SITL's offboard link:
    /// LOCAL_POSITION_NED 30 Hz) or `normal` (a telemetry radio: LOCAL_POSITION_NED 1 Hz).
    #[arg(long, default_value_t = LinkProfile::Onboard)]
    link_profile: LinkProfile,
    /// Observe real PX4 SITL vehicles instead of simulating any: drone slot i is read on its
    /// GCS link at 127.0.0.1:(this + i) (PX4 instance n binds 18570+n). The world (targets,
    /// detections, breach checks) then runs on what the vehicles report.
    #[arg(long, requires = "observe_px4_sysid")]
    observe_px4_gcs_port: Option<u16>,
    /// The MAVLink system id of the first observed vehicle (PX4 instance n has n+1).
    #[arg(long, requires = "observe_px4_gcs_port")]
    observe_px4_sysid: Option<u8>,
    #[command(flatten)]
    bus: BusArgs,
}

#[tokio::main]
async fn main() -> ExitCode {
    match run().await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("tacos-sitl: {e:#}");
            ExitCode::FAILURE
        }
    }
}

async fn run() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .init();
    let cli = Cli::parse();
    let scenario = load_scenario(&cli.scenario)
        .with_context(|| format!("loading scenario {:?}", cli.scenario))?;
    let config = SitlConfig {
        scenario,
        drones: cli.drones,
        mavlink_base_port: cli.mavlink_base_port,
        sitl_base_port: cli.sitl_base_port,
        speed: cli.speed,
        px4: Px4Options {
            origin: GeoOrigin {
                lat_deg: cli.origin_lat,
                lon_deg: cli.origin_lon,
                amsl_m: cli.origin_amsl,
            },
            readiness_delay_s: cli.readiness_delay,
            link_profile: cli.link_profile,
        },
        observe: cli.observe_px4_gcs_port.zip(cli.observe_px4_sysid).map(
            |(gcs_base_port, first_sysid)| ObservePx4 {
                gcs_base_port,
                first_sysid,
            },
        ),
        bus: cli.bus,
    };
    tacos_sitl::run(config, shutdown_signal()).await?;
    Ok(())
}

/// Completes on SIGINT or SIGTERM.
async fn shutdown_signal() {
    let interrupt = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::warn!("cannot listen for Ctrl-C: {e}");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut term) => {
                term.recv().await;
            }
            Err(e) => {
                tracing::warn!("cannot listen for SIGTERM: {e}");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = interrupt => tracing::info!("interrupted"),
        () = terminate => tracing::info!("terminated"),
    }
}

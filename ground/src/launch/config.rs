//! What a stack is made of (the swarm, the scenario, the drones, the autopilot, the arguments
//! passed on), and the free ports and binaries it is started with.

use super::{AutopilotKind, LaunchError};
use std::net::{TcpListener, UdpSocket};
use std::path::{Path, PathBuf};
use tacos_bus::BusArgs;
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, SwarmId};

#[derive(Debug, Clone)]
pub struct StackConfig {
    pub swarm: SwarmId,
    /// What the children are told (`city`, `lab` or a file path).
    pub scenario_arg: String,
    pub scenario: Scenario,
    pub drones: usize,
    /// The zenoh endpoint the ground listens on and every child connects to.
    pub hub_endpoint: String,
    pub mavlink_base_port: u16,
    pub sitl_base_port: u16,
    pub bin_dir: PathBuf,
    pub log_dir: PathBuf,
    /// Simulated seconds per wall second while no model call is in flight (`tacos-sitl
    /// --speed`); every other process follows the simulator's clock, so any speed the machine
    /// can compute flies the same mission.
    pub sim_speed: f64,
    /// Extra arguments for tacos-sitl.
    pub sitl_args: Vec<String>,
    /// Extra arguments for every tacos-onboard.
    pub onboard_args: Vec<String>,
    /// Extra arguments for every tacos-px4.
    pub writer_args: Vec<String>,
    pub autopilot: AutopilotKind,
}

impl StackConfig {
    /// A configuration with free ports on loopback and binaries found next to this executable.
    pub fn on_loopback(
        swarm: SwarmId,
        scenario_arg: &str,
        scenario: Scenario,
        drones: usize,
    ) -> Result<Self, LaunchError> {
        scenario
            .first_drones(drones)
            .map_err(LaunchError::Scenario)?;
        let hub_port = free_tcp_port()?;
        let (mavlink_base_port, sitl_base_port) = free_udp_blocks(drones)?;
        let log_dir = std::env::temp_dir().join(format!("tacos-{swarm}"));
        Ok(StackConfig {
            swarm,
            scenario_arg: scenario_arg.to_owned(),
            scenario,
            drones,
            hub_endpoint: format!("tcp/127.0.0.1:{hub_port}"),
            mavlink_base_port,
            sitl_base_port,
            bin_dir: bin_dir(),
            log_dir,
            sim_speed: 1.0,
            sitl_args: Vec::new(),
            onboard_args: Vec::new(),
            writer_args: Vec::new(),
            autopilot: AutopilotKind::Sitl,
        })
    }

    /// How the ground joins this stack: it listens on the hub and follows the simulator's clock.
    pub fn ground_bus(&self) -> BusArgs {
        let mut bus =
            BusArgs::loopback(self.swarm.clone(), Some(self.hub_endpoint.clone()), vec![]);
        bus.sim_clock = true;
        bus
    }

    pub fn drone_ids(&self) -> Vec<DroneId> {
        self.scenario
            .drones
            .iter()
            .take(self.drones)
            .map(|d| d.id.clone())
            .collect()
    }
}

/// Where the TACOS binaries are: `$TACOS_BIN_DIR`, else beside the running executable (one
/// level up when that is cargo's `deps/`, as for tests).
pub fn bin_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("TACOS_BIN_DIR") {
        return PathBuf::from(dir);
    }
    let exe_dir = std::env::current_exe()
        .ok()
        .and_then(|p| p.parent().map(Path::to_path_buf))
        .unwrap_or_default();
    if exe_dir.file_name().is_some_and(|n| n == "deps") {
        exe_dir.parent().map(Path::to_path_buf).unwrap_or(exe_dir)
    } else {
        exe_dir
    }
}

/// A TCP port that was free on loopback a moment ago.
pub fn free_tcp_port() -> Result<u16, LaunchError> {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(|_| LaunchError::NoFreePort { what: "TCP" })
}

fn udp_block_free(base: u16, n: usize) -> bool {
    (0..n).all(|i| {
        base.checked_add(i as u16)
            .is_some_and(|p| UdpSocket::bind(("127.0.0.1", p)).is_ok())
    })
}

/// Two blocks of `n` consecutive UDP ports free on loopback, picked at random from the high
/// range. Not PX4's usual 14540/14580, as this once preferred: real PX4 SITL instances bind
/// those, and two stacks started at once both found them free (each probes, then releases
/// them for its processes), so the second swarm's vehicles never answered.
pub fn free_udp_blocks(n: usize) -> Result<(u16, u16), LaunchError> {
    let seed = std::process::id() as u64
        ^ std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
    for attempt in 0..200u64 {
        let base = 20000
            + ((seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(attempt * 1442695040888963407)
                >> 33)
                % 40000) as u16;
        let other = base.saturating_add(n as u16 + 10);
        if other < 65000 && udp_block_free(base, n) && udp_block_free(other, n) {
            return Ok((base, other));
        }
    }
    Err(LaunchError::NoFreePort { what: "UDP" })
}

//! Starts and supervises a simulated swarm on this machine: `tacos-sitl`, and per drone a
//! `tacos-px4` writer and a `tacos-onboard` process, all joined to one zenoh hub on loopback.
//!
//! Children die with us: each is started with the parent-death signal set (forked from one
//! long-lived thread, `forker`, since the signal follows the forking thread), kept in the
//! supervisor (which kills on drop), and shut down with SIGTERM then SIGKILL.

mod config;
mod forker;
pub mod px4;

pub use config::{StackConfig, bin_dir, free_tcp_port, free_udp_blocks};

use std::path::PathBuf;
use std::process::{ExitStatus, Stdio};
use std::time::Duration;
use tacos_shared::DroneId;
use tokio::process::Command;
use tokio::sync::mpsc;
use tracing::{info, warn};

#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    #[error(
        "{binary} not found in {dir}: build the workspace first (cargo build --workspace --bins) or set TACOS_BIN_DIR"
    )]
    MissingBinary { binary: String, dir: String },
    #[error("cannot start {name}: {reason}")]
    Spawn { name: String, reason: String },
    #[error("cannot prepare the log directory {dir}: {reason}")]
    LogDir { dir: String, reason: String },
    #[error("no free {what} port found on loopback")]
    NoFreePort { what: &'static str },
    #[error("{0}")]
    Scenario(String),
    #[error("{0}")]
    Config(String),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    Sitl,
    Writer,
    Onboard,
    /// A PX4 SITL instance (with `--autopilot px4-sitl`).
    Px4,
}

impl Role {
    pub fn binary(self) -> &'static str {
        match self {
            Role::Sitl => "tacos-sitl",
            Role::Writer => "tacos-px4",
            Role::Onboard => "tacos-onboard",
            Role::Px4 => "px4",
        }
    }
}

/// Which autopilot the drones fly on.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum AutopilotKind {
    /// `tacos-sitl`'s own vehicles, the stand-in for PX4.
    Sitl,
    /// Real PX4 SITL instances (SIH) from this build folder; `tacos-sitl` runs only the world
    /// (targets, detections, breach checks) and observes the vehicles on their GCS links.
    Px4Sitl { dir: PathBuf },
}

/// `--autopilot` and `--px4-sitl`, as the demo and the tests take them.
#[derive(Debug, Clone, clap::Args)]
pub struct AutopilotArgs {
    /// What the drones fly on: `sitl` (tacos-sitl's simulated vehicles) or `px4-sitl` (real
    /// PX4 SITL instances with SIH, one per drone, at the map's pads; runs at real time).
    #[arg(long, value_enum, default_value_t = AutopilotChoice::Sitl)]
    pub autopilot: AutopilotChoice,
    /// The PX4 SITL build folder (bin/px4, etc/); else $TACOS_PX4_SITL, else ../shared/px4-sitl.
    #[arg(long)]
    pub px4_sitl: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum AutopilotChoice {
    Sitl,
    Px4Sitl,
}

impl AutopilotArgs {
    /// The autopilot chosen, with PX4 SITL's folder found.
    pub fn kind(&self) -> Result<AutopilotKind, LaunchError> {
        match self.autopilot {
            AutopilotChoice::Sitl => Ok(AutopilotKind::Sitl),
            AutopilotChoice::Px4Sitl => Ok(AutopilotKind::Px4Sitl {
                dir: px4::find_px4_sitl(self.px4_sitl.as_deref())?,
            }),
        }
    }
}

/// How a child is started: the program and its surroundings.
#[derive(Debug, Clone)]
struct ChildSpec {
    program: PathBuf,
    args: Vec<String>,
    cwd: Option<PathBuf>,
    env: Vec<(String, String)>,
}

/// A child that ended, and how.
#[derive(Debug)]
pub struct ChildExit {
    pub name: String,
    pub role: Role,
    pub drone: Option<DroneId>,
    pub status: Result<ExitStatus, String>,
}

struct ChildHandle {
    role: Role,
    drone: Option<DroneId>,
    pid: Option<u32>,
    running: bool,
    /// How it was started, for [`Stack::restart`].
    spec: ChildSpec,
}

/// The running stack.
pub struct Stack {
    children: Vec<ChildHandle>,
    exits: mpsc::UnboundedReceiver<ChildExit>,
    exit_tx: mpsc::UnboundedSender<ChildExit>,
    pub config: StackConfig,
    /// The first PX4 SITL instance, when the autopilots are PX4.
    px4_base: Option<u16>,
}

impl Stack {
    /// Where a ground station talks MAVLink to the autopilot of the `index`th drone, and the
    /// autopilot's system id: PX4's GCS link, or the stand-in's vehicle port (which takes any
    /// sender's messages, as PX4 does, and answers its first partner).
    pub fn autopilot_address(&self, index: usize) -> Option<(std::net::SocketAddr, u8)> {
        let index = u16::try_from(index).ok()?;
        let (port, sysid) = match self.px4_base {
            Some(base) => (
                px4::GCS_PORT.checked_add(base)?.checked_add(index)?,
                px4::sysid(base.checked_add(index)?),
            ),
            None => (
                self.config.sitl_base_port.checked_add(index)?,
                index.checked_add(1)?,
            ),
        };
        let sysid = u8::try_from(sysid).ok()?;
        Some((std::net::SocketAddr::from(([127, 0, 0, 1], port)), sysid))
    }

    /// Starts the simulator, then a writer and an onboard process per drone.
    pub fn start(config: StackConfig) -> Result<Stack, LaunchError> {
        for role in [Role::Sitl, Role::Writer, Role::Onboard] {
            let path = config.bin_dir.join(role.binary());
            if !path.is_file() {
                return Err(LaunchError::MissingBinary {
                    binary: role.binary().into(),
                    dir: config.bin_dir.display().to_string(),
                });
            }
        }
        std::fs::create_dir_all(&config.log_dir).map_err(|e| LaunchError::LogDir {
            dir: config.log_dir.display().to_string(),
            reason: e.to_string(),
        })?;
        let (exit_tx, exits) = mpsc::unbounded_channel();
        let mut stack = Stack {
            children: Vec::new(),
            exits,
            exit_tx,
            config,
            px4_base: None,
        };
        let c = stack.config.clone();
        let bus = |args: &mut Vec<String>| {
            args.extend([
                "--swarm".into(),
                c.swarm.to_string(),
                "--zenoh-connect".into(),
                c.hub_endpoint.clone(),
            ]);
        };
        if !(c.sim_speed.is_finite() && c.sim_speed > 0.0) {
            return Err(LaunchError::Config(format!(
                "the simulation speed must be positive, got {}",
                c.sim_speed
            )));
        }

        let px4 = match &c.autopilot {
            AutopilotKind::Sitl => None,
            AutopilotKind::Px4Sitl { dir } => {
                if c.sim_speed != 1.0 {
                    return Err(LaunchError::Config(format!(
                        "PX4 SITL runs at real time: the simulation speed must be 1, got {}",
                        c.sim_speed
                    )));
                }
                let bundle = px4::prepare(dir, &c.log_dir.join("px4"))?;
                let base = px4::free_instance_base(c.drones)?;
                stack.px4_base = Some(base);
                Some((bundle, base))
            }
        };

        let mut sitl = vec![
            "--scenario".into(),
            c.scenario_arg.clone(),
            "--drones".into(),
            c.drones.to_string(),
            "--mavlink-base-port".into(),
            c.mavlink_base_port.to_string(),
            "--sitl-base-port".into(),
            c.sitl_base_port.to_string(),
        ];
        bus(&mut sitl);
        sitl.extend(["--speed".into(), c.sim_speed.to_string()]);
        if let Some((_, base)) = &px4 {
            sitl.extend([
                "--observe-px4-gcs-port".into(),
                (px4::GCS_PORT + base).to_string(),
                "--observe-px4-sysid".into(),
                px4::sysid(*base).to_string(),
            ]);
        }
        sitl.extend(c.sitl_args.iter().cloned());

        for (i, slot) in c.scenario.drones.iter().take(c.drones).enumerate() {
            let home = format!("{},{},{}", slot.home.x, slot.home.y, slot.home.z);
            let mut writer = vec![
                "--swarm".into(),
                c.swarm.to_string(),
                "--drone".into(),
                slot.id.to_string(),
                "--home".into(),
                home,
            ];
            let local = format!("127.0.0.1:{}", c.mavlink_base_port as usize + i);
            // The map's box becomes the autopilot's own geofence (breach: hold).
            let (lo, hi) = (c.scenario.world.bounds.min, c.scenario.world.bounds.max);
            writer.push(format!(
                "--geofence={},{},{},{},{},{}",
                lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
            ));
            match &px4 {
                None => writer.extend([
                    "--mavlink".into(),
                    format!("udpin:{local}"),
                    "--autopilot-sysid".into(),
                    (i + 1).to_string(),
                ]),
                Some((bundle, base)) => {
                    let instance = base + i as u16;
                    let launch = px4::instance(bundle, instance, &slot.home);
                    std::fs::create_dir_all(&launch.cwd).map_err(|e| LaunchError::LogDir {
                        dir: launch.cwd.display().to_string(),
                        reason: e.to_string(),
                    })?;
                    stack.spawn_child(
                        Role::Px4,
                        Some(slot.id.clone()),
                        ChildSpec {
                            program: bundle.px4.clone(),
                            args: launch.args,
                            cwd: Some(launch.cwd),
                            env: launch.env,
                        },
                    )?;
                    writer.extend([
                        "--mavlink".into(),
                        format!("udpout:127.0.0.1:{}", px4::OFFBOARD_PORT + instance),
                        "--mavlink-local".into(),
                        local,
                        "--autopilot-sysid".into(),
                        px4::sysid(instance).to_string(),
                    ]);
                }
            }
            writer.extend(c.writer_args.iter().cloned());
            stack.spawn(Role::Writer, Some(slot.id.clone()), writer)?;
            let mut onboard = vec![
                "--drone".into(),
                slot.id.to_string(),
                "--scenario".into(),
                c.scenario_arg.clone(),
            ];
            bus(&mut onboard);
            onboard.push("--sim-clock".into());
            onboard.extend(c.onboard_args.iter().cloned());
            stack.spawn(Role::Onboard, Some(slot.id.clone()), onboard)?;
        }
        // The world last: with PX4 it must be the first to talk to each GCS link.
        stack.spawn(Role::Sitl, None, sitl)?;
        info!(drones = c.drones, logs = %c.log_dir.display(), hub = %c.hub_endpoint, "simulated swarm started");
        Ok(stack)
    }

    /// Starts (or restarts) one TACOS process of the stack.
    pub fn spawn(
        &mut self,
        role: Role,
        drone: Option<DroneId>,
        args: Vec<String>,
    ) -> Result<(), LaunchError> {
        let spec = ChildSpec {
            program: self.config.bin_dir.join(role.binary()),
            args,
            cwd: None,
            env: Vec::new(),
        };
        self.spawn_child(role, drone, spec)
    }

    fn spawn_child(
        &mut self,
        role: Role,
        drone: Option<DroneId>,
        spec: ChildSpec,
    ) -> Result<(), LaunchError> {
        let name = match &drone {
            Some(d) => format!("{}[{d}]", role.binary()),
            None => role.binary().to_owned(),
        };
        let log_name = match &drone {
            Some(d) => format!("{}-{d}.log", role.binary()),
            None => format!("{}.log", role.binary()),
        };
        let log_path = self.config.log_dir.join(log_name);
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .map_err(|e| LaunchError::Spawn {
                name: name.clone(),
                reason: format!("log file {}: {e}", log_path.display()),
            })?;
        let log_err = log.try_clone().map_err(|e| LaunchError::Spawn {
            name: name.clone(),
            reason: e.to_string(),
        })?;
        let handle_spec = spec.clone();
        let mut command = Command::new(&spec.program);
        if let Some(cwd) = &spec.cwd {
            command.current_dir(cwd);
        }
        command
            .args(&spec.args)
            .envs(spec.env.iter().map(|(k, v)| (k, v)))
            .stdin(Stdio::null())
            .stdout(log)
            .stderr(log_err)
            .kill_on_drop(true);
        // SAFETY: prctl is async-signal-safe; it only sets the signal the child gets when this
        // process dies, so no child outlives a ground station that was killed.
        unsafe {
            command.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                Ok(())
            });
        }
        let mut child = forker::spawn(command).map_err(|e| LaunchError::Spawn {
            name: name.clone(),
            reason: e.to_string(),
        })?;
        let pid = child.id();
        let tx = self.exit_tx.clone();
        let exit = ChildExit {
            name: name.clone(),
            role,
            drone: drone.clone(),
            status: Err(String::new()),
        };
        tokio::spawn(async move {
            let status = child.wait().await.map_err(|e| e.to_string());
            let _ = tx.send(ChildExit { status, ..exit });
        });
        self.children
            .retain(|c| !(c.role == role && c.drone == drone && !c.running));
        self.children.push(ChildHandle {
            role,
            drone,
            pid,
            running: true,
            spec: handle_spec,
        });
        Ok(())
    }

    /// Starts a process that exited (or was crashed) again, exactly as it was started before:
    /// what a service manager's `Restart=` does.
    pub fn restart(&mut self, role: Role, drone: Option<&DroneId>) -> Result<(), LaunchError> {
        let spec = self
            .children
            .iter()
            .find(|c| c.role == role && c.drone.as_ref() == drone)
            .map(|c| c.spec.clone())
            .ok_or_else(|| LaunchError::Config(format!("no {} to restart", role.binary())))?;
        if self
            .children
            .iter()
            .any(|c| c.running && c.role == role && c.drone.as_ref() == drone)
        {
            return Err(LaunchError::Config(format!(
                "{} is still running",
                role.binary()
            )));
        }
        self.spawn_child(role, drone.cloned(), spec)
    }

    fn signal(&self, role: Role, drone: Option<&DroneId>, signal: i32) -> bool {
        let mut sent = false;
        for c in self
            .children
            .iter()
            .filter(|c| c.running && c.role == role && c.drone.as_ref() == drone)
        {
            if let Some(pid) = c.pid {
                // SAFETY: kill(2) with a pid we spawned and have not reaped yet.
                unsafe { libc::kill(pid as i32, signal) };
                sent = true;
            }
        }
        sent
    }

    /// Freezes one process (SIGSTOP), as an overloaded computer descheduling it would, until
    /// [`Stack::thaw`]. False when it is not running.
    pub fn freeze(&self, role: Role, drone: Option<&DroneId>) -> bool {
        self.signal(role, drone, libc::SIGSTOP)
    }

    /// Lets a frozen process go on (SIGCONT).
    pub fn thaw(&self, role: Role, drone: Option<&DroneId>) -> bool {
        self.signal(role, drone, libc::SIGCONT)
    }

    /// Kills one process hard (SIGKILL), as a crash would; returns its exit once reaped.
    pub async fn crash(&mut self, role: Role, drone: Option<&DroneId>) -> Option<ChildExit> {
        if !self.signal(role, drone, libc::SIGKILL) {
            return None;
        }
        loop {
            let exit = self.exits.recv().await?;
            self.mark_exited(&exit);
            if exit.role == role && exit.drone.as_ref() == drone {
                return Some(exit);
            }
            warn!(child = %exit.name, status = ?exit.status, "another child exited while one was being killed");
        }
    }

    fn mark_exited(&mut self, exit: &ChildExit) {
        for c in self
            .children
            .iter_mut()
            .filter(|c| c.role == exit.role && c.drone == exit.drone)
        {
            c.running = false;
        }
    }

    /// Resolves when any child exits (the demo treats that as a failure).
    pub async fn next_exit(&mut self) -> Option<ChildExit> {
        let exit = self.exits.recv().await?;
        self.mark_exited(&exit);
        Some(exit)
    }

    /// A child exit that happens within `wait`, if any: used to tell "a drone vanished" apart
    /// from "its process died", which the link may notice first.
    pub async fn exit_within(&mut self, wait: Duration) -> Option<ChildExit> {
        let exit = tokio::time::timeout(wait, self.exits.recv())
            .await
            .ok()
            .flatten()?;
        self.mark_exited(&exit);
        Some(exit)
    }

    /// SIGTERM to every child, SIGKILL to those still running after `grace`; waits for all.
    pub async fn shutdown(mut self, grace: Duration) {
        let running: Vec<(Role, Option<DroneId>)> = self
            .children
            .iter()
            .filter(|c| c.running)
            .map(|c| (c.role, c.drone.clone()))
            .collect();
        for (role, drone) in &running {
            self.signal(*role, drone.as_ref(), libc::SIGTERM);
        }
        let deadline = tokio::time::Instant::now() + grace;
        while self.children.iter().any(|c| c.running) {
            match tokio::time::timeout_at(deadline, self.exits.recv()).await {
                Ok(Some(exit)) => self.mark_exited(&exit),
                Ok(None) => break,
                Err(_) => {
                    let left: Vec<(Role, Option<DroneId>)> = self
                        .children
                        .iter()
                        .filter(|c| c.running)
                        .map(|c| (c.role, c.drone.clone()))
                        .collect();
                    for (role, drone) in &left {
                        warn!(binary = role.binary(), drone = ?drone, "did not stop on SIGTERM; killing");
                        self.signal(*role, drone.as_ref(), libc::SIGKILL);
                    }
                    while self.children.iter().any(|c| c.running) {
                        match tokio::time::timeout(Duration::from_secs(5), self.exits.recv()).await
                        {
                            Ok(Some(exit)) => self.mark_exited(&exit),
                            _ => break,
                        }
                    }
                    break;
                }
            }
        }
    }
}

impl Drop for Stack {
    fn drop(&mut self) {
        for c in self.children.iter().filter(|c| c.running) {
            if let Some(pid) = c.pid {
                // SAFETY: as in `signal`.
                unsafe { libc::kill(pid as i32, libc::SIGKILL) };
            }
        }
    }
}

//! The task shell around the executor and the planner: zenoh in and out (actions, heartbeats,
//! neighbours' paths, targets; status, this drone's path), iceoryx2 to the writer, the clock.
//! Actions and heartbeats are acted on in zenoh's callbacks (`shared_core`); the rest is read
//! by the loop task.
//!
//! Every time here is read from one `tacos_bus::clock::Clock`: the wall clock on a drone, the simulator's with
//! `--sim-clock`, so that rates, deadlines, the failsafe and path stamps keep their meaning when a
//! simulation runs faster than real time.

mod ground_side;
mod shared_core;

use crate::executor::{Executor, ExecutorConfig};
use crate::failsafe::FailsafeTimer;
use crate::ground_follow::GroundFollower;
use crate::motion::{Motion, MotionConfig, SolveDone, Steering};
use crate::planner::{PlannerConfig, PlannerError};
use crate::stall::StallWatch;
use ground_side::GroundSide;
use shared_core::{Core, CorePoisoned, SharedCore, take_ground_messages};
use std::future::Future;
use tacos_bus::{BusArgs, BusError};
use tacos_ipc::{IpcError, IpcNode};
use tacos_shared::DroneId;
use tacos_shared::ipc::SetpointSample;
use tacos_shared::messages::{DroneStatus, PathMessage, TargetsMessage};
use tacos_shared::scenario::Scenario;
use tracing::{Instrument, info, info_span, warn};

#[derive(Debug, Clone)]
pub struct OnboardConfig {
    pub bus: BusArgs,
    pub drone: DroneId,
    pub scenario: Scenario,
    /// Setpoint and executor rate.
    pub control_rate_hz: f64,
    /// Status publication rate (≥ 10 Hz).
    pub status_rate_hz: f64,
    /// Ground silent this long → hold.
    pub failsafe_hold_s: f64,
    /// Ground silent this long → land.
    pub failsafe_land_s: f64,
    /// Every known neighbour silent this long → hold (see `Executor::set_peers_silent`).
    pub peers_silent_hold_s: f64,
    /// An action of the followed ground arriving this much later than its heartbeats take is
    /// refused (land and hold aside): see `ground_follow`.
    pub max_action_late_s: f64,
    /// No vehicle state from the writer for this long → autopilot link treated as lost.
    pub writer_timeout_s: f64,
    /// Control ticks further apart than this mean the process stalled: the time lost is not
    /// counted as the ground's or the peers' silence (see `crate::stall`).
    pub stall_after_s: f64,
    /// The planner's rate, the neighbours' paths, the tracker.
    pub motion: MotionConfig,
}

impl OnboardConfig {
    pub fn new(bus: BusArgs, drone: DroneId, scenario: Scenario) -> Self {
        OnboardConfig {
            bus,
            drone,
            scenario,
            control_rate_hz: 50.0,
            status_rate_hz: 20.0,
            failsafe_hold_s: 3.0,
            failsafe_land_s: 30.0,
            peers_silent_hold_s: 3.0,
            max_action_late_s: 2.0,
            writer_timeout_s: 1.0,
            stall_after_s: 0.25,
            motion: MotionConfig::default(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum OnboardError {
    #[error(transparent)]
    Bus(#[from] BusError),
    #[error(transparent)]
    Ipc(#[from] IpcError),
    #[error("the zenoh subscriber for {0} closed")]
    SubscriberClosed(String),
    #[error(transparent)]
    Planner(#[from] PlannerError),
    #[error("the planner's solve did not return: {0}")]
    PlannerLost(String),
    #[error(transparent)]
    CorePoisoned(#[from] CorePoisoned),
}

/// Counts malformed payloads of one kind, warning on the 1st, 2nd, 4th, 8th… so a flood does not
/// flood the log.
#[derive(Debug, Default)]
struct Malformed {
    what: &'static str,
    count: u64,
}

impl Malformed {
    fn new(what: &'static str) -> Self {
        Malformed { what, count: 0 }
    }

    fn note(&mut self, error: &dyn std::fmt::Display) {
        self.count += 1;
        if self.count.is_power_of_two() {
            warn!(error = %error, count = self.count, "malformed {} ignored", self.what);
        }
    }
}

/// Takes in the neighbours' path samples queued since the last call.
///
/// Paths are taken in at the control ticks and before a solve starts, never as each one
/// arrives: a select arm per sample woke this loop for every neighbour's path (19 × 20 a
/// second in a 20-drone swarm), and those wake-ups were a quarter of the onboards' context
/// switches (issue 19 item 3). A path waits at most one control period (20 ms); its age is
/// taken from its stamp either way.
fn take_paths(
    motion: &mut Motion,
    paths: &tacos_bus::Latest<PathMessage>,
    malformed: &mut Malformed,
    key: &str,
) -> Result<(), OnboardError> {
    while let Some(path) = paths
        .try_recv()
        .map_err(|_| OnboardError::SubscriberClosed(key.to_owned()))?
    {
        match path {
            Ok(path) => motion.on_path(path),
            Err(e) => malformed.note(&e),
        }
    }
    Ok(())
}

/// Hands a solve to a blocking thread when the planner flies (`Steering::Toward`).
fn start_solve(
    motion: &mut Motion,
    executor: &Executor,
    steering: Steering,
    now: f64,
) -> Option<tokio::task::JoinHandle<SolveDone>> {
    let Steering::Toward(goal) = steering else {
        return None;
    };
    let vehicle = executor.vehicle()?;
    let tracking = executor.following().map(|(target, _)| target);
    let job = motion.solve_job(now, vehicle.position, vehicle.velocity, goal, tracking)?;
    Some(tokio::task::spawn_blocking(move || job.run()))
}

/// The status `core` tells, numbered `counter`.
fn status_of(core: &Core, drone: &DroneId, counter: u64) -> DroneStatus {
    let Core { executor, ground } = core;
    let vehicle = executor.vehicle().copied();
    DroneStatus {
        drone: drone.clone(),
        counter,
        mode: executor.mode(),
        armed: vehicle.is_some_and(|v| v.armed),
        position: vehicle.map(|v| v.position).unwrap_or_default(),
        velocity: vehicle.map(|v| v.velocity).unwrap_or_default(),
        autopilot_link: vehicle.is_some_and(|v| v.link_ok),
        action: executor.progress().cloned(),
        failsafe: executor.failsafe(),
        peers_silent: executor.peers_silent(),
        malformed_actions: ground.malformed_actions,
        ground: ground.grounds.followed(),
        refused: ground.refused.clone(),
        autopilot_took_over: executor.autopilot_took_over(),
    }
}

/// Runs the drone until `shutdown` completes.
pub async fn run(
    cfg: OnboardConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<(), OnboardError> {
    let span = info_span!("drone", id = %cfg.drone);
    run_inner(cfg, shutdown).instrument(span).await
}

async fn run_inner(
    cfg: OnboardConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<(), OnboardError> {
    let keys = cfg.bus.keys();
    let drone = cfg.drone.clone();
    let session = cfg.bus.open().await?;
    let clock = cfg.bus.clock(&session).await?;
    // The simulator is up before its onboards; waiting keeps the timers from jumping clocks.
    clock
        .synced(std::time::Duration::from_secs(10))
        .await
        .map_err(BusError::from)?;
    let now = || clock.now();
    // A ground station silent for the hold time may be replaced by another.
    let core = SharedCore::new(Core {
        executor: Executor::new(ExecutorConfig::new(
            cfg.scenario.limits,
            cfg.scenario.world.clone(),
        )),
        ground: GroundSide::new(
            GroundFollower::new(cfg.failsafe_hold_s, cfg.max_action_late_s),
            FailsafeTimer::new(cfg.failsafe_hold_s, cfg.failsafe_land_s, now()),
        ),
    });
    let _ground_subscribers = take_ground_messages(&session, &keys, &drone, &core, &clock).await?;
    // Enough room for a few rounds of every neighbour's path; older ones are superseded anyway.
    let paths_key = keys.all_paths();
    let paths = tacos_bus::subscribe_latest::<PathMessage>(&session, &paths_key, 256).await?;
    let targets =
        tacos_bus::subscribe_latest::<TargetsMessage>(&session, &keys.targets(), 8).await?;
    let ipc = IpcNode::new(&cfg.bus.swarm, &drone)?;
    let ports = ipc.onboard_ports()?;
    // Declared last: the ground sees the drone only once it can take actions.
    let _alive = tacos_bus::declare_alive(&session, &keys.alive(&drone)).await?;
    info!(swarm = %cfg.bus.swarm, "onboard up");

    let mut motion = Motion::new(
        drone.clone(),
        PlannerConfig::from_scenario(&cfg.scenario.limits, &cfg.scenario.world),
        cfg.motion.clone(),
    )?;
    let path_key = keys.path(&drone);
    let mut malformed_paths = Malformed::new("neighbour path");
    let mut malformed_targets = Malformed::new("targets message");
    let mut stats_logged_at = now();
    // The solve in flight on a blocking thread: the control loop keeps streaming the current
    // plan meanwhile, so a slow solve never stalls the setpoints.
    let mut solving: Option<tokio::task::JoinHandle<SolveDone>> = None;
    // Solves are paced by their own timer (not every n-th control tick, which would round the
    // period up to a multiple of 20 ms); each starts from the state the last tick saw.
    let mut plan_timer = clock.ticker(cfg.motion.plan_period);
    // A tick that found a solve still running: the next solve starts as soon as that one is
    // done instead of a whole period later. On a starved CPU (20 drones on two cores, where
    // the swap crosses) a solve can outlast the period; skipping the tick left the drones
    // 10–14 solves a second where they should have 20.
    let mut solve_due = false;
    let mut last_steering: Option<Steering> = None;
    let mut control = clock.ticker(1.0 / cfg.control_rate_hz);
    let mut stalls = StallWatch::new(1.0 / cfg.control_rate_hz, cfg.stall_after_s);
    let status_every = (cfg.control_rate_hz / cfg.status_rate_hz).round().max(1.0) as u64;
    let status_key = keys.status(&drone);

    let mut ticks: u64 = 0;
    let mut status_counter: u64 = 0;
    let mut setpoint_seq: u64 = 0;
    let mut last_state_at: Option<f64> = None;
    let mut ipc_errors: u64 = 0;
    let mut publish_now = false;
    tokio::pin!(shutdown);

    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            () = core.status_due() => publish_now = true,
            done = async {
                match solving.as_mut() {
                    Some(job) => job.await,
                    None => std::future::pending().await,
                }
            } => {
                solving = None;
                match done {
                    Ok(done) => {
                        if let Some(path) = motion.solve_done(done, now())
                            && let Err(e) = tacos_bus::put(&session, &path_key, &path, tacos_bus::Delivery::Telemetry).await
                        {
                            warn!(error = %e, "path not published");
                        }
                    }
                    // Only a panic in the solver gets here; the planner went with it.
                    Err(e) => return Err(OnboardError::PlannerLost(e.to_string())),
                }
                if std::mem::take(&mut solve_due) && let Some(steering) = last_steering {
                    take_paths(&mut motion, &paths, &mut malformed_paths, &paths_key)?;
                    solving = start_solve(&mut motion, &core.lock()?.executor, steering, now());
                }
            }
            _ = plan_timer.tick() => {
                if solving.is_some() {
                    solve_due = true;
                } else if let Some(steering) = last_steering {
                    take_paths(&mut motion, &paths, &mut malformed_paths, &paths_key)?;
                    solving = start_solve(&mut motion, &core.lock()?.executor, steering, now());
                }
            }
            message = targets.recv_async() => {
                match message.map_err(|_| OnboardError::SubscriberClosed(keys.targets()))? {
                    Ok(message) => motion.on_targets(&message, now()),
                    Err(e) => malformed_targets.note(&e),
                }
            }
            _ = control.tick() => {
                let t = now();
                // The core's lock is let go before the path goes out (never held across an `.await`).
                let (step, path_out) = {
                    let mut held = core.lock()?;
                    let Core { executor, ground } = &mut *held;
                    if let Some(deaf_s) = stalls.tick(t) {
                        ground.failsafe.excuse(deaf_s, t);
                        motion.excuse_peers(deaf_s, t);
                        if deaf_s >= 1.0 {
                            warn!(deaf_s, "this onboard stalled: the time is not counted as silence");
                        }
                    }
                    // Every path queued since the last tick, before the peers' silence is judged
                    // on them. (Heartbeats are taken in by their callback as they arrive.)
                    take_paths(&mut motion, &paths, &mut malformed_paths, &paths_key)?;
                    let mut path_out = None;
                    let step = (|| -> Result<(), IpcError> {
                        for result in ports.results.drain()? {
                            executor.on_result(&result, t);
                        }
                        if let Some(state) = ports.state.latest()? {
                            executor.on_vehicle(&state);
                            last_state_at = Some(t);
                        }
                        if last_state_at.is_some_and(|at| t - at > cfg.writer_timeout_s) {
                            executor.on_writer_silent();
                        }
                        let before = executor.failsafe();
                        executor.set_failsafe(ground.failsafe.stage(t), t);
                        if executor.failsafe() != before {
                            warn!(stage = ?executor.failsafe(), silence_s = ground.failsafe.silence(t), "failsafe changed");
                        }
                        let peers_silence = motion.peers_silence(t);
                        let peers_were_silent = executor.peers_silent();
                        executor.set_peers_silent(peers_silence.is_some_and(|s| s >= cfg.peers_silent_hold_s));
                        if executor.peers_silent() != peers_were_silent {
                            match peers_silence {
                                Some(s) if executor.peers_silent() => warn!(silence_s = s, "no neighbour heard: an airborne drone holds"),
                                _ => info!("a neighbour is heard again"),
                            }
                        }
                        if let Some((target, altitude)) = executor.following() {
                            let station = motion.station(target, altitude, t);
                            executor.on_station(station, t);
                        }
                        let out = executor.tick(t);
                        motion.set_airborne(executor.airborne());
                        for command in out.commands {
                            ports.send_command(command)?;
                        }
                        last_steering = out.steering;
                        if let (Some(steering), Some(vehicle)) = (out.steering, executor.vehicle()) {
                            // The first solve of a new goal starts at once; then the timer paces.
                            if let Steering::Toward(_) = steering
                                && solving.is_none()
                                && !motion.has_plan()
                            {
                                solving = start_solve(&mut motion, executor, steering, t);
                            }
                            let step = motion.tick(t, vehicle.position, vehicle.velocity, steering);
                            path_out = step.path;
                            let reference = step.reference;
                            setpoint_seq += 1;
                            ports.send_setpoint(SetpointSample {
                                seq: setpoint_seq,
                                stamp_ns: (t.max(0.0) * 1e9) as u64,
                                position: reference.position.into(),
                                velocity: reference.velocity.into(),
                                acceleration: reference.acceleration.into(),
                                yaw: f64::NAN,
                            })?;
                        }
                        Ok(())
                    })();
                    (step, path_out)
                };
                if let Some(path) = path_out
                    && let Err(e) = tacos_bus::put(&session, &path_key, &path, tacos_bus::Delivery::Telemetry).await
                {
                    warn!(error = %e, "path not published");
                }
                if t - stats_logged_at >= 10.0 {
                    stats_logged_at = t;
                    let s = motion.stats();
                    info!(solves = s.solves, relaxed = s.relaxed, braking = s.braking, rejected = s.rejected, slowest_ms = s.slowest_s * 1e3, overran_ms = s.overran_s * 1e3, widest_margin_m = s.widest_margin_m, "planner");
                }
                if let Err(e) = step {
                    ipc_errors += 1;
                    if ipc_errors.is_power_of_two() {
                        warn!(error = %e, count = ipc_errors, "iceoryx2 exchange with the writer failed");
                    }
                }
                ticks += 1;
                if ticks.is_multiple_of(status_every) {
                    publish_now = true;
                }
            }
        }
        if publish_now {
            publish_now = false;
            status_counter += 1;
            let status = status_of(&*core.lock()?, &drone, status_counter);
            if let Err(e) = tacos_bus::put(
                &session,
                &status_key,
                &status,
                tacos_bus::Delivery::Telemetry,
            )
            .await
            {
                warn!(error = %e, "status not published");
            }
        }
    }
    info!("onboard shutting down");
    Ok(())
}

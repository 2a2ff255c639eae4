//! The ground's zenoh link: keeps the swarm view current, sends checked actions, waits for
//! their outcome, and beats the ground heartbeat the drones' failsafe listens for. It also holds
//! the ground's clock (the simulator's with `--sim-clock`) and tells a simulator when a model call
//! is in flight (`sim/pace`), so that the simulation runs at real time while a model thinks.

use crate::safety::CheckedAction;
use crate::swarm::{SwarmChange, SwarmView};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tacos_bus::clock::Clock;
use tacos_bus::{BusArgs, BusError};
use tacos_shared::keys::Keys;
use tacos_shared::messages::{
    ActionState, DroneStatus, FaultRequest, GroundHeartbeat, RefusedBecause, SimPace, SimTruth,
    TargetObservation, TargetsMessage, WorldEvent,
};
use tacos_shared::scenario::FaultKind;
use tacos_shared::{ActionCommand, DroneId};
use tokio::sync::{broadcast, watch};
use tokio::task::JoinHandle;
use tracing::{debug, warn};
use zenoh::sample::SampleKind;

/// How often the ground heartbeat is sent.
pub const HEARTBEAT_PERIOD: Duration = Duration::from_millis(200);
/// How often `sim/pace` is repeated when nothing changes (a simulator that missed a change, or
/// started later, learns it within this).
const PACE_REPEAT: Duration = Duration::from_secs(1);

#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error(transparent)]
    Bus(#[from] BusError),
    #[error("{drone} did not finish action #{seq} within {waited:?}")]
    Timeout {
        drone: DroneId,
        seq: u64,
        waited: Duration,
    },
    #[error("{0} left the swarm before its action finished")]
    DroneLost(DroneId),
    #[error("{drone}: action #{seq} was replaced by #{newer} before it finished")]
    Superseded {
        drone: DroneId,
        seq: u64,
        newer: u64,
    },
    #[error("timed out after {0:?} waiting for drones: {1}")]
    WaitDrones(Duration, String),
    #[error(
        "{drone} follows another ground station ({followed}), which is still beating: a drone takes actions from one ground station at a time"
    )]
    NotFollowed { drone: DroneId, followed: u64 },
    #[error("{drone} refused action #{seq}: {why}")]
    Refused {
        drone: DroneId,
        seq: u64,
        why: RefusedBecause,
    },
}

struct Shared {
    view: Mutex<SwarmView>,
    version: watch::Sender<u64>,
    changes: broadcast::Sender<SwarmChange>,
    /// Joins and departures only: rare, so a slow reader never misses one to lag.
    membership: broadcast::Sender<SwarmChange>,
    malformed_status: AtomicU64,
    /// False while the ground plays dead (`set_heartbeat`).
    heartbeat_on: std::sync::atomic::AtomicBool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, SwarmView> {
        // A panic while holding the lock cannot leave the view half-written (every update is a
        // single assignment), so a poisoned lock is still safe to read.
        self.view.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn changed(&self, change: SwarmChange) {
        self.version.send_modify(|v| *v += 1);
        if !matches!(change, SwarmChange::Status(_)) {
            let _ = self.membership.send(change.clone());
        }
        let _ = self.changes.send(change);
    }
}

/// A model call in flight, from [`GroundLink::model_call`] until dropped.
#[must_use = "the call counts as in flight only while the guard lives"]
pub struct ModelCallGuard {
    calls_in_flight: Arc<watch::Sender<u32>>,
}

impl Drop for ModelCallGuard {
    fn drop(&mut self) {
        self.calls_in_flight
            .send_modify(|n| *n = n.saturating_sub(1));
    }
}

pub struct GroundLink {
    session: zenoh::Session,
    keys: Keys,
    clock: Clock,
    /// Model calls in flight (see [`GroundLink::model_call`]).
    calls_in_flight: Arc<watch::Sender<u32>>,
    shared: Arc<Shared>,
    next_seq: AtomicU64,
    /// This ground station's epoch: named in its heartbeats and actions (a drone follows one
    /// ground station at a time).
    epoch: u64,
    tasks: Vec<JoinHandle<()>>,
}

impl Drop for GroundLink {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
    }
}

/// Whether a ground station supervises the swarm. Only one in control beats the heartbeat
/// the drones' ground-silence failsafe listens for: a passive monitor that kept it going
/// would keep every drone "supervised" with nobody at the controls.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GroundRole {
    InControl,
    Monitor,
}

impl GroundLink {
    /// Joins the swarm's network as the ground station in control and starts following it.
    pub async fn connect(bus: &BusArgs) -> Result<GroundLink, LinkError> {
        Self::connect_as(bus, GroundRole::InControl).await
    }

    /// Joins the swarm's network in `role` and starts following it.
    pub async fn connect_as(bus: &BusArgs, role: GroundRole) -> Result<GroundLink, LinkError> {
        let session = bus.open().await?;
        let keys = bus.keys();
        let clock = bus.clock(&session).await?;
        let (version, _) = watch::channel(0);
        let (changes, _) = broadcast::channel(256);
        let (membership, _) = broadcast::channel(64);
        let shared = Arc::new(Shared {
            view: Mutex::new(SwarmView::default()),
            version,
            changes,
            membership,
            malformed_status: AtomicU64::new(0),
            heartbeat_on: std::sync::atomic::AtomicBool::new(role == GroundRole::InControl),
        });
        let mut tasks = Vec::new();

        let statuses = tacos_bus::subscribe(&session, &keys.all_status()).await?;
        let s = shared.clone();
        let c = clock.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(sample) = statuses.recv_async().await {
                match tacos_bus::decode::<DroneStatus>(&sample) {
                    Ok(status) => {
                        let change = s.lock().apply_status(status, c.instant());
                        s.changed(change);
                    }
                    Err(e) => {
                        let n = s.malformed_status.fetch_add(1, Ordering::Relaxed) + 1;
                        warn!(key = %sample.key_expr(), error = %e, count = n, "malformed status ignored");
                    }
                }
            }
        }));

        let alive = tacos_bus::watch_alive(&session, &keys.all_alive()).await?;
        let s = shared.clone();
        let k = keys.clone();
        let c = clock.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(sample) = alive.recv_async().await {
                let Some(id) = k.drone_of(sample.key_expr().as_str()) else {
                    continue;
                };
                let is_alive = sample.kind() == SampleKind::Put;
                let change = s.lock().apply_liveliness(&id, is_alive, c.instant());
                if let Some(change) = change {
                    debug!(?change, "liveliness");
                    s.changed(change);
                }
            }
        }));

        // Sequence numbers grow across ground restarts: start from the wall clock. The start
        // is this station's epoch too (two started in the same microsecond are not told apart).
        let epoch = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(1, |d| d.as_micros() as u64);
        let hb_session = session.clone();
        let hb_key = keys.ground_heartbeat();
        let hb_shared = shared.clone();
        let hb_clock = clock.clone();
        tasks.push(tokio::spawn(async move {
            let mut tick = tokio::time::interval(HEARTBEAT_PERIOD);
            let mut counter = 0u64;
            loop {
                tick.tick().await;
                if !hb_shared.heartbeat_on.load(Ordering::Relaxed) {
                    continue;
                }
                counter += 1;
                if let Err(e) = tacos_bus::put(
                    &hb_session,
                    &hb_key,
                    &GroundHeartbeat {
                        counter,
                        ground: epoch,
                        stamp: hb_clock.now(),
                    },
                    tacos_bus::Delivery::Beat,
                )
                .await
                {
                    warn!(error = %e, "ground heartbeat not sent");
                }
            }
        }));

        let (calls_in_flight, mut calls) = watch::channel(0u32);
        if clock.is_simulated() {
            let pace_session = session.clone();
            let pace_key = keys.sim_pace();
            tasks.push(tokio::spawn(async move {
                loop {
                    let pace = SimPace {
                        model_call_in_flight: *calls.borrow_and_update() > 0,
                    };
                    if let Err(e) = tacos_bus::put(
                        &pace_session,
                        &pace_key,
                        &pace,
                        tacos_bus::Delivery::Command,
                    )
                    .await
                    {
                        warn!(error = %e, "simulator pace not sent");
                    }
                    // Wakes at a change, or to repeat the current pace; ends with the link.
                    if let Ok(Err(_)) = tokio::time::timeout(PACE_REPEAT, calls.changed()).await {
                        return;
                    }
                }
            }));
        }

        Ok(GroundLink {
            session,
            keys,
            clock,
            calls_in_flight: Arc::new(calls_in_flight),
            shared,
            next_seq: AtomicU64::new(epoch),
            epoch,
            tasks,
        })
    }

    /// This ground station's epoch (see `GroundHeartbeat::ground`).
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    pub fn keys(&self) -> &Keys {
        &self.keys
    }

    /// The ground's clock: the simulator's in a simulated run (`--sim-clock`), else the wall
    /// clock. Every mission timer (cycles, stuck plans, link ages) reads it.
    pub fn clock(&self) -> &Clock {
        &self.clock
    }

    /// Marks a model call in flight until the guard drops; a simulator then runs at real time.
    pub fn model_call(&self) -> ModelCallGuard {
        self.calls_in_flight.send_modify(|n| *n += 1);
        ModelCallGuard {
            calls_in_flight: self.calls_in_flight.clone(),
        }
    }

    /// A locked view of the swarm (hold it briefly).
    pub fn view(&self) -> MutexGuard<'_, SwarmView> {
        self.shared.lock()
    }

    pub fn changes(&self) -> broadcast::Receiver<SwarmChange> {
        self.shared.changes.subscribe()
    }

    /// Drones joining and leaving the swarm.
    pub fn membership(&self) -> broadcast::Receiver<SwarmChange> {
        self.shared.membership.subscribe()
    }

    /// Stops (false) or resumes (true) the ground heartbeat, as a ground station that dies or
    /// loses its network would: the drones' ground-silence failsafe is tested with it.
    pub fn set_heartbeat(&self, on: bool) {
        self.shared.heartbeat_on.store(on, Ordering::Relaxed);
    }

    pub fn malformed_status_count(&self) -> u64 {
        self.shared.malformed_status.load(Ordering::Relaxed)
    }

    /// Sends a checked action; returns its sequence number.
    pub async fn send(
        &self,
        checked: &CheckedAction,
        task_id: Option<String>,
    ) -> Result<u64, LinkError> {
        let seq = self.next_seq.fetch_add(1, Ordering::Relaxed);
        let command = ActionCommand {
            ground: self.epoch,
            seq,
            sent_at: self.clock.now(),
            task_id,
            action: checked.action().clone(),
        };
        tacos_bus::put(
            &self.session,
            &self.keys.action(checked.drone()),
            &command,
            tacos_bus::Delivery::Command,
        )
        .await?;
        Ok(seq)
    }

    /// Asks the simulator to inject a fault on one vehicle (`sim/faults`; simulation only: a
    /// real swarm has no simulator listening).
    pub async fn inject_fault(&self, drone: &DroneId, fault: FaultKind) -> Result<(), LinkError> {
        let request = FaultRequest {
            drone: drone.clone(),
            fault,
        };
        tacos_bus::put(
            &self.session,
            &self.keys.sim_faults(),
            &request,
            tacos_bus::Delivery::Command,
        )
        .await?;
        Ok(())
    }

    /// Waits until every drone in `ids` is alive and satisfies `ready`.
    pub async fn wait_for_drones(
        &self,
        ids: &[DroneId],
        timeout: Duration,
        ready: impl Fn(&DroneStatus) -> bool,
    ) -> Result<(), LinkError> {
        let mut version = self.shared.version.subscribe();
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            let missing: Vec<String> = {
                let view = self.view();
                ids.iter()
                    .filter(|id| {
                        !view
                            .get(id)
                            .is_some_and(|e| e.alive && e.status.as_ref().is_some_and(&ready))
                    })
                    .map(|id| id.to_string())
                    .collect()
            };
            if missing.is_empty() {
                return Ok(());
            }
            match tokio::time::timeout_at(deadline, version.changed()).await {
                Ok(Ok(())) => {}
                _ => return Err(LinkError::WaitDrones(timeout, missing.join(", "))),
            }
        }
    }

    /// Waits for the outcome of action `seq` on `drone`.
    pub async fn wait_outcome(
        &self,
        drone: &DroneId,
        seq: u64,
        timeout: Duration,
    ) -> Result<ActionState, LinkError> {
        let mut version = self.shared.version.subscribe();
        let deadline = tokio::time::Instant::now() + timeout;
        // Statuses sent before the drone read the action may still name a ground it is about
        // to give up: only one two statuses later tells which it follows.
        let counter_at_send = self
            .view()
            .get(drone)
            .and_then(|e| e.status.as_ref())
            .map_or(0, |s| s.counter);
        loop {
            {
                let view = self.view();
                let entry = view.get(drone);
                if entry.is_some_and(|e| !e.alive) {
                    return Err(LinkError::DroneLost(drone.clone()));
                }
                let status = entry.and_then(|e| e.status.as_ref());
                // The ground this drone follows, when it is another one.
                let other = status.and_then(|s| s.ground).filter(|g| *g != self.epoch);
                if let (Some(s), Some(followed)) = (status, other)
                    && s.counter >= counter_at_send + 2
                {
                    return Err(LinkError::NotFollowed {
                        drone: drone.clone(),
                        followed,
                    });
                }
                if let Some(refused) = status.and_then(|s| s.refused.as_ref())
                    && refused.seq == seq
                {
                    return Err(LinkError::Refused {
                        drone: drone.clone(),
                        seq,
                        why: refused.why,
                    });
                }
                if let Some(progress) = status.and_then(|s| s.action.as_ref()) {
                    if progress.seq == seq && progress.state.is_finished() {
                        return Ok(progress.state.clone());
                    }
                    if progress.seq > seq {
                        // A newer action of another ground station is not ours superseded:
                        // the drone follows that one.
                        return Err(match other {
                            Some(followed) => LinkError::NotFollowed {
                                drone: drone.clone(),
                                followed,
                            },
                            None => LinkError::Superseded {
                                drone: drone.clone(),
                                seq,
                                newer: progress.seq,
                            },
                        });
                    }
                }
            }
            match tokio::time::timeout_at(deadline, version.changed()).await {
                Ok(Ok(())) => {}
                _ => {
                    return Err(LinkError::Timeout {
                        drone: drone.clone(),
                        seq,
                        waited: timeout,
                    });
                }
            }
        }
    }

    /// Follows the simulator's ground truth (`sim/truth`), newest first.
    pub async fn watch_truth(&self) -> Result<watch::Receiver<Option<SimTruth>>, LinkError> {
        let sub = tacos_bus::subscribe(&self.session, &self.keys.sim_truth()).await?;
        let (tx, rx) = watch::channel(None);
        tokio::spawn(async move {
            while let Ok(sample) = sub.recv_async().await {
                match tacos_bus::decode::<SimTruth>(&sample) {
                    Ok(truth) => {
                        if tx.send(Some(truth)).is_err() {
                            break;
                        }
                    }
                    Err(e) => warn!(error = %e, "malformed sim truth ignored"),
                }
            }
        });
        Ok(rx)
    }

    /// Follows `world/targets`: the newest observation of every visible target.
    pub async fn watch_targets(
        &self,
    ) -> Result<watch::Receiver<Vec<TargetObservation>>, LinkError> {
        let sub = tacos_bus::subscribe(&self.session, &self.keys.targets()).await?;
        let (tx, rx) = watch::channel(Vec::new());
        tokio::spawn(async move {
            while let Ok(sample) = sub.recv_async().await {
                match tacos_bus::decode::<TargetsMessage>(&sample) {
                    Ok(message) => {
                        if tx.send(message.targets).is_err() {
                            break;
                        }
                    }
                    Err(e) => warn!(error = %e, "malformed targets message ignored"),
                }
            }
        });
        Ok(rx)
    }

    /// Follows `world/events`.
    pub async fn watch_events(&self) -> Result<tokio::sync::mpsc::Receiver<WorldEvent>, LinkError> {
        let sub = tacos_bus::subscribe(&self.session, &self.keys.events()).await?;
        let (tx, rx) = tokio::sync::mpsc::channel(256);
        tokio::spawn(async move {
            while let Ok(sample) = sub.recv_async().await {
                match tacos_bus::decode::<WorldEvent>(&sample) {
                    Ok(event) => {
                        if tx.send(event).await.is_err() {
                            break;
                        }
                    }
                    Err(e) => warn!(error = %e, "malformed world event ignored"),
                }
            }
        });
        Ok(rx)
    }
}

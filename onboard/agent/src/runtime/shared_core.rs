//! What zenoh's receiving thread and the loop task share: the executor and the ground side.
//!
//! Actions and ground heartbeats are acted on in zenoh's subscriber callbacks, the moment they
//! arrive, instead of being queued for the loop task: handing a sample from zenoh's thread to a
//! task costs as much as zenoh's whole delivery (20-35 µs on the 2-core machines, README
//! "Benchmarks"), and a `land` should not wait for it. The loop locks the same core for its
//! control ticks; every lock is short and never held across an `.await`. The callbacks only
//! ask the loop to publish the status.

use super::ground_side::GroundSide;
use crate::executor::Executor;
use std::sync::{Arc, Mutex, MutexGuard};
use tacos_bus::clock::Clock;
use tacos_bus::{BusError, subscribe_with};
use tacos_shared::codec::CodecError;
use tacos_shared::keys::Keys;
use tokio::sync::Notify;
use zenoh::Session;
use zenoh::pubsub::Subscriber;

pub(super) struct Core {
    pub executor: Executor,
    pub ground: GroundSide,
}

/// A panic while the core was held (in a callback or a tick) may have left it half-changed:
/// the onboard stops rather than fly on it (the writer, without setpoints, then holds the
/// vehicle where it is and lands it after 15 s: `tacos-px4`'s `orphan`).
#[derive(Debug, thiserror::Error)]
#[error("the executor was left half-changed by a panic")]
pub struct CorePoisoned;

pub(super) struct SharedCore {
    core: Mutex<Core>,
    /// Set by a callback whose message the status should tell at once.
    status_due: Notify,
}

impl SharedCore {
    pub fn new(core: Core) -> Arc<Self> {
        Arc::new(SharedCore {
            core: Mutex::new(core),
            status_due: Notify::new(),
        })
    }

    pub fn lock(&self) -> Result<MutexGuard<'_, Core>, CorePoisoned> {
        self.core.lock().map_err(|_| CorePoisoned)
    }

    /// Completes when a callback has asked for the status since the last time it completed.
    pub async fn status_due(&self) {
        self.status_due.notified().await
    }

    fn ask_status(&self) {
        self.status_due.notify_one();
    }
}

/// The subscribers whose callbacks act on the core; they stop when this is dropped.
pub(super) struct GroundSubscribers {
    _actions: Subscriber<()>,
    _heartbeats: Subscriber<()>,
}

/// Declares the subscribers of `drone`'s actions and of the ground heartbeats, each taken in on
/// zenoh's thread by `core` at `clock`'s time.
pub(super) async fn take_ground_messages(
    session: &Session,
    keys: &Keys,
    drone: &tacos_shared::DroneId,
    core: &Arc<SharedCore>,
    clock: &Clock,
) -> Result<GroundSubscribers, BusError> {
    let actions = subscribe_with(
        session,
        &keys.action(drone),
        taking(core, clock, GroundSide::on_action),
    )
    .await?;
    let heartbeats = subscribe_with(
        session,
        &keys.ground_heartbeat(),
        taking(core, clock, GroundSide::on_heartbeat),
    )
    .await?;
    Ok(GroundSubscribers {
        _actions: actions,
        _heartbeats: heartbeats,
    })
}

/// What the ground side does with one message of a kind: true when the status should go out.
type Take<T> = fn(&mut GroundSide, Result<T, CodecError>, &mut Executor, f64) -> bool;

/// A callback that takes each message in with `take` under the core's lock. One that finds the
/// core poisoned drops its message: the loop stops at its next lock.
fn taking<T: 'static>(
    core: &Arc<SharedCore>,
    clock: &Clock,
    take: Take<T>,
) -> impl Fn(Result<T, CodecError>) + Send + Sync + 'static {
    // Callbacks run on zenoh's threads, outside the drone's span: they enter it themselves.
    let (core, clock, span) = (core.clone(), clock.clone(), tracing::Span::current());
    move |message| {
        let _entered = span.enter();
        let Ok(mut held) = core.lock() else { return };
        let Core { executor, ground } = &mut *held;
        let due = take(ground, message, executor, clock.now());
        drop(held);
        if due {
            core.ask_status();
        }
    }
}

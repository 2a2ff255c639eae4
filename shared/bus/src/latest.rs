//! [`Latest`]: the newest values of a stream where only recent samples matter (neighbours'
//! paths, targets, the simulator's clock and pace), decoded on zenoh's receiving thread.
//!
//! Why not zenoh's own `RingChannel` of samples: a sample's payload is a slice of the buffer
//! zenoh read it into, and a buffer still referenced is not recycled. Samples waiting in a ring
//! for the reader (a control tick takes the neighbours' paths every 20 ms) each kept a 64 KiB
//! receive buffer alive, so nearly every read from the link allocated and zeroed a fresh one
//! (`memset`, `malloc`, `madvise` in `perf` of the 20-drone demo's onboards). Decoding in the
//! callback releases the buffer before zenoh reads the next batch.

use crate::BusError;
use serde::de::DeserializeOwned;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use tacos_shared::codec::CodecError;
use tokio::sync::Notify;
use zenoh::Session;

/// The subscriber's values are no longer delivered: its session closed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the subscriber closed")]
pub struct Closed;

/// The last `capacity` values decoded from a key (each a decoding error when the payload was
/// malformed), oldest first; older ones are dropped. Zenoh's receiving task never waits for
/// the reader, so a busy reader cannot stall the session. Undeclared when dropped.
pub struct Latest<T> {
    shared: Arc<Shared<T>>,
    _subscriber: zenoh::pubsub::Subscriber<()>,
}

struct Shared<T> {
    queue: Mutex<VecDeque<Result<T, CodecError>>>,
    capacity: usize,
    closed: AtomicBool,
    arrived: Notify,
}

impl<T> Shared<T> {
    fn queue(&self) -> MutexGuard<'_, VecDeque<Result<T, CodecError>>> {
        // Nothing panics while holding it; a poisoned queue still holds whole values.
        self.queue.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn push(&self, value: Result<T, CodecError>) {
        {
            let mut queue = self.queue();
            if queue.len() == self.capacity {
                queue.pop_front();
            }
            queue.push_back(value);
        }
        self.arrived.notify_one();
    }
}

/// Owned by zenoh's callback: when zenoh drops the callback (the subscriber undeclared, the
/// session closed), the reader is told.
struct CloseOnDrop<T>(Arc<Shared<T>>);

impl<T> Drop for CloseOnDrop<T> {
    fn drop(&mut self) {
        self.0.closed.store(true, Ordering::Release);
        self.0.arrived.notify_one();
    }
}

/// Declares a [`Latest`] subscriber of `key` keeping the last `capacity` values (at least one).
pub async fn subscribe_latest<T>(
    session: &Session,
    key: &str,
    capacity: usize,
) -> Result<Latest<T>, BusError>
where
    T: DeserializeOwned + Send + 'static,
{
    let shared = Arc::new(Shared {
        queue: Mutex::new(VecDeque::new()),
        capacity: capacity.max(1),
        closed: AtomicBool::new(false),
        arrived: Notify::new(),
    });
    let guard = CloseOnDrop(shared.clone());
    let subscriber = crate::subscribe_with(session, key, move |value| guard.0.push(value)).await?;
    Ok(Latest {
        shared,
        _subscriber: subscriber,
    })
}

impl<T> Latest<T> {
    /// The oldest value kept, if any, without waiting.
    pub fn try_recv(&self) -> Result<Option<Result<T, CodecError>>, Closed> {
        // Read before the queue: once closed, no value is pushed any more, so an empty queue
        // then is empty for good (read after, a last value pushed in between would be lost).
        let closed = self.shared.closed.load(Ordering::Acquire);
        if let Some(value) = self.shared.queue().pop_front() {
            return Ok(Some(value));
        }
        if closed {
            return Err(Closed);
        }
        Ok(None)
    }

    /// The oldest value kept, waiting for one. Cancel-safe: a value is taken only when
    /// returned.
    pub async fn recv_async(&self) -> Result<Result<T, CodecError>, Closed> {
        loop {
            if let Some(value) = self.try_recv()? {
                return Ok(value);
            }
            // `notify_one` keeps a permit when nobody waits: a value pushed between the check
            // above and this wait is not missed.
            self.shared.arrived.notified().await;
        }
    }
}

impl<T> std::fmt::Debug for Latest<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Latest")
            .field("queued", &self.shared.queue().len())
            .field("capacity", &self.shared.capacity)
            .field("closed", &self.shared.closed.load(Ordering::Relaxed))
            .finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tests::{pair, put_one_malformed_between, until_matched};
    use crate::{Delivery, put};
    use std::time::Duration;

    #[test]
    fn the_oldest_value_is_dropped_beyond_the_capacity() {
        let shared = Shared {
            queue: Mutex::new(VecDeque::new()),
            capacity: 2,
            closed: AtomicBool::new(false),
            arrived: Notify::new(),
        };
        for v in 1..=3u64 {
            shared.push(Ok(v));
        }
        assert_eq!(
            shared.queue().iter().cloned().collect::<Vec<_>>(),
            [Ok(2), Ok(3)]
        );
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn values_come_decoded_in_order_a_malformed_one_as_its_error_then_closed() {
        let (publisher_side, subscriber_side) = pair().await;
        let key = "tacos/bus-test/latest";
        let latest = subscribe_latest::<u64>(&subscriber_side, key, 8)
            .await
            .expect("declared");
        assert_eq!(latest.try_recv(), Ok(None), "nothing yet, not closed");
        until_matched(&publisher_side, key).await;
        put_one_malformed_between(&publisher_side, key).await;
        let mut heard = Vec::new();
        for _ in 0..3 {
            let value = tokio::time::timeout(Duration::from_secs(10), latest.recv_async())
                .await
                .expect("heard within 10 s")
                .expect("open");
            heard.push(value);
        }
        assert_eq!(heard[0], Ok(1));
        assert!(
            matches!(heard[1], Err(CodecError::Truncated)),
            "{:?}",
            heard[1]
        );
        assert_eq!(heard[2], Ok(3));

        // The session closed: a value still queued is handed out, then `Closed`, at once.
        put(&subscriber_side, key, &4u64, Delivery::Telemetry)
            .await
            .expect("put");
        subscriber_side.close().await.expect("closed");
        assert_eq!(latest.try_recv(), Ok(Some(Ok(4))));
        let closed = tokio::time::timeout(Duration::from_secs(10), latest.recv_async())
            .await
            .expect("told within 10 s");
        assert_eq!(closed, Err(Closed));
    }
}

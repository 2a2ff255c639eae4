//! The clock every timer of a TACOS process reads: the wall clock on a real drone, or the
//! simulator's clock (`sim/clock`) in a simulated run, which may go faster than real time.
//!
//! Time is in seconds on the Unix scale either way, so stamps carried between processes (paths)
//! compare across them. The simulator's clock is an anchor (`SimClock`: simulated time, the
//! wall time it was taken, the rate) that each process extrapolates from its own wall clock;
//! the processes of a simulated run share one machine, hence one wall clock.

use crate::BusError;
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tacos_shared::keys::Keys;
use tacos_shared::messages::SimClock;
use tracing::warn;
use zenoh::Session;

/// The longest a clock wait sleeps at once: a change of rate (a model call starting) takes
/// effect within this much wall time.
const MAX_WAIT: Duration = Duration::from_millis(20);

/// The wall clock in seconds since the Unix epoch.
pub fn wall_unix() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Anchor {
    sim_unix_s: f64,
    wall_unix_s: f64,
    rate: f64,
}

impl Anchor {
    fn from_message(m: &SimClock) -> Option<Anchor> {
        (m.sim_unix_s.is_finite()
            && m.wall_unix_s.is_finite()
            && m.rate.is_finite()
            && m.rate > 0.0)
            .then_some(Anchor {
                sim_unix_s: m.sim_unix_s,
                wall_unix_s: m.wall_unix_s,
                rate: m.rate,
            })
    }

    fn at(&self, wall_unix_s: f64) -> f64 {
        self.sim_unix_s + self.rate * (wall_unix_s - self.wall_unix_s)
    }
}

#[derive(Debug)]
struct Followed {
    anchor: Anchor,
    /// The latest time handed out: the clock never goes back, even when a new anchor says the
    /// simulation lagged behind the last extrapolation (a loaded machine).
    last: f64,
}

impl Followed {
    fn now(&mut self, wall_unix_s: f64) -> f64 {
        self.last = self.last.max(self.anchor.at(wall_unix_s));
        self.last
    }

    fn update(&mut self, anchor: Anchor) {
        self.anchor = anchor;
    }
}

/// No anchor from the simulator within the wait.
#[derive(Debug, Clone, Copy, thiserror::Error)]
#[error("no simulator clock within {waited_s} s: is tacos-sitl running on this swarm?")]
pub struct ClockNotSynced {
    pub waited_s: f64,
}

#[derive(Debug)]
struct Shared {
    followed: Mutex<Followed>,
    /// Set once the first anchor arrived.
    synced: tokio::sync::watch::Sender<bool>,
    /// Aborted with the last clone of the clock.
    follower: Mutex<Option<tokio::task::JoinHandle<()>>>,
}

impl Drop for Shared {
    fn drop(&mut self) {
        if let Some(task) = self.follower.get_mut().ok().and_then(Option::take) {
            task.abort();
        }
    }
}

#[derive(Debug, Clone)]
enum Source {
    /// The wall clock, read through `Instant` so that it never steps (an NTP correction).
    Wall {
        unix_at: f64,
        at: Instant,
    },
    Sim(Arc<Shared>),
}

/// A clock: cheap to clone, every clone reads the same time.
#[derive(Debug, Clone)]
pub struct Clock {
    source: Source,
    /// For `instant`: this clock's time at `origin`.
    origin_s: f64,
    origin: Instant,
}

impl Clock {
    /// The wall clock.
    pub fn wall() -> Clock {
        let (unix_at, at) = (wall_unix(), Instant::now());
        Clock {
            source: Source::Wall { unix_at, at },
            origin_s: unix_at,
            origin: at,
        }
    }

    /// Follows the simulator's clock on `sim/clock`. Until the simulator's first anchor arrives
    /// it reads the wall clock (see [`Clock::synced`]).
    pub async fn follow(session: &Session, keys: &Keys) -> Result<Clock, BusError> {
        let key = keys.sim_clock();
        let subscriber = crate::subscribe_latest::<SimClock>(session, &key, 4).await?;
        let wall = wall_unix();
        let (synced, _) = tokio::sync::watch::channel(false);
        let shared = Arc::new(Shared {
            followed: Mutex::new(Followed {
                anchor: Anchor {
                    sim_unix_s: wall,
                    wall_unix_s: wall,
                    rate: 1.0,
                },
                last: f64::NEG_INFINITY,
            }),
            synced,
            follower: Mutex::new(None),
        });
        let weak: Weak<Shared> = Arc::downgrade(&shared);
        let task = tokio::spawn(async move {
            let mut malformed = 0u64;
            while let Ok(message) = subscriber.recv_async().await {
                let Some(shared) = weak.upgrade() else { return };
                match message.ok().and_then(|m| Anchor::from_message(&m)) {
                    Some(anchor) => {
                        lock(&shared.followed).update(anchor);
                        shared
                            .synced
                            .send_if_modified(|s| !std::mem::replace(s, true));
                    }
                    None => {
                        malformed += 1;
                        if malformed.is_power_of_two() {
                            warn!(%key, count = malformed, "malformed simulator clock ignored");
                        }
                    }
                }
            }
            warn!("the simulator clock's subscriber closed: the clock runs on at its last rate");
        });
        *lock(&shared.follower) = Some(task);
        let mut clock = Clock {
            source: Source::Sim(shared),
            origin_s: 0.0,
            origin: Instant::now(),
        };
        clock.origin_s = clock.now();
        Ok(clock)
    }

    /// Waits up to `within` until a simulated clock has heard the simulator (at once for the
    /// wall clock), so that a process does not start its timers on one clock and jump to another.
    pub async fn synced(&self, within: Duration) -> Result<(), ClockNotSynced> {
        let Source::Sim(shared) = &self.source else {
            return Ok(());
        };
        let mut synced = shared.synced.subscribe();
        match tokio::time::timeout(within, synced.wait_for(|s| *s)).await {
            Ok(Ok(_)) => Ok(()),
            _ => Err(ClockNotSynced {
                waited_s: within.as_secs_f64(),
            }),
        }
    }

    /// The time in seconds on the Unix scale; never goes back.
    pub fn now(&self) -> f64 {
        match &self.source {
            Source::Wall { unix_at, at } => unix_at + at.elapsed().as_secs_f64(),
            Source::Sim(shared) => lock(&shared.followed).now(wall_unix()),
        }
    }

    /// Seconds of this clock per wall second now.
    pub fn rate(&self) -> f64 {
        match &self.source {
            Source::Wall { .. } => 1.0,
            Source::Sim(shared) => lock(&shared.followed).anchor.rate,
        }
    }

    /// True when this clock follows the simulator.
    pub fn is_simulated(&self) -> bool {
        matches!(self.source, Source::Sim(_))
    }

    /// This clock's time as an `Instant`, for code that measures durations with `Instant`s:
    /// instants from one clock (or its clones) differ by this clock's seconds.
    pub fn instant(&self) -> Instant {
        let since = (self.now() - self.origin_s).max(0.0);
        self.origin + Duration::from_secs_f64(since)
    }

    /// Returns once this clock reads `at` or later.
    pub async fn sleep_until(&self, at: f64) {
        loop {
            let left = at - self.now();
            if left <= 0.0 {
                return;
            }
            tokio::time::sleep(wall_wait(left, self.rate())).await;
        }
    }

    /// Returns after `seconds` of this clock.
    pub async fn sleep(&self, seconds: f64) {
        self.sleep_until(self.now() + seconds).await;
    }

    /// A ticker every `period_s` of this clock; the first tick is at once, missed ticks are
    /// skipped (like `tokio::time::MissedTickBehavior::Skip`).
    pub fn ticker(&self, period_s: f64) -> Ticker {
        Ticker {
            clock: self.clone(),
            period_s: period_s.max(1e-4),
            next: self.now(),
        }
    }
}

/// The wall time to sleep for `left` seconds of a clock at `rate`, at most `MAX_WAIT`.
fn wall_wait(left: f64, rate: f64) -> Duration {
    let wall = left / rate.max(1e-3);
    Duration::from_secs_f64(wall.clamp(0.0, MAX_WAIT.as_secs_f64()))
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic while holding the lock leaves plain numbers behind: still usable.
    mutex
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// See [`Clock::ticker`].
#[derive(Debug)]
pub struct Ticker {
    clock: Clock,
    period_s: f64,
    next: f64,
}

impl Ticker {
    /// Waits for the next tick and returns the clock's time. Cancel-safe: a tick is consumed
    /// only when this returns.
    pub async fn tick(&mut self) -> f64 {
        loop {
            let now = self.clock.now();
            if now >= self.next {
                self.next += self.period_s;
                if self.next <= now {
                    self.next = now + self.period_s;
                }
                return now;
            }
            tokio::time::sleep(wall_wait(self.next - now, self.clock.rate())).await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn followed(sim: f64, wall: f64, rate: f64) -> Followed {
        Followed {
            anchor: Anchor {
                sim_unix_s: sim,
                wall_unix_s: wall,
                rate,
            },
            last: f64::NEG_INFINITY,
        }
    }

    #[test]
    fn extrapolates_from_the_anchor_at_its_rate() {
        let mut f = followed(1000.0, 500.0, 4.0);
        assert_eq!(f.now(500.0), 1000.0);
        assert_eq!(f.now(502.5), 1010.0);
    }

    #[test]
    fn never_goes_back_when_a_new_anchor_says_the_simulation_lagged() {
        let mut f = followed(1000.0, 500.0, 4.0);
        assert_eq!(f.now(501.0), 1004.0);
        // The simulator only got to 1002 by wall 501 (a stall), now at real time.
        f.update(Anchor {
            sim_unix_s: 1002.0,
            wall_unix_s: 501.0,
            rate: 1.0,
        });
        assert_eq!(f.now(501.5), 1004.0, "held, not stepped back");
        assert_eq!(f.now(503.0), 1004.0);
        assert_eq!(f.now(503.5), 1004.5, "runs on once the anchor catches up");
    }

    #[test]
    fn anchors_that_cannot_be_followed_are_refused() {
        let m = |rate: f64, sim: f64| SimClock {
            sim_unix_s: sim,
            wall_unix_s: 1.0,
            rate,
        };
        assert!(Anchor::from_message(&m(1.0, 5.0)).is_some());
        assert!(Anchor::from_message(&m(0.0, 5.0)).is_none());
        assert!(Anchor::from_message(&m(-2.0, 5.0)).is_none());
        assert!(Anchor::from_message(&m(f64::NAN, 5.0)).is_none());
        assert!(Anchor::from_message(&m(1.0, f64::INFINITY)).is_none());
    }

    #[test]
    fn a_wait_is_scaled_by_the_rate_and_bounded() {
        assert_eq!(wall_wait(0.008, 4.0), Duration::from_millis(2));
        assert_eq!(wall_wait(10.0, 1.0), MAX_WAIT);
        assert_eq!(wall_wait(-1.0, 1.0), Duration::ZERO);
    }

    #[tokio::test]
    async fn the_wall_clock_ticks_at_its_period_and_instants_follow_it() {
        let clock = Clock::wall();
        let mut ticker = clock.ticker(0.01);
        let first = ticker.tick().await;
        for k in 1..=5 {
            let t = ticker.tick().await;
            // A late tick is not made up for, but none comes early.
            assert!(
                t - first >= 0.01 * k as f64 - 1e-6,
                "tick {k} at {t}, first at {first}"
            );
        }
        // Instants differ by the clock's seconds: each read lies between two of the clock's.
        let read = || {
            let before = clock.now();
            let at = clock.instant();
            (before, at, clock.now())
        };
        let (a0, a, a1) = read();
        clock.sleep(0.02).await;
        let (b0, b, b1) = read();
        let by_instant = b.duration_since(a).as_secs_f64();
        assert!(by_instant >= b0 - a1 - 1e-6 && by_instant <= b1 - a0 + 1e-6);
        assert!(b0 - a1 >= 0.0199 - 1e-6, "slept {} s", b0 - a1);
    }
}

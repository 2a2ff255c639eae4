//! The core of `tacos-latency`, a pinger and a ponger (like zenoh's `z_ping` / `z_pong`) over any
//! network a [`crate::BusArgs`] describes: TCP on loopback, QUIC with mutual TLS through the
//! swarm's router, one host or two. A round trip carries TACOS's real messages, an
//! `ActionCommand` out and a `DroneStatus` back, encoded by the wire codec and sent with the QoS
//! the binaries give them (`crate::put`: `Delivery::Command` for the command, `Telemetry` for the status); beside
//! it, on the same sessions, as many bytes go out and back as bare zenoh puts. The two figures
//! differ only by what TACOS adds. The keys are `bench/<drone>/{ping,pong}/{tacos,bare}` of the
//! swarm, which no TACOS process reads: a ponger in a drone's name never meets its onboard.

use crate::BusError;
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tacos_shared::action::{Action, ActionCommand};
use tacos_shared::codec;
use tacos_shared::keys::Keys;
use tacos_shared::messages::{ActionProgress, DroneStatus};
use tacos_shared::{DroneId, DroneMode, Vec3};
use zenoh::Session;

/// What a round trip carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Carrier {
    /// An `ActionCommand` out and a `DroneStatus` back, through `tacos_bus`.
    Tacos,
    /// The same numbers of bytes as bare zenoh puts.
    Bare,
}

impl Carrier {
    pub fn as_str(self) -> &'static str {
        match self {
            Carrier::Tacos => "tacos",
            Carrier::Bare => "bare",
        }
    }
}

/// The probe's keys for one drone slot.
pub struct ProbeKeys {
    prefix: String,
}

impl ProbeKeys {
    pub fn new(keys: &Keys, drone: &DroneId) -> Self {
        ProbeKeys {
            prefix: format!("{}/bench/{drone}", keys.prefix()),
        }
    }

    pub fn ping(&self, carrier: Carrier) -> String {
        format!("{}/ping/{}", self.prefix, carrier.as_str())
    }

    pub fn pong(&self, carrier: Carrier) -> String {
        format!("{}/pong/{}", self.prefix, carrier.as_str())
    }
}

/// Out: a real action, numbered and stamped.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Ping {
    pub seq: u64,
    /// Wall clock, µs since the epoch: one-way times compare the two hosts' clocks.
    pub sent_us: u64,
    pub command: ActionCommand,
}

/// Back: a real status, with when the ping arrived.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Pong {
    pub seq: u64,
    pub ping_sent_us: u64,
    pub received_us: u64,
    pub status: DroneStatus,
}

fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

fn ping_message(seq: u64, drone: &DroneId) -> Ping {
    let sent_us = now_us();
    Ping {
        seq,
        sent_us,
        command: ActionCommand {
            ground: 1,
            seq,
            sent_at: sent_us as f64 / 1e6,
            task_id: Some(format!("bench-{drone}")),
            action: Action::Goto {
                target: Vec3::new(12.5, -40.0, 10.0),
            },
        },
    }
}

fn pong_message(ping: &Ping, received_us: u64, drone: &DroneId) -> Pong {
    Pong {
        seq: ping.seq,
        ping_sent_us: ping.sent_us,
        received_us,
        status: DroneStatus {
            drone: drone.clone(),
            counter: ping.seq,
            mode: DroneMode::Flying,
            armed: true,
            position: Vec3::new(12.0, -39.5, 9.8),
            velocity: Vec3::new(0.4, -0.2, 0.0),
            autopilot_link: true,
            action: Some(ActionProgress::started(&ping.command)),
            failsafe: None,
            peers_silent: false,
            malformed_actions: 0,
            ground: Some(ping.command.ground),
            refused: None,
            autopilot_took_over: None,
        },
    }
}

/// A bare probe: seq, sent, received (little-endian u64s), zero-padded to `len` bytes.
fn bare_bytes(seq: u64, sent_us: u64, received_us: u64, len: usize) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(len.max(24));
    for n in [seq, sent_us, received_us] {
        bytes.extend_from_slice(&n.to_le_bytes());
    }
    bytes.resize(len.max(24), 0);
    bytes
}

fn bare_fields(bytes: &[u8]) -> Option<(u64, u64, u64)> {
    let n = |i: usize| -> Option<u64> {
        Some(u64::from_le_bytes(bytes.get(i..i + 8)?.try_into().ok()?))
    };
    Some((n(0)?, n(8)?, n(16)?))
}

/// The encoded sizes of a probe's ping and pong: the bare probes use the same.
pub fn probe_sizes(drone: &DroneId) -> Result<(usize, usize), BusError> {
    let ping = ping_message(u64::MAX / 3, drone);
    let pong = pong_message(&ping, now_us(), drone);
    Ok((codec::encode(&ping)?.len(), codec::encode(&pong)?.len()))
}

/// Answers every ping of `drone`'s slot, both carriers, until `stop` completes; returns how many
/// it answered. A malformed ping is counted and skipped.
pub async fn pong(
    session: &Session,
    keys: &ProbeKeys,
    drone: &DroneId,
    stop: impl std::future::Future<Output = ()>,
) -> Result<PongCount, BusError> {
    let tacos = crate::subscribe(session, &keys.ping(Carrier::Tacos)).await?;
    let bare = crate::subscribe(session, &keys.ping(Carrier::Bare)).await?;
    let (_, pong_len) = probe_sizes(drone)?;
    let mut count = PongCount::default();
    tokio::pin!(stop);
    loop {
        tokio::select! {
            () = &mut stop => return Ok(count),
            sample = tacos.recv_async() => {
                let Ok(sample) = sample else { return Ok(count) };
                let received = now_us();
                match crate::decode::<Ping>(&sample) {
                    Ok(ping) => {
                        let reply = pong_message(&ping, received, drone);
                        crate::put(session, &keys.pong(Carrier::Tacos), &reply, crate::Delivery::Telemetry).await?;
                        count.answered += 1;
                    }
                    Err(_) => count.malformed += 1,
                }
            }
            sample = bare.recv_async() => {
                let Ok(sample) = sample else { return Ok(count) };
                let received = now_us();
                match bare_fields(&sample.payload().to_bytes()) {
                    Some((seq, sent, _)) => {
                        let reply = bare_bytes(seq, sent, received, pong_len);
                        session
                            .put(keys.pong(Carrier::Bare), reply)
                            .await
                            .map_err(|e| BusError::Put { key: keys.pong(Carrier::Bare), reason: e.to_string() })?;
                        count.answered += 1;
                    }
                    None => count.malformed += 1,
                }
            }
        }
    }
}

#[derive(Debug, Default, Clone, Copy)]
pub struct PongCount {
    pub answered: u64,
    pub malformed: u64,
}

/// p50, p99 and max of a series, µs.
#[derive(Debug, Clone, Copy)]
pub struct Spread {
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
}

impl Spread {
    /// `None` for an empty series.
    pub fn of(mut samples: Vec<f64>) -> Option<Spread> {
        if samples.is_empty() {
            return None;
        }
        samples.sort_by(f64::total_cmp);
        let at = |p: f64| samples[((samples.len() - 1) as f64 * p).round() as usize];
        Some(Spread {
            p50: at(0.5),
            p99: at(0.99),
            max: samples[samples.len() - 1],
        })
    }
}

/// What one carrier measured.
#[derive(Debug, Clone, Copy)]
pub struct Figures {
    pub round_trip: Spread,
    /// Ping sent → received by the ponger, by the two hosts' wall clocks.
    pub out: Spread,
    /// Ponger received → pong back, by the two hosts' wall clocks.
    pub back: Spread,
    /// Round trips per second with `burst` pings in flight at once.
    pub per_second: f64,
    /// Pings never answered within the wait.
    pub lost: u64,
}

/// How a ping run goes.
#[derive(Debug, Clone, Copy)]
pub struct PingPlan {
    pub count: usize,
    pub warmup: usize,
    /// Pings in flight at once in the throughput phase.
    pub burst: usize,
    /// How long one pong is waited for before the ping counts as lost.
    pub wait: Duration,
}

#[derive(Debug, thiserror::Error)]
pub enum PingError {
    #[error(transparent)]
    Bus(#[from] BusError),
    #[error(
        "no ponger answered on {key} within {waited:?}: is `tacos-latency pong` running on this swarm and drone?"
    )]
    NoPonger { key: String, waited: Duration },
}

struct Pinger<'a> {
    session: &'a Session,
    keys: &'a ProbeKeys,
    drone: &'a DroneId,
    carrier: Carrier,
    ping_len: usize,
    pongs: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
}

/// One pong as read: its seq and the three stamps.
struct Heard {
    seq: u64,
    sent_us: u64,
    received_us: u64,
}

impl Pinger<'_> {
    async fn send(&self, seq: u64) -> Result<(), BusError> {
        let key = self.keys.ping(self.carrier);
        match self.carrier {
            Carrier::Tacos => {
                crate::put(
                    self.session,
                    &key,
                    &ping_message(seq, self.drone),
                    crate::Delivery::Command,
                )
                .await
            }
            Carrier::Bare => self
                .session
                .put(key.clone(), bare_bytes(seq, now_us(), 0, self.ping_len))
                .await
                .map_err(|e| BusError::Put {
                    key,
                    reason: e.to_string(),
                }),
        }
    }

    /// The next pong within `wait`, `None` when none came (a malformed one is skipped).
    async fn next(&self, wait: Duration) -> Option<Heard> {
        let deadline = tokio::time::Instant::now() + wait;
        loop {
            let sample = tokio::time::timeout_at(deadline, self.pongs.recv_async())
                .await
                .ok()?
                .ok()?;
            let heard =
                match self.carrier {
                    Carrier::Tacos => crate::decode::<Pong>(&sample).ok().map(|p| Heard {
                        seq: p.seq,
                        sent_us: p.ping_sent_us,
                        received_us: p.received_us,
                    }),
                    Carrier::Bare => bare_fields(&sample.payload().to_bytes()).map(
                        |(seq, sent_us, received_us)| Heard {
                            seq,
                            sent_us,
                            received_us,
                        },
                    ),
                };
            if heard.is_some() {
                return heard;
            }
        }
    }
}

/// Pings `drone`'s ponger with `carrier`: first until it answers (up to `find_within`), then
/// `plan.warmup + plan.count` round trips one at a time, then `plan.count` more with
/// `plan.burst` in flight for the throughput.
pub async fn ping(
    session: &Session,
    keys: &ProbeKeys,
    drone: &DroneId,
    carrier: Carrier,
    plan: PingPlan,
    find_within: Duration,
) -> Result<Figures, PingError> {
    let (ping_len, _) = probe_sizes(drone)?;
    let pongs = crate::subscribe(session, &keys.pong(carrier)).await?;
    let p = Pinger {
        session,
        keys,
        drone,
        carrier,
        ping_len,
        pongs,
    };
    // Seqs count up through the whole run: a late pong of an earlier phase is never mistaken.
    let mut seq = 1u64 << 40;
    let started = Instant::now();
    loop {
        p.send(seq).await?;
        if let Some(h) = p.next(Duration::from_millis(200)).await
            && h.seq == seq
        {
            break;
        }
        if started.elapsed() > find_within {
            return Err(PingError::NoPonger {
                key: keys.ping(carrier),
                waited: find_within,
            });
        }
        seq += 1;
    }
    let (mut rtt, mut out, mut back) = (Vec::new(), Vec::new(), Vec::new());
    let mut lost = 0;
    for i in 0..plan.warmup + plan.count {
        seq += 1;
        let t = Instant::now();
        p.send(seq).await?;
        let answer = loop {
            match p.next(plan.wait.saturating_sub(t.elapsed())).await {
                Some(h) if h.seq == seq => break Some(h),
                Some(_) => continue,
                None => break None,
            }
        };
        let Some(h) = answer else {
            lost += 1;
            continue;
        };
        let took = t.elapsed().as_secs_f64() * 1e6;
        if i >= plan.warmup {
            let back_us = now_us();
            rtt.push(took);
            out.push(h.received_us as f64 - h.sent_us as f64);
            back.push(back_us as f64 - h.received_us as f64);
        }
    }
    // Throughput: keep `burst` pings in flight until `count` have come back.
    let first = seq + 1;
    let last = first + plan.count as u64 - 1;
    let t = Instant::now();
    let mut next = first;
    let mut answered = 0usize;
    while next <= last && next < first + plan.burst.max(1) as u64 {
        p.send(next).await?;
        next += 1;
    }
    while answered < plan.count {
        match p.next(plan.wait).await {
            Some(h) if (first..=last).contains(&h.seq) => {
                answered += 1;
                if next <= last {
                    p.send(next).await?;
                    next += 1;
                }
            }
            Some(_) => {}
            None => break,
        }
    }
    let per_second = answered as f64 / t.elapsed().as_secs_f64().max(1e-9);
    lost += (plan.count - answered) as u64;
    let none = Spread {
        p50: f64::NAN,
        p99: f64::NAN,
        max: f64::NAN,
    };
    Ok(Figures {
        round_trip: Spread::of(rtt).unwrap_or(none),
        out: Spread::of(out).unwrap_or(none),
        back: Spread::of(back).unwrap_or(none),
        per_second,
        lost,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bare_probe_is_as_long_as_the_real_message_and_reads_back() {
        let drone = DroneId::new("alfa").expect("id");
        let (ping_len, pong_len) = probe_sizes(&drone).expect("sizes");
        assert!(
            ping_len > 24 && pong_len > ping_len,
            "{ping_len} {pong_len}"
        );
        let bytes = bare_bytes(7, 11, 13, ping_len);
        assert_eq!(bytes.len(), ping_len);
        assert_eq!(bare_fields(&bytes), Some((7, 11, 13)));
        assert_eq!(bare_fields(&bytes[..20]), None);
    }

    #[test]
    fn spreads_read_the_sorted_series() {
        let s = Spread::of((1..=100).map(f64::from).rev().collect()).expect("a spread");
        assert_eq!((s.p50, s.p99, s.max), (51.0, 99.0, 100.0));
        assert!(Spread::of(Vec::new()).is_none());
    }
}

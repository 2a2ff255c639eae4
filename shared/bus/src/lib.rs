//! The zenoh side of TACOS: opening a session from typed settings, and publishing / decoding
//! messages through the one wire codec. Kept apart from `tacos-shared`, which does no I/O.

pub mod clock;
pub mod latency;
mod latest;
pub mod router;

pub use latest::{Closed, Latest, subscribe_latest};

use serde::Serialize;
use serde::de::DeserializeOwned;
use std::path::PathBuf;
use std::time::Duration;
use tacos_shared::SwarmId;
use tacos_shared::codec::{self, CodecError};
use tacos_shared::keys::Keys;
use zenoh::Session;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::Sample;

#[derive(Debug, thiserror::Error)]
pub enum BusError {
    #[error("zenoh configuration {key}: {reason}")]
    Config { key: String, reason: String },
    #[error("could not open the zenoh session: {0}")]
    Open(String),
    #[error("zenoh {what} on {key}: {reason}")]
    Declare {
        what: &'static str,
        key: String,
        reason: String,
    },
    #[error("zenoh put on {key}: {reason}")]
    Put { key: String, reason: String },
    #[error(transparent)]
    Codec(#[from] CodecError),
    #[error(transparent)]
    NoClock(#[from] clock::ClockNotSynced),
}

/// How this process joins the swarm's zenoh network. Shared by every TACOS binary.
#[derive(Debug, Clone, clap::Args)]
pub struct BusArgs {
    /// The swarm's name: every key starts with `tacos/<swarm>/`.
    #[arg(long, default_value = "default", env = "TACOS_SWARM")]
    pub swarm: SwarmId,
    /// Endpoints to connect to (e.g. `tcp/192.168.1.10:7447`), repeatable.
    #[arg(long = "zenoh-connect", value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// Endpoints to listen on (e.g. `tcp/0.0.0.0:7447`), repeatable.
    #[arg(long = "zenoh-listen", value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// Join as a client of a zenohd router instead of as a peer.
    #[arg(long = "zenoh-client")]
    pub client: bool,
    /// Discover peers by UDP multicast on the LAN (off by default: set endpoints instead).
    #[arg(long = "zenoh-multicast")]
    pub multicast: bool,
    /// A zenoh JSON5 configuration file (mode, endpoints, TLS, access control; see
    /// deploy/zenoh/). It replaces the other --zenoh-* flags, which are refused beside it.
    #[arg(long = "zenoh-config", value_name = "FILE")]
    pub config_file: Option<PathBuf>,
    /// Follow the simulator's clock (`sim/clock`) instead of the wall clock. Only for the
    /// processes of a simulated run: the simulation may then run faster than real time.
    #[arg(long = "sim-clock")]
    pub sim_clock: bool,
}

impl BusArgs {
    /// Settings for a process on loopback that connects to `connect` (tests, the demo).
    pub fn loopback(swarm: SwarmId, listen: Option<String>, connect: Vec<String>) -> Self {
        BusArgs {
            swarm,
            connect,
            listen: listen.into_iter().collect(),
            client: false,
            multicast: false,
            config_file: None,
            sim_clock: false,
        }
    }

    /// The clock this process's timers read: the simulator's with `--sim-clock` (reading the
    /// wall clock until the simulator is heard: see `Clock::synced`), else the wall clock.
    pub async fn clock(&self, session: &Session) -> Result<clock::Clock, BusError> {
        if self.sim_clock {
            clock::Clock::follow(session, &self.keys()).await
        } else {
            Ok(clock::Clock::wall())
        }
    }

    pub fn keys(&self) -> Keys {
        Keys::new(&self.swarm)
    }

    /// The zenoh configuration these settings describe. With `--zenoh-config`, the file says
    /// everything about the network (mode, endpoints, scouting, TLS, access control): a
    /// `--zenoh-*` flag beside it is refused, not quietly laid over what the file sets (a
    /// client file turned back into a listening peer would bypass the router).
    pub fn zenoh_config(&self) -> Result<zenoh::Config, BusError> {
        if let Some(path) = &self.config_file {
            let flags = [
                ("--zenoh-connect", !self.connect.is_empty()),
                ("--zenoh-listen", !self.listen.is_empty()),
                ("--zenoh-client", self.client),
                ("--zenoh-multicast", self.multicast),
            ];
            let given: Vec<&str> = flags
                .iter()
                .filter(|(_, on)| *on)
                .map(|(f, _)| *f)
                .collect();
            if !given.is_empty() {
                return Err(BusError::Config {
                    key: path.display().to_string(),
                    reason: format!(
                        "{} given with --zenoh-config: set it in the file instead",
                        given.join(", ")
                    ),
                });
            }
            return zenoh::Config::from_file(path).map_err(|e| BusError::Config {
                key: path.display().to_string(),
                reason: e.to_string(),
            });
        }
        let mut config = zenoh::Config::default();
        let mut set = |key: &str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| BusError::Config {
                    key: key.to_owned(),
                    reason: e.to_string(),
                })
        };
        let json_list = |items: &[String]| {
            format!(
                "[{}]",
                items
                    .iter()
                    .map(|s| format!("{s:?}"))
                    .collect::<Vec<_>>()
                    .join(",")
            )
        };
        set(
            "mode",
            if self.client {
                "\"client\"".into()
            } else {
                "\"peer\"".into()
            },
        )?;
        set("scouting/multicast/enabled", self.multicast.to_string())?;
        if !self.connect.is_empty() {
            set("connect/endpoints", json_list(&self.connect))?;
        }
        if !self.listen.is_empty() {
            set("listen/endpoints", json_list(&self.listen))?;
        } else if !self.client {
            // Peers must be reachable by the others that gossip discovers; an ephemeral port on
            // loopback keeps a default run off the network.
            set("listen/endpoints", "[\"tcp/127.0.0.1:0\"]".into())?;
        }
        Ok(config)
    }

    /// Opens the session. zenoh retries a connection for ever without saying why it fails (a
    /// router refusing this host's certificate looks the same as one not yet up), so while the
    /// session is not open this says so every [`JOIN_WARNING_PERIOD`], naming the endpoints and
    /// the certificate in use. zenoh's open blocks its thread until it is connected (its future
    /// is a `ready(wait())`), so it runs on a blocking thread, not on the caller's runtime.
    pub async fn open(&self) -> Result<Session, BusError> {
        let config = self.zenoh_config()?;
        let joining = join_description(&config);
        let mut open = tokio::task::spawn_blocking(move || zenoh::Wait::wait(zenoh::open(config)));
        let mut waited = Duration::ZERO;
        loop {
            match tokio::time::timeout(JOIN_WARNING_PERIOD, &mut open).await {
                Ok(Ok(opened)) => return opened.map_err(|e| BusError::Open(e.to_string())),
                Ok(Err(join)) => return Err(BusError::Open(join.to_string())),
                Err(_) => {
                    waited += JOIN_WARNING_PERIOD;
                    tracing::warn!(
                        "not joined the swarm network after {:.0} s: {joining}; still trying. \
                         A router that refuses this host's certificate (not signed by the swarm's \
                         CA, or none shown) or a router not reachable looks like this; zenoh's \
                         own warnings above say which",
                        waited.as_secs_f64()
                    );
                }
            }
        }
    }
}

/// How often [`BusArgs::open`] says it has not yet joined.
pub const JOIN_WARNING_PERIOD: Duration = Duration::from_secs(5);

/// "connecting to [..] with certificate ..": what a session opened from `config` tries.
fn join_description(config: &zenoh::Config) -> String {
    let get = |key: &str| config.get_json(key).unwrap_or_else(|_| "none".into());
    format!(
        "{} to {} (TLS certificate {}, CA {})",
        get("mode").trim_matches('"'),
        get("connect/endpoints"),
        get("transport/link/tls/connect_certificate"),
        get("transport/link/tls/root_ca_certificate"),
    )
}

/// How a message goes out: zenoh's priority, congestion control and batching.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delivery {
    /// Commands (actions, faults, the simulator's events): reliable, never dropped, sent at
    /// once at high priority.
    Command,
    /// The ground's heartbeat: at the commands' priority, so that zenoh's per-priority queues
    /// keep a beat ahead of every action sent after it (a drone judges an action after the
    /// beats before it, `onboard/agent/src/runtime/ground_side.rs`), but dropped under
    /// congestion: a newer beat follows.
    Beat,
    /// Telemetry (statuses, paths): may be dropped under congestion, batched at data priority.
    Telemetry,
}

/// Encodes `value` and puts it on `key` as `delivery` says.
pub async fn put<T: Serialize>(
    session: &Session,
    key: &str,
    value: &T,
    delivery: Delivery,
) -> Result<(), BusError> {
    let bytes = codec::encode(value)?;
    let builder = session.put(key, bytes);
    let builder = match delivery {
        Delivery::Command => builder
            .congestion_control(CongestionControl::Block)
            .priority(Priority::InteractiveHigh)
            .express(true),
        Delivery::Beat => builder
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::InteractiveHigh)
            .express(true),
        Delivery::Telemetry => builder
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::Data),
    };
    builder.await.map_err(|e| BusError::Put {
        key: key.to_owned(),
        reason: e.to_string(),
    })
}

/// Decodes a sample's payload with the wire codec.
pub fn decode<T: DeserializeOwned>(sample: &Sample) -> Result<T, CodecError> {
    codec::decode(&sample.payload().to_bytes())
}

/// Declares a subscriber, mapping the error.
pub async fn subscribe(
    session: &Session,
    key: &str,
) -> Result<zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<Sample>>, BusError> {
    session
        .declare_subscriber(key.to_owned())
        .await
        .map_err(|e| BusError::Declare {
            what: "subscriber",
            key: key.to_owned(),
            reason: e.to_string(),
        })
}

/// Declares a subscriber that decodes each sample and hands it to `handler` on zenoh's own
/// receiving thread, in the order the samples arrived. For messages acted on at once (a drone's
/// actions and the heartbeats they must follow), and under [`subscribe_latest`]'s ring: no
/// hand-over to another thread, which costs as much as zenoh's whole delivery (README,
/// "Benchmarks"). `handler` must be quick and must not block on anything zenoh itself waits
/// for; the subscriber lives until the returned value is dropped.
pub async fn subscribe_with<T, F>(
    session: &Session,
    key: &str,
    handler: F,
) -> Result<zenoh::pubsub::Subscriber<()>, BusError>
where
    T: DeserializeOwned,
    F: Fn(Result<T, CodecError>) + Send + Sync + 'static,
{
    session
        .declare_subscriber(key.to_owned())
        .callback(move |sample| handler(decode(&sample)))
        .await
        .map_err(|e| BusError::Declare {
            what: "subscriber",
            key: key.to_owned(),
            reason: e.to_string(),
        })
}

/// Declares this process's liveliness token on `key`; dropping it (or dying) withdraws it.
pub async fn declare_alive(
    session: &Session,
    key: &str,
) -> Result<zenoh::liveliness::LivelinessToken, BusError> {
    session
        .liveliness()
        .declare_token(key.to_owned())
        .await
        .map_err(|e| BusError::Declare {
            what: "liveliness token",
            key: key.to_owned(),
            reason: e.to_string(),
        })
}

/// Subscribes to liveliness changes under `key` (with the current state first).
pub async fn watch_alive(
    session: &Session,
    key: &str,
) -> Result<zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<Sample>>, BusError> {
    session
        .liveliness()
        .declare_subscriber(key.to_owned())
        .history(true)
        .await
        .map_err(|e| BusError::Declare {
            what: "liveliness subscriber",
            key: key.to_owned(),
            reason: e.to_string(),
        })
}

/// Loads a scenario given on a command line: a built-in name (`city`, `lab`) or a TOML file path.
pub fn load_scenario(arg: &str) -> Result<tacos_shared::scenario::Scenario, ScenarioLoadError> {
    use tacos_shared::scenario::{BUILTIN, Scenario};
    if BUILTIN.contains(&arg) {
        return Ok(Scenario::builtin(arg)?);
    }
    let text = std::fs::read_to_string(arg).map_err(|e| ScenarioLoadError::Read {
        path: arg.to_owned(),
        reason: e.to_string(),
    })?;
    Ok(Scenario::from_toml(&text)?)
}

#[derive(Debug, thiserror::Error)]
pub enum ScenarioLoadError {
    #[error("cannot read scenario {path}: {reason} (built-in scenarios: city, lab)")]
    Read { path: String, reason: String },
    #[error(transparent)]
    Invalid(#[from] tacos_shared::scenario::ScenarioError),
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    /// Two peer sessions on loopback TCP, the second connected to the first.
    pub(crate) async fn pair() -> (Session, Session) {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let swarm = SwarmId::new(format!("bus{}", std::process::id())).expect("swarm id");
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let listening = BusArgs::loopback(swarm.clone(), Some(endpoint.clone()), vec![]);
        let connecting = BusArgs::loopback(swarm, None, vec![endpoint]);
        let a = listening.open().await.expect("first session");
        let b = connecting.open().await.expect("second session");
        (a, b)
    }

    /// Puts 1, a payload cut short (the wire version alone), then 3; all at the same priority:
    /// zenoh orders samples within a priority, not across.
    pub(crate) async fn put_one_malformed_between(session: &Session, key: &str) {
        put(session, key, &1u64, Delivery::Telemetry)
            .await
            .expect("put");
        session
            .put(key, vec![codec::WIRE_VERSION])
            .await
            .expect("raw put");
        put(session, key, &3u64, Delivery::Telemetry)
            .await
            .expect("put");
    }

    /// Waits (10 s at most) until `session` knows a subscriber of `key`.
    pub(crate) async fn until_matched(session: &Session, key: &str) {
        let publisher = session
            .declare_publisher(key.to_owned())
            .await
            .expect("publisher");
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        while !publisher
            .matching_status()
            .await
            .expect("matching status")
            .matching()
        {
            assert!(std::time::Instant::now() < deadline, "never matched");
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn subscribe_with_hands_each_sample_decoded_in_order_and_a_malformed_one_as_its_error() {
        let (publisher_side, subscriber_side) = pair().await;
        let key = "tacos/bus-test/with";
        let heard: Arc<Mutex<Vec<Result<u64, CodecError>>>> = Arc::default();
        let (done_tx, mut done_rx) = tokio::sync::mpsc::unbounded_channel();
        let _subscriber = {
            let heard = heard.clone();
            subscribe_with(
                &subscriber_side,
                key,
                move |value: Result<u64, CodecError>| {
                    let mut heard = heard.lock().expect("not poisoned");
                    heard.push(value);
                    if heard.len() == 4 {
                        let _ = done_tx.send(());
                    }
                },
            )
            .await
            .expect("declared")
        };
        until_matched(&publisher_side, key).await;
        put_one_malformed_between(&publisher_side, key).await;
        put(&publisher_side, key, &4u64, Delivery::Telemetry)
            .await
            .expect("put");
        tokio::time::timeout(Duration::from_secs(10), done_rx.recv())
            .await
            .expect("all four heard within 10 s");
        let heard = heard.lock().expect("not poisoned");
        assert_eq!(heard[0], Ok(1));
        assert!(
            matches!(heard[1], Err(CodecError::Truncated)),
            "{:?}",
            heard[1]
        );
        assert_eq!(heard[2..], [Ok(3), Ok(4)]);
    }
}

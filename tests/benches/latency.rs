//! Latency benchmarks (a program that prints figures; nothing here asserts a speed).
//!
//! * `zenoh_action`: an `ActionCommand` from a ground session to an onboard session over zenoh
//!   TCP on loopback, publish to decoded receipt, through the same `tacos_bus` calls the
//!   binaries use; beside it, a bare zenoh put/subscribe of the same bytes in the same run.
//! * `iceoryx2_setpoint`: a `SetpointSample` from the onboard ports to the writer ports over
//!   iceoryx2 shared memory, woken by the event service, publish to receipt; beside it bare
//!   iceoryx2 ports with the same event wake-up, and a busy-polling subscriber.
//!
//! Messages are sent one at a time (each waits for the previous receipt), so these are
//! latencies, not throughput. Run: `cargo bench --bench latency`.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tacos_bus::BusArgs;
use tacos_ipc::IpcNode;
use tacos_shared::action::{Action, ActionCommand};
use tacos_shared::ipc::SetpointSample;
use tacos_shared::{DroneId, SwarmId, Vec3};

const MESSAGES: usize = 10_000;
/// Messages sent before each round's measured ones.
const WARMUP: usize = 50;
/// Each path's messages are measured in this many rounds, the paths taking turns. Short
/// rounds: this machine's wake-up latency moves between levels for seconds at a time (5, 9,
/// 13 or 18 µs for the same iceoryx2 path in one session), and with ten rounds of 1,000 a
/// path that drew more of a slow spell read up to 1.44× the other.
const ROUNDS: usize = 50;

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let idx = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[idx.min(sorted.len() - 1)]
}

fn summarize(mut samples: Vec<f64>) -> (f64, f64) {
    samples.sort_by(f64::total_cmp);
    (percentile(&samples, 0.5), percentile(&samples, 0.99))
}

fn swarm_id(tag: &str) -> SwarmId {
    SwarmId::new(format!("bench{tag}{}", std::process::id()))
        .unwrap_or_else(|e| panic!("bad swarm id: {e}"))
}

async fn zenoh_pair(swarm: &SwarmId) -> anyhow::Result<(zenoh::Session, zenoh::Session)> {
    let port = tacos_ground::launch::free_tcp_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let ground = BusArgs::loopback(swarm.clone(), Some(endpoint.clone()), vec![])
        .open()
        .await?;
    let onboard = BusArgs::loopback(
        swarm.clone(),
        Some("tcp/127.0.0.1:0".into()),
        vec![endpoint],
    )
    .open()
    .await?;
    Ok((ground, onboard))
}

/// Sends `WARMUP + count` messages one at a time, numbered from `base`; `send(i)` publishes
/// message i, the receiver reports receipt of message i through `received`. Returns the
/// latency of the last `count`, in microseconds.
async fn ping_series<F, Fut>(
    received: &tokio::sync::watch::Sender<(u64, Instant)>,
    base: u64,
    count: usize,
    mut send: F,
) -> anyhow::Result<Vec<f64>>
where
    F: FnMut(u64) -> Fut,
    Fut: std::future::Future<Output = anyhow::Result<()>>,
{
    let mut rx = received.subscribe();
    let mut latencies = Vec::with_capacity(count);
    for n in 0..(WARMUP + count) {
        let i = base + n as u64;
        let sent_at = Instant::now();
        send(i).await?;
        let got_at = loop {
            tokio::time::timeout(Duration::from_secs(5), rx.changed())
                .await
                .map_err(|_| anyhow::anyhow!("message {i} not received within 5 s"))??;
            let (seq, at) = *rx.borrow_and_update();
            if seq == i {
                break at;
            }
        };
        if n >= WARMUP {
            latencies.push(got_at.duration_since(sent_at).as_secs_f64() * 1e6);
        }
    }
    Ok(latencies)
}

/// The path of an `ActionCommand`, and the steps that separate it from a bare put, each on the
/// same two sessions with the same payload size:
/// * `bare`: zenoh's default put, received in a subscriber callback on zenoh's own thread;
/// * `bare+qos`: the put with TACOS's action QoS (express, blocking congestion control,
///   interactive-high priority), same callback;
/// * `bare+fifo`: default put, received through zenoh's default FIFO handler by a tokio task
///   (what an async program's `recv_async` costs: a hand-over between threads);
/// * `tacos`: `tacos_bus::put` (codec, QoS) and `tacos_bus::subscribe_with` (decoded in zenoh's
///   callback), the calls the ground and `tacos-onboard` make; the onboard's handler then
///   takes its executor's lock and hands the action over (`runtime::shared_core`).
#[derive(Debug, Clone, Copy, PartialEq)]
enum ZenohPath {
    Bare,
    BareQos,
    BareFifo,
    Tacos,
}

const ZENOH_PATHS: [ZenohPath; 4] = [
    ZenohPath::Bare,
    ZenohPath::BareQos,
    ZenohPath::BareFifo,
    ZenohPath::Tacos,
];

impl ZenohPath {
    fn name(self) -> &'static str {
        match self {
            ZenohPath::Bare => "bare",
            ZenohPath::BareQos => "bare+qos",
            ZenohPath::BareFifo => "bare+fifo",
            ZenohPath::Tacos => "tacos",
        }
    }
}

fn command(seq: u64) -> ActionCommand {
    ActionCommand {
        ground: 1,
        seq,
        sent_at: 0.0,
        task_id: Some("T1".into()),
        action: Action::Goto {
            target: Vec3::new(12.5, -40.0, 10.0),
        },
    }
}

/// A bare probe of `len` bytes carrying its seq at bytes 1..9.
fn probe(seq: u64, len: usize) -> Vec<u8> {
    let mut bytes = vec![0u8; len];
    bytes[1..9].copy_from_slice(&seq.to_le_bytes());
    bytes
}

fn seq_of(bytes: &[u8]) -> Option<u64> {
    let seq: [u8; 8] = bytes.get(1..9)?.try_into().ok()?;
    Some(u64::from_le_bytes(seq))
}

type Receipts = Arc<tokio::sync::watch::Sender<(u64, Instant)>>;

/// Declares `path`'s receiving end on `onboard` (a callback, or a task reading a FIFO).
async fn receiver(
    onboard: &zenoh::Session,
    path: ZenohPath,
    key: &str,
    receipts: Receipts,
) -> anyhow::Result<Box<dyn std::any::Any + Send>> {
    Ok(match path {
        ZenohPath::Bare | ZenohPath::BareQos => Box::new(
            onboard
                .declare_subscriber(key.to_owned())
                .callback(move |sample| {
                    if let Some(seq) = seq_of(&sample.payload().to_bytes()) {
                        let _ = receipts.send((seq, Instant::now()));
                    }
                })
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?,
        ),
        ZenohPath::BareFifo => {
            let sub = onboard
                .declare_subscriber(key.to_owned())
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            Box::new(AbortOnDrop(tokio::spawn(async move {
                while let Ok(sample) = sub.recv_async().await {
                    if let Some(seq) = seq_of(&sample.payload().to_bytes()) {
                        let _ = receipts.send((seq, Instant::now()));
                    }
                }
            })))
        }
        ZenohPath::Tacos => Box::new(
            tacos_bus::subscribe_with(onboard, key, move |cmd: Result<ActionCommand, _>| {
                if let Ok(cmd) = cmd {
                    let _ = receipts.send((cmd.seq, Instant::now()));
                }
            })
            .await?,
        ),
    })
}

struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

async fn send_on(
    ground: &zenoh::Session,
    path: ZenohPath,
    key: &str,
    seq: u64,
    len: usize,
) -> anyhow::Result<()> {
    match path {
        ZenohPath::Tacos => {
            Ok(tacos_bus::put(ground, key, &command(seq), tacos_bus::Delivery::Command).await?)
        }
        ZenohPath::Bare | ZenohPath::BareFifo => ground
            .put(key, probe(seq, len))
            .await
            .map_err(|e| anyhow::anyhow!("{e}")),
        ZenohPath::BareQos => ground
            .put(key, probe(seq, len))
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .priority(zenoh::qos::Priority::InteractiveHigh)
            .express(true)
            .await
            .map_err(|e| anyhow::anyhow!("{e}")),
    }
}

/// Every path's latencies (µs), measured in interleaved rounds so that no path gets a quieter
/// stretch of the run than another.
async fn zenoh_action() -> anyhow::Result<Vec<(ZenohPath, Vec<f64>)>> {
    let swarm = swarm_id("z");
    let keys = tacos_shared::keys::Keys::new(&swarm);
    let alfa = DroneId::new("alfa")?;
    let (ground, onboard) = zenoh_pair(&swarm).await?;
    let len = tacos_shared::codec::encode(&command(0))?.len();
    let mut ends = Vec::new();
    for path in ZENOH_PATHS {
        let key = match path {
            ZenohPath::Tacos => keys.action(&alfa),
            other => format!("{}_{}", keys.action(&alfa), other.name().replace('+', "_")),
        };
        let (tx, _) = tokio::sync::watch::channel((u64::MAX, Instant::now()));
        let receipts = Arc::new(tx);
        let end = receiver(&onboard, path, &key, receipts.clone()).await?;
        tacos_tests::wait_for_subscriber(&ground, &key).await?;
        ends.push((path, key, receipts, end, Vec::with_capacity(MESSAGES)));
    }
    let per_round = MESSAGES / ROUNDS;
    for round in 0..ROUNDS {
        for (path, key, receipts, _, samples) in &mut ends {
            let base = (round * (WARMUP + per_round)) as u64;
            let series = ping_series(receipts, base, per_round, |i| {
                send_on(&ground, *path, key, i, len)
            })
            .await?;
            samples.extend(series);
        }
    }
    Ok(ends
        .into_iter()
        .map(|(path, _, _, _, samples)| (path, samples))
        .collect())
}

type Svc = iceoryx2::prelude::ipc_threadsafe::Service;

/// The setpoint path's variants, each a publisher and a subscriber of `SetpointSample` with
/// the QoS `tacos-ipc` uses (buffer 4, history 1, safe overflow):
/// * `tacos`: `tacos-ipc`'s onboard and writer ports, woken by its event service;
/// * `bare`: iceoryx2's own ports and an event service of the same kind, the same calls;
/// * `busy-poll`: iceoryx2's subscriber polled in a spin, no event (a core spent waiting).
#[derive(Debug, Clone, Copy, PartialEq)]
enum SetpointPath {
    Tacos,
    Bare,
    BusyPoll,
}

impl SetpointPath {
    fn name(self) -> &'static str {
        match self {
            SetpointPath::Tacos => "tacos",
            SetpointPath::Bare => "bare",
            SetpointPath::BusyPoll => "busy-poll",
        }
    }
}

fn iox<T, E: std::fmt::Debug>(what: &str, r: Result<T, E>) -> anyhow::Result<T> {
    r.map_err(|e| anyhow::anyhow!("iceoryx2 {what}: {e:?}"))
}

/// Bare iceoryx2 ports on services of their own.
struct BarePorts {
    publisher: iceoryx2::port::publisher::Publisher<Svc, SetpointSample, ()>,
    subscriber: iceoryx2::port::subscriber::Subscriber<Svc, SetpointSample, ()>,
    notifier: iceoryx2::port::notifier::Notifier<Svc>,
    listener: iceoryx2::port::listener::Listener<Svc>,
}

fn bare_ports(node: &iceoryx2::node::Node<Svc>, tag: &str) -> anyhow::Result<BarePorts> {
    use iceoryx2::prelude::*;
    let name = format!("tacos-bench/{}/{tag}", std::process::id());
    let data = iox(
        "service",
        node.service_builder(&iox("name", ServiceName::new(&format!("{name}/data")))?)
            .publish_subscribe::<SetpointSample>()
            .max_publishers(2)
            .max_subscribers(4)
            .subscriber_max_buffer_size(4)
            .history_size(1)
            .enable_safe_overflow(true)
            .open_or_create(),
    )?;
    let events = iox(
        "service",
        node.service_builder(&iox("name", ServiceName::new(&format!("{name}/wake")))?)
            .event()
            .max_notifiers(2)
            .max_listeners(2)
            .open_or_create(),
    )?;
    Ok(BarePorts {
        publisher: iox("publisher", data.publisher_builder().create())?,
        subscriber: iox("subscriber", data.subscriber_builder().create())?,
        notifier: iox("notifier", events.notifier_builder().create())?,
        listener: iox("listener", events.listener_builder().create())?,
    })
}

/// Sends one setpoint on `path` and spins until the reader has seen it.
struct SetpointSender {
    tacos: tacos_ipc::OnboardPorts,
    bare: Arc<BarePorts>,
    busy: Arc<BarePorts>,
}

impl SetpointSender {
    fn send(&self, path: SetpointPath, sample: SetpointSample) -> anyhow::Result<()> {
        let bare_send = |ports: &BarePorts, wake: bool| -> anyhow::Result<()> {
            let loaned = iox("loan", ports.publisher.loan_uninit())?;
            iox("send", loaned.write_payload(sample).send())?;
            if wake {
                iox("notify", ports.notifier.notify())?;
            }
            Ok(())
        };
        match path {
            SetpointPath::Tacos => Ok(self.tacos.send_setpoint(sample)?),
            SetpointPath::Bare => bare_send(&self.bare, true),
            SetpointPath::BusyPoll => bare_send(&self.busy, false),
        }
    }
}

/// Every setpoint path's one-way latencies (µs). `tacos` and `bare` take turns in rounds;
/// `busy-poll` runs last, alone, since its reader keeps a core busy.
fn iceoryx2_setpoint() -> anyhow::Result<Vec<(SetpointPath, Vec<f64>)>> {
    use iceoryx2::prelude::*;
    set_log_level_from_env_or(LogLevel::Error);
    let swarm = swarm_id("i");
    let drone = DroneId::new("alfa")?;
    let node = iox(
        "node",
        NodeBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Svc>(),
    )?;
    let bare = Arc::new(bare_ports(&node, "bare")?);
    let busy = Arc::new(bare_ports(&node, "busy")?);
    let writer_node = IpcNode::new(&swarm, &drone)?;
    let writer = writer_node.writer_ports()?;
    let onboard_node = IpcNode::new(&swarm, &drone)?;
    let sender = SetpointSender {
        tacos: onboard_node.onboard_ports()?,
        bare: bare.clone(),
        busy: busy.clone(),
    };
    let origin = Instant::now();
    // The reader's side: which path is being measured (an index into PATHS; PATHS.len() = stop)
    // and the last seq received.
    const PATHS: [SetpointPath; 3] = [
        SetpointPath::Tacos,
        SetpointPath::Bare,
        SetpointPath::BusyPoll,
    ];
    let active = Arc::new(AtomicU64::new(0));
    let received = Arc::new(AtomicU64::new(u64::MAX));
    let (a, r) = (active.clone(), received.clone());
    let reader = std::thread::spawn(move || -> anyhow::Result<Vec<Vec<f64>>> {
        let mut latencies = vec![Vec::with_capacity(MESSAGES); PATHS.len()];
        let mut take = |path: usize, sp: SetpointSample| {
            let now_ns = origin.elapsed().as_nanos() as u64;
            if sp.seq as usize % (WARMUP + MESSAGES / ROUNDS) >= WARMUP {
                latencies[path].push(now_ns.saturating_sub(sp.stamp_ns) as f64 / 1e3);
            }
            r.store(sp.seq, Ordering::Release);
        };
        loop {
            let path = a.load(Ordering::Acquire) as usize;
            match PATHS.get(path) {
                None => break,
                Some(SetpointPath::Tacos) => {
                    if writer.wait_for_wakeup(Duration::from_millis(20))? {
                        while let Some(sp) = writer.setpoints.try_recv()? {
                            take(path, sp);
                        }
                    }
                }
                Some(SetpointPath::Bare) => {
                    let mut woken = false;
                    iox(
                        "wait",
                        bare.listener
                            .timed_wait(|_| woken = true, Duration::from_millis(20)),
                    )?;
                    if woken {
                        while let Some(sp) = iox("receive", bare.subscriber.receive())? {
                            take(path, *sp);
                        }
                    }
                }
                Some(SetpointPath::BusyPoll) => {
                    while let Some(sp) = iox("receive", busy.subscriber.receive())? {
                        take(path, *sp);
                    }
                    std::hint::spin_loop();
                }
            }
        }
        Ok(latencies)
    });
    let per_round = MESSAGES / ROUNDS;
    let mut seq = 0u64;
    let mut run = |path: usize| -> anyhow::Result<()> {
        active.store(path as u64, Ordering::Release);
        for _ in 0..(WARMUP + per_round) {
            let sample = SetpointSample {
                seq,
                stamp_ns: origin.elapsed().as_nanos() as u64,
                position: [1.0, 2.0, 3.0],
                velocity: [0.5, 0.0, 0.0],
                acceleration: [0.0; 3],
                yaw: f64::NAN,
            };
            sender.send(PATHS[path], sample)?;
            let deadline = Instant::now() + Duration::from_secs(5);
            while received.load(Ordering::Acquire) != seq {
                if Instant::now() > deadline {
                    anyhow::bail!(
                        "setpoint {seq} on {} not received within 5 s",
                        PATHS[path].name()
                    );
                }
                std::hint::spin_loop();
            }
            seq += 1;
        }
        Ok(())
    };
    let mut result = Ok(());
    for _ in 0..ROUNDS {
        for path in [0, 1] {
            if result.is_ok() {
                result = run(path);
            }
        }
    }
    for _ in 0..ROUNDS {
        if result.is_ok() {
            result = run(2);
        }
    }
    active.store(PATHS.len() as u64, Ordering::Release);
    let latencies = reader
        .join()
        .map_err(|_| anyhow::anyhow!("reader thread panicked"))??;
    result?;
    Ok(PATHS.into_iter().zip(latencies).collect())
}

fn p50_p99(samples: &[f64]) -> (f64, f64) {
    summarize(samples.to_vec())
}

fn main() -> anyhow::Result<()> {
    // `cargo bench` passes `--bench`; nothing to parse.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let zenoh = runtime.block_on(zenoh_action())?;
    let find = |paths: &[(ZenohPath, Vec<f64>)], p: ZenohPath| {
        paths
            .iter()
            .find(|(q, _)| *q == p)
            .map(|(_, s)| p50_p99(s))
            .unwrap_or((f64::NAN, f64::NAN))
    };
    for (path, samples) in &zenoh {
        let (p50, p99) = p50_p99(samples);
        eprintln!(
            "zenoh {:<10} p50 {p50:7.1} us  p99 {p99:7.1} us  ({} messages)",
            path.name(),
            samples.len()
        );
    }
    let (p50, p99) = find(&zenoh, ZenohPath::Tacos);
    let (bare_p50, bare_p99) = find(&zenoh, ZenohPath::Bare);
    let (fifo_p50, fifo_p99) = find(&zenoh, ZenohPath::BareFifo);
    drop(runtime);
    let setpoints = iceoryx2_setpoint()?;
    for (path, samples) in &setpoints {
        let (p50, p99) = p50_p99(samples);
        eprintln!(
            "iceoryx2 {:<10} p50 {p50:7.2} us  p99 {p99:7.2} us  ({} messages)",
            path.name(),
            samples.len()
        );
    }
    println!(
        "zenoh_action p50_us={p50:.1} p99_us={p99:.1} bare_p50_us={bare_p50:.1} bare_p99_us={bare_p99:.1} ratio={:.2} ratio_p99={:.2} bare_fifo_p50_us={fifo_p50:.1} bare_fifo_p99_us={fifo_p99:.1} ratio_to_fifo={:.2} ratio_to_fifo_p99={:.2}",
        p50 / bare_p50,
        p99 / bare_p99,
        p50 / fifo_p50,
        p99 / fifo_p99,
    );
    let sp = |p: SetpointPath| {
        setpoints
            .iter()
            .find(|(q, _)| *q == p)
            .map(|(_, s)| p50_p99(s))
            .unwrap_or((f64::NAN, f64::NAN))
    };
    let (ip50, ip99) = sp(SetpointPath::Tacos);
    let (bp50, bp99) = sp(SetpointPath::Bare);
    let (busy50, busy99) = sp(SetpointPath::BusyPoll);
    println!(
        "iceoryx2_setpoint p50_us={ip50:.2} p99_us={ip99:.2} bare_p50_us={bp50:.2} bare_p99_us={bp99:.2} ratio={:.2} ratio_p99={:.2} busy_poll_p50_us={busy50:.2} busy_poll_p99_us={busy99:.2}",
        ip50 / bp50,
        ip99 / bp99,
    );
    Ok(())
}

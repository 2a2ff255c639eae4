//! Latency benchmarks (a program that prints figures; nothing here asserts a speed).
//!
//! * `zenoh_action`: an `ActionCommand` from a ground session to an onboard session over zenoh
//!   TCP on loopback, publish to decoded receipt, through the same `tacos_bus` calls the
//!   binaries use; beside it, a bare zenoh put/subscribe of the same bytes in the same run.
//! * `iceoryx2_setpoint`: a `SetpointSample` from the onboard ports to the writer ports over
//!   iceoryx2 shared memory, woken by the event service, publish to receipt.
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
const WARMUP: usize = 500;

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

/// Sends `MESSAGES` messages one at a time; `send(i)` publishes message i, the receiver reports
/// receipt of message i through `received`. Returns per-message latency in microseconds.
async fn ping_series<F, Fut>(
    received: &tokio::sync::watch::Sender<(u64, Instant)>,
    mut send: F,
) -> anyhow::Result<Vec<f64>>
where
    F: FnMut(u64) -> Fut,
    Fut: std::future::Future<Output = anyhow::Result<()>>,
{
    let mut rx = received.subscribe();
    let mut latencies = Vec::with_capacity(MESSAGES);
    for i in 0..(WARMUP + MESSAGES) as u64 {
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
        if i as usize >= WARMUP {
            latencies.push(got_at.duration_since(sent_at).as_secs_f64() * 1e6);
        }
    }
    Ok(latencies)
}

async fn zenoh_action() -> anyhow::Result<((f64, f64), (f64, f64))> {
    let swarm = swarm_id("z");
    let keys = tacos_shared::keys::Keys::new(&swarm);
    let alfa = DroneId::new("alfa")?;
    let (ground, onboard) = zenoh_pair(&swarm).await?;

    // TACOS path: tacos_bus::put (urgent QoS) → subscriber → codec decode.
    let action_key = keys.action(&alfa);
    let (tx, _) = tokio::sync::watch::channel((u64::MAX, Instant::now()));
    let tx = Arc::new(tx);
    let sub = tacos_bus::subscribe(&onboard, &action_key).await?;
    let t = tx.clone();
    let receiver = tokio::spawn(async move {
        while let Ok(sample) = sub.recv_async().await {
            if let Ok(cmd) = tacos_bus::decode::<ActionCommand>(&sample) {
                let _ = t.send((cmd.seq, Instant::now()));
            }
        }
    });
    wait_for_match(&ground, &action_key).await?;
    let command = |seq| ActionCommand {
        ground: 1,
        seq,
        sent_at: 0.0,
        task_id: Some("T1".into()),
        action: Action::Goto {
            target: Vec3::new(12.5, -40.0, 10.0),
        },
    };
    let tacos = ping_series(&tx, |i| {
        let (g, k, c) = (&ground, &action_key, command(i));
        async move { Ok(tacos_bus::put(g, k, &c, true).await?) }
    })
    .await?;
    receiver.abort();

    // Bare zenoh: the same encoded bytes, default put, no decode (the seq is read from a
    // fixed offset so the receiver does the least possible work).
    let bare_key = format!("{action_key}_bare");
    let (btx, _) = tokio::sync::watch::channel((u64::MAX, Instant::now()));
    let btx = Arc::new(btx);
    let bt = btx.clone();
    let _bare_sub = onboard
        .declare_subscriber(bare_key.clone())
        .callback(move |sample| {
            let bytes = sample.payload().to_bytes();
            let mut seq = [0u8; 8];
            if bytes.len() >= 9 {
                seq.copy_from_slice(&bytes[1..9]);
                let _ = bt.send((u64::from_le_bytes(seq), Instant::now()));
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    wait_for_match(&ground, &bare_key).await?;
    let payload_len = tacos_shared::codec::encode(&command(0))?.len();
    let bare = ping_series(&btx, |i| {
        let (g, k) = (&ground, &bare_key);
        let mut bytes = vec![0u8; payload_len];
        bytes[1..9].copy_from_slice(&i.to_le_bytes());
        async move { g.put(k, bytes).await.map_err(|e| anyhow::anyhow!("{e}")) }
    })
    .await?;
    Ok((summarize(tacos), summarize(bare)))
}

/// Waits until a put on `key` from `session` reaches a subscriber (routes are set up).
async fn wait_for_match(session: &zenoh::Session, key: &str) -> anyhow::Result<()> {
    let publisher = session
        .declare_publisher(key.to_owned())
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let deadline = Instant::now() + Duration::from_secs(10);
    while !publisher
        .matching_status()
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?
        .matching()
    {
        if Instant::now() > deadline {
            anyhow::bail!("no subscriber matched {key} within 10 s");
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    Ok(())
}

fn iceoryx2_setpoint() -> anyhow::Result<(f64, f64)> {
    let swarm = swarm_id("i");
    let drone = DroneId::new("alfa")?;
    let writer_node = IpcNode::new(&swarm, &drone)?;
    let writer = writer_node.writer_ports()?;
    let origin = Instant::now();
    let received = Arc::new(AtomicU64::new(u64::MAX));
    let done = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (r, d) = (received.clone(), done.clone());
    let reader = std::thread::spawn(move || -> anyhow::Result<Vec<f64>> {
        let mut latencies = Vec::with_capacity(MESSAGES);
        while !d.load(Ordering::Acquire) {
            if !writer.wait_for_wakeup(Duration::from_millis(100))? {
                continue;
            }
            while let Some(sp) = writer.setpoints.try_recv()? {
                let now_ns = origin.elapsed().as_nanos() as u64;
                if sp.seq as usize >= WARMUP {
                    latencies.push(now_ns.saturating_sub(sp.stamp_ns) as f64 / 1e3);
                }
                r.store(sp.seq, Ordering::Release);
            }
        }
        Ok(latencies)
    });
    let onboard_node = IpcNode::new(&swarm, &drone)?;
    let onboard = onboard_node.onboard_ports()?;
    for seq in 0..(WARMUP + MESSAGES) as u64 {
        let sample = SetpointSample {
            seq,
            stamp_ns: origin.elapsed().as_nanos() as u64,
            position: [1.0, 2.0, 3.0],
            velocity: [0.5, 0.0, 0.0],
            acceleration: [0.0; 3],
            yaw: f64::NAN,
        };
        onboard.send_setpoint(sample)?;
        let deadline = Instant::now() + Duration::from_secs(5);
        while received.load(Ordering::Acquire) != seq {
            if Instant::now() > deadline {
                anyhow::bail!("setpoint {seq} not received within 5 s");
            }
            std::hint::spin_loop();
        }
    }
    done.store(true, Ordering::Release);
    let latencies = reader
        .join()
        .map_err(|_| anyhow::anyhow!("reader thread panicked"))??;
    Ok(summarize(latencies))
}

fn main() -> anyhow::Result<()> {
    // `cargo bench` passes `--bench`; nothing to parse.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let ((p50, p99), (bare_p50, bare_p99)) = runtime.block_on(zenoh_action())?;
    eprintln!(
        "zenoh bare put/subscribe: p50 {bare_p50:.1} us, p99 {bare_p99:.1} us ({MESSAGES} messages)"
    );
    let (ip50, ip99) = iceoryx2_setpoint()?;
    println!(
        "zenoh_action p50_us={p50:.1} p99_us={p99:.1} bare_p50_us={bare_p50:.1} ratio={:.2}",
        p50 / bare_p50
    );
    println!("iceoryx2_setpoint p50_us={ip50:.1} p99_us={ip99:.1}");
    Ok(())
}

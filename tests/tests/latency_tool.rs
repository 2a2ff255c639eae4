//! `tacos-latency` as a user runs it, on loopback: a ponger and a pinger as two processes over
//! TCP, TACOS's messages beside bare zenoh in the same run; and a pinger with nobody to answer
//! says so instead of hanging. (Across hosts, through the router over QUIC with mutual TLS, it
//! runs in `multi_host.rs`.)

use std::process::Stdio;
use std::time::Duration;
use tacos_ground::launch::{bin_dir, free_tcp_port};
use tacos_tests::unique_swarm;
use tokio::process::Command;

fn latency(args: &[&str]) -> Command {
    let mut cmd = Command::new(bin_dir().join("tacos-latency"));
    cmd.args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true);
    cmd
}

/// The numbers of the row that starts with `name`.
fn row(out: &str, name: &str) -> Vec<f64> {
    out.lines()
        .find(|l| l.starts_with(name))
        .map(|l| {
            l[name.len()..]
                .split_whitespace()
                .filter_map(|w| w.parse::<f64>().ok())
                .collect()
        })
        .unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_pinger_and_a_ponger_measure_tacos_messages_beside_bare_zenoh() -> anyhow::Result<()> {
    let swarm = unique_swarm("lat");
    let swarm = swarm.as_str();
    let port = free_tcp_port()?;
    let listen = format!("tcp/127.0.0.1:{port}");
    let pong = latency(&[
        "pong",
        "--swarm",
        swarm,
        "--drone",
        "alfa",
        "--zenoh-listen",
        &listen,
    ])
    .spawn()?;
    let ping = latency(&[
        "ping",
        "--swarm",
        swarm,
        "--drone",
        "alfa",
        "--zenoh-connect",
        &listen,
        "--count",
        "300",
        "--warmup",
        "50",
    ])
    .output();
    let out = tokio::time::timeout(Duration::from_secs(90), ping).await??;
    drop(pong);
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "ping failed: {stdout}\n{stderr}");
    println!("{stdout}");
    for name in ["bare zenoh", "tacos "] {
        let numbers = row(&stdout, name);
        // rtt p50 p99 max, out p50 p99, back p50 p99, msgs/s, lost
        assert_eq!(numbers.len(), 9, "{name} row: {stdout}");
        assert!(
            numbers[0] > 0.0 && numbers[0] <= numbers[1] && numbers[1] <= numbers[2],
            "{name}: {numbers:?}"
        );
        assert!(numbers[7] > 0.0, "{name}: no throughput: {numbers:?}");
        assert_eq!(
            numbers[8], 0.0,
            "{name}: lost pings on loopback: {numbers:?}"
        );
    }
    assert!(stdout.contains("tacos / bare: "), "{stdout}");

    // Nobody answers: a clear error, not a hang.
    let lonely = latency(&[
        "ping",
        "--swarm",
        swarm,
        "--drone",
        "bravo",
        "--zenoh-listen",
        "tcp/127.0.0.1:0",
        "--find-s",
        "2",
    ])
    .output();
    let out = tokio::time::timeout(Duration::from_secs(30), lonely).await??;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "a ping with no ponger succeeded");
    assert!(stderr.contains("no ponger answered"), "{stderr}");
    Ok(())
}

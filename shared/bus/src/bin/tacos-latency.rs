//! `tacos-latency`: round trips of TACOS's real messages beside bare zenoh on the same path, as
//! two processes (see `tacos_bus::latency`). Start the ponger where a drone would be, the pinger
//! where the ground would be:
//!
//! ```text
//! tacos-latency pong --drone alfa --zenoh-listen tcp/0.0.0.0:7447
//! tacos-latency ping --drone alfa --zenoh-connect tcp/10.0.0.5:7447
//! tacos-latency pong --drone alfa --zenoh-config /etc/tacos/zenoh/client.json5   # through the router
//! ```

use clap::{Parser, Subcommand};
use std::time::Duration;
use tacos_bus::BusArgs;
use tacos_bus::latency::{Carrier, Figures, PingPlan, ProbeKeys, Spread, ping, pong, probe_sizes};
use tacos_shared::DroneId;

#[derive(Debug, Parser)]
#[command(
    name = "tacos-latency",
    version,
    about = "Round trips of TACOS messages beside bare zenoh"
)]
struct Cli {
    #[command(subcommand)]
    role: Role,
}

#[derive(Debug, Subcommand)]
enum Role {
    /// Answer pings in a drone's name until Ctrl-C (or --for-s).
    Pong {
        #[command(flatten)]
        bus: BusArgs,
        #[arg(long, default_value = "alfa")]
        drone: String,
        /// Stop after this many seconds (0: until Ctrl-C).
        #[arg(long, default_value_t = 0.0)]
        for_s: f64,
    },
    /// Measure round trips to a ponger: bare zenoh first, then TACOS's messages.
    Ping {
        #[command(flatten)]
        bus: BusArgs,
        #[arg(long, default_value = "alfa")]
        drone: String,
        /// Round trips measured per carrier (one at a time; as many again for the throughput).
        #[arg(long, default_value_t = 2000)]
        count: usize,
        #[arg(long, default_value_t = 200)]
        warmup: usize,
        /// Pings in flight at once for the messages-per-second figure.
        #[arg(long, default_value_t = 32)]
        burst: usize,
        /// Seconds to wait for the ponger to answer at all.
        #[arg(long, default_value_t = 30.0)]
        find_s: f64,
    },
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("tacos-latency: starting the async runtime: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    match runtime.block_on(run(cli.role)) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("tacos-latency: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn drone_id(text: &str) -> anyhow::Result<DroneId> {
    DroneId::new(text).map_err(|e| anyhow::anyhow!("--drone {text:?}: {e}"))
}

async fn run(role: Role) -> anyhow::Result<()> {
    match role {
        Role::Pong { bus, drone, for_s } => {
            let drone = drone_id(&drone)?;
            let session = bus.open().await?;
            let keys = ProbeKeys::new(&bus.keys(), &drone);
            eprintln!("answering pings for {drone} on swarm {}", bus.swarm);
            let stop = async {
                if for_s > 0.0 {
                    tokio::time::sleep(Duration::from_secs_f64(for_s)).await;
                } else {
                    let _ = tokio::signal::ctrl_c().await;
                }
            };
            let count = pong(&session, &keys, &drone, stop).await?;
            println!(
                "answered {} pings ({} malformed)",
                count.answered, count.malformed
            );
            Ok(())
        }
        Role::Ping {
            bus,
            drone,
            count,
            warmup,
            burst,
            find_s,
        } => {
            anyhow::ensure!(count > 0, "--count must be at least 1");
            let drone = drone_id(&drone)?;
            let session = bus.open().await?;
            let keys = ProbeKeys::new(&bus.keys(), &drone);
            let plan = PingPlan {
                count,
                warmup,
                burst,
                wait: Duration::from_secs(2),
            };
            let (out_len, back_len) = probe_sizes(&drone)?;
            println!(
                "{count} round trips per carrier to {drone} on swarm {} ({out_len} B out: an ActionCommand; {back_len} B back: a DroneStatus); µs",
                bus.swarm
            );
            println!(
                "{:<11} {:>8} {:>8} {:>8} | {:>8} {:>8} | {:>8} {:>8} | {:>9} {:>5}",
                "carrier",
                "rtt p50",
                "rtt p99",
                "rtt max",
                "out p50",
                "out p99",
                "back p50",
                "back p99",
                "msgs/s",
                "lost"
            );
            let find = Duration::from_secs_f64(find_s.max(0.0));
            let bare = ping(&session, &keys, &drone, Carrier::Bare, plan, find).await?;
            print_row("bare zenoh", &bare);
            let tacos = ping(&session, &keys, &drone, Carrier::Tacos, plan, find).await?;
            print_row("tacos", &tacos);
            println!(
                "tacos / bare: {:.2}x at p50, {:.2}x at p99 (one-way figures compare the two hosts' clocks)",
                tacos.round_trip.p50 / bare.round_trip.p50,
                tacos.round_trip.p99 / bare.round_trip.p99
            );
            Ok(())
        }
    }
}

fn print_row(name: &str, f: &Figures) {
    let s = |s: &Spread| (s.p50, s.p99);
    let (rp50, rp99) = s(&f.round_trip);
    let (op50, op99) = s(&f.out);
    let (bp50, bp99) = s(&f.back);
    println!(
        "{name:<11} {rp50:>8.1} {rp99:>8.1} {:>8.1} | {op50:>8.1} {op99:>8.1} | {bp50:>8.1} {bp99:>8.1} | {:>9.0} {:>5}",
        f.round_trip.max, f.per_second, f.lost
    );
}

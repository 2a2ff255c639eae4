//! `tacos-router`: the swarm's zenoh router (see `tacos_bus::router`). It reports what its access
//! control refused, per principal, kind of message and key, every few seconds while new
//! refusals come (zenoh itself drops them silently).

use std::path::PathBuf;
use std::time::Duration;
use tacos_bus::router::refusals::{Counts, RefusalCounter};
use tracing_subscriber::prelude::*;

/// How often new refusals are reported.
const REPORT_PERIOD: Duration = Duration::from_secs(2);

/// Usage: tacos-router --zenoh-config FILE
fn config_path() -> Result<PathBuf, String> {
    let mut args = std::env::args().skip(1);
    match (args.next().as_deref(), args.next(), args.next()) {
        (Some("--zenoh-config"), Some(path), None) => Ok(PathBuf::from(path)),
        _ => Err("usage: tacos-router --zenoh-config FILE (see deploy/zenoh/router.json5)".into()),
    }
}

fn main() -> std::process::ExitCode {
    let refusals = RefusalCounter::default();
    let filter =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_filter(filter),
        )
        .with(refusals.layer())
        .init();
    match run(refusals) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("tacos-router: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(refusals: RefusalCounter) -> Result<(), String> {
    let path = config_path()?;
    let config = tacos_bus::router::load(&path).map_err(|e| e.to_string())?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| format!("starting the async runtime: {e}"))?;
    runtime.block_on(async {
        let session = tacos_bus::router::open(config)
            .await
            .map_err(|e| e.to_string())?;
        tracing::info!(zid = %session.zid(), config = %path.display(), "router up");
        let mut terminate =
            tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
                .map_err(|e| format!("SIGTERM handler: {e}"))?;
        let mut reported = Counts::new();
        let mut tick = tokio::time::interval(REPORT_PERIOD);
        loop {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => break,
                _ = terminate.recv() => break,
                _ = tick.tick() => report(&refusals.counts(), &mut reported),
            }
        }
        report(&refusals.counts(), &mut reported);
        tracing::info!("router stopping");
        session.close().await.map_err(|e| e.to_string())
    })
}

/// Logs every count that grew since the last report.
fn report(now: &Counts, reported: &mut Counts) {
    for ((principal, what, key), n) in now {
        let before = reported.get(&(principal.clone(), what.clone(), key.clone()));
        if before != Some(n) {
            tracing::warn!(
                principal = %principal,
                kind = %what,
                key = %key,
                total = n,
                new = n - before.copied().unwrap_or(0),
                "refused by the access control"
            );
        }
    }
    *reported = now.clone();
}

//! `tacos-router`: the swarm's zenoh router (see `tacos_bus::router`).

use std::path::PathBuf;

/// Usage: tacos-router --zenoh-config FILE
fn config_path() -> Result<PathBuf, String> {
    let mut args = std::env::args().skip(1);
    match (args.next().as_deref(), args.next(), args.next()) {
        (Some("--zenoh-config"), Some(path), None) => Ok(PathBuf::from(path)),
        _ => Err("usage: tacos-router --zenoh-config FILE (see deploy/zenoh/router.json5)".into()),
    }
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("tacos-router: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run() -> Result<(), String> {
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
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = terminate.recv() => {}
        }
        tracing::info!("router stopping");
        session.close().await.map_err(|e| e.to_string())
    })
}

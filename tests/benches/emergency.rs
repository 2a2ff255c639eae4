//! How long `land all` and `hold all` take to reach a whole swarm (a program that prints its
//! figures; nothing here asserts a speed).
//!
//! A simulated swarm of 20 drones (the city map, the simulator, a writer and an onboard per
//! drone: 41 processes beside this one) is taken off; then the pilot's line is submitted the
//! way the terminal submits it (`PilotInput::submit`: the directive, the gate, concurrent puts,
//! the mission log), and the clock stops when every drone's own status reports the land or hold
//! under way (running or done). `hold all` is repeated while the swarm hovers; each `land all`
//! lands the swarm, which is then taken off again.
//!
//! The drones' processes are the ones the demo runs (`cargo build --workspace --bins`, in
//! `target/debug`, or `$TACOS_BIN_DIR`). Run alone on the machine:
//! `cargo build --workspace --bins && cargo bench --bench emergency`.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tacos_ground::direct::run_actions;
use tacos_ground::mission::PilotInput;
use tacos_ground::mission::log::MissionLog;
use tacos_ground::safety::SafetyGate;
use tacos_shared::action::Action;
use tacos_shared::messages::DroneStatus;
use tacos_shared::{DroneId, DroneMode};
use tacos_tests::SimSwarm;

const DRONES: usize = 20;
const HOLD_RUNS: usize = 30;
const LAND_RUNS: usize = 6;

fn percentile(sorted: &[f64], p: f64) -> f64 {
    let idx = ((sorted.len().saturating_sub(1)) as f64 * p).round() as usize;
    sorted.get(idx).copied().unwrap_or(f64::NAN)
}

fn report(name: &str, mut reached: Vec<f64>, mut sent: Vec<f64>) {
    reached.sort_by(f64::total_cmp);
    sent.sort_by(f64::total_cmp);
    println!(
        "emergency {name} drones={DRONES} runs={} p50_ms={:.1} p99_ms={:.1} max_ms={:.1} sent_p50_ms={:.1} sent_max_ms={:.1}",
        reached.len(),
        percentile(&reached, 0.5),
        percentile(&reached, 0.99),
        reached.last().copied().unwrap_or(f64::NAN),
        percentile(&sent, 0.5),
        sent.last().copied().unwrap_or(f64::NAN),
    );
}

/// The sequence number of each drone's current action (0 when it has none).
fn current_seqs(swarm: &SimSwarm, ids: &[DroneId]) -> HashMap<DroneId, u64> {
    let view = swarm.link.view();
    ids.iter()
        .map(|d| {
            let seq = view
                .get(d)
                .and_then(|e| e.status.as_ref())
                .and_then(|s| s.action.as_ref())
                .map_or(0, |a| a.seq);
            (d.clone(), seq)
        })
        .collect()
}

/// Submits `line` and returns (ms until `submit` returned: sent and logged, ms until every
/// drone reported `action` under way).
async fn time_command(
    swarm: &SimSwarm,
    input: &PilotInput,
    ids: &[DroneId],
    line: &str,
    action: Action,
) -> anyhow::Result<(f64, f64)> {
    let before = current_seqs(swarm, ids);
    let under_way = |s: &DroneStatus| {
        s.action.as_ref().is_some_and(|a| {
            a.action == action
                && a.seq > before.get(&s.drone).copied().unwrap_or(0)
                && !matches!(a.state, tacos_shared::messages::ActionState::Failed(_))
        })
    };
    let start = Instant::now();
    // The drones are watched while the command goes out: a drone may report before the
    // ground has finished its bookkeeping.
    let submitted = async {
        input
            .submit(line)
            .await
            .map_err(|e| anyhow::anyhow!("{line}: {e}"))?;
        anyhow::Ok(start.elapsed())
    };
    let reached = async {
        swarm
            .link
            .wait_for_drones(ids, Duration::from_secs(10), under_way)
            .await?;
        anyhow::Ok(start.elapsed())
    };
    let (sent, reached) = tokio::join!(submitted, reached);
    Ok((sent?.as_secs_f64() * 1e3, reached?.as_secs_f64() * 1e3))
}

async fn take_off(swarm: &SimSwarm, gate: &SafetyGate, ids: &[DroneId]) -> anyhow::Result<()> {
    let all: Vec<_> = ids
        .iter()
        .map(|d| (d.clone(), Action::ArmTakeoff))
        .collect();
    run_actions(&swarm.link, gate, &all, None, Duration::from_secs(120)).await?;
    Ok(())
}

async fn bench(swarm: &SimSwarm) -> anyhow::Result<()> {
    let names: Vec<String> = swarm
        .scenario
        .drones
        .iter()
        .take(DRONES)
        .map(|d| d.id.to_string())
        .collect();
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    let ids = swarm.wait_on_the_ground(&names).await?;
    let gate = SafetyGate::new(swarm.scenario.clone());
    let log_path =
        std::env::temp_dir().join(format!("tacos-emergency-{}.jsonl", std::process::id()));
    let log = Arc::new(MissionLog::create(&log_path)?);
    let (updates, _updates) = tokio::sync::mpsc::unbounded_channel();
    let (input, _inputs) = PilotInput::new(swarm.link.clone(), gate.clone(), log, updates);
    take_off(swarm, &gate, &ids).await?;

    let (mut sent, mut reached) = (Vec::new(), Vec::new());
    for _ in 0..HOLD_RUNS {
        let (s, r) = time_command(swarm, &input, &ids, "hold all", Action::Hold).await?;
        sent.push(s);
        reached.push(r);
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    report("hold_all", reached, sent);

    let (mut sent, mut reached) = (Vec::new(), Vec::new());
    for run in 0..LAND_RUNS {
        let (s, r) = time_command(swarm, &input, &ids, "land all", Action::Land).await?;
        sent.push(s);
        reached.push(r);
        swarm
            .link
            .wait_for_drones(&ids, Duration::from_secs(120), |s| {
                s.mode == DroneMode::Idle && !s.armed
            })
            .await?;
        if run + 1 < LAND_RUNS {
            take_off(swarm, &gate, &ids).await?;
        }
    }
    report("land_all", reached, sent);
    let _ = std::fs::remove_file(&log_path);
    Ok(())
}

fn main() -> anyhow::Result<()> {
    // The swarm's processes are the demo's build, not this program's profile.
    let bin_dir = match std::env::var_os("TACOS_BIN_DIR") {
        Some(dir) => std::path::PathBuf::from(dir),
        None => std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/debug"),
    };
    anyhow::ensure!(
        bin_dir.join("tacos-onboard").exists(),
        "no TACOS binaries in {}: run `cargo build --workspace --bins` first, or set TACOS_BIN_DIR",
        bin_dir.display()
    );
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let swarm =
            SimSwarm::start_with("emergency", "city", DRONES, |c| c.bin_dir = bin_dir).await?;
        let result = bench(&swarm).await;
        swarm.stop().await;
        result
    })
}

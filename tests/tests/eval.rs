//! The evaluation harness on real simulated swarms, with a stand-in model that answers from its
//! prompt: one that plays a good plan for Task 1 (search every car, give a lost drone's cars to
//! another) succeeds, with the injected failure and a replan on the way; one that plays a bad
//! plan (search the villas) fails as soon as its plan completes without a detection.

use serde_json::{Value, json};
use std::sync::Arc;
use std::time::Duration;
use tacos_ground::eval::TaskSpec;
use tacos_ground::eval::results::Status;
use tacos_ground::eval::run::{RunPlan, run_once};
use tacos_ground::mission::log::{self, Record};
use tacos_ground::mission::{Mode, ModelAids};
use tacos_llm::{ChatRequest, LlmError};
use tacos_shared::scenario::Scenario;
use tacos_shared::world::LandmarkKind;
use tacos_tests::prompt_text::{plan_lines, request_text, swarm_lines};
use tacos_tests::{PolicyBackend, within};

fn call(task: &str, drone: &str, target: &str) -> Value {
    json!({ "task": task, "drone": drone, "action": "goto", "target": target, "xyz": null })
}

/// A stand-in model. The Coordinator spreads `places` over the flying drones (round robin) and,
/// on an automatic replan, gives a lost drone's unfinished subtasks to a flying one; the
/// Supervisor starts every subtask whose drone is free.
fn policy(places: Vec<String>) -> impl Fn(&ChatRequest) -> Result<String, LlmError> + Send + Sync {
    move |request: &ChatRequest| {
        let system = &request.messages[0].content;
        let user = request_text(request);
        let swarm = swarm_lines(user);
        let flying: Vec<&String> = swarm
            .iter()
            .filter(|(_, m, _, _)| m == "flying")
            .map(|(d, _, _, _)| d)
            .collect();
        if system.starts_with("You are the Coordinator") {
            if user.contains("(automatic replan)") {
                let plan: Vec<Value> = plan_lines(user)
                    .into_iter()
                    .filter(|(_, _, _, _, status)| status != "done")
                    .enumerate()
                    .map(|(i, (task, drone, _, target, _))| {
                        let drone = if flying.contains(&&drone) || flying.is_empty() {
                            drone
                        } else {
                            flying[i % flying.len()].clone()
                        };
                        call(&task, &drone, &target)
                    })
                    .collect();
                return Ok(json!({ "reasoning": "Give the lost drone's places to the others.", "plan": plan }).to_string());
            }
            if flying.is_empty() {
                return Err(LlmError::Generation("no flying drone in the prompt".into()));
            }
            let plan: Vec<Value> = places
                .iter()
                .enumerate()
                .map(|(i, place)| call(&format!("T{}", i + 1), flying[i % flying.len()], place))
                .collect();
            return Ok(json!({ "reasoning": "Search the places, spread over the flying drones.", "plan": plan }).to_string());
        }
        let mut actions: Vec<Value> = Vec::new();
        for (task, drone, _, target, status) in plan_lines(user) {
            if status != "not started" && !status.starts_with("failed") {
                continue;
            }
            let free = swarm
                .iter()
                .any(|(d, m, busy, _)| *d == drone && m == "flying" && !busy);
            if free && !actions.iter().any(|a| a["drone"] == drone.as_str()) {
                actions.push(call(&task, &drone, &target));
            }
        }
        let complete = plan_lines(user).iter().all(|(_, _, _, _, s)| s == "done");
        Ok(json!({ "reasoning": "Start what can start now.", "actions": actions, "plan_complete": complete }).to_string())
    }
}

fn landmarks(kind: LandmarkKind) -> anyhow::Result<Vec<String>> {
    Ok(Scenario::builtin("city")?
        .world
        .landmarks
        .iter()
        .filter(|l| l.kind == kind)
        .map(|l| l.name.clone())
        .collect())
}

fn plan(places: Vec<String>, tag: &str) -> anyhow::Result<RunPlan> {
    let task = TaskSpec::load("find-suspect")?;
    let scenario = Scenario::builtin(&task.scenario)?;
    let drones = 4;
    let hiding_place = task.validate(&scenario, drones)?;
    Ok(RunPlan {
        task,
        scenario,
        hiding_place,
        mode: Mode::Tacos,
        drones,
        run: 0,
        seed: 1,
        temperature: 0.0,
        time_limit: Duration::from_secs(240),
        backend: Arc::new(PolicyBackend::new(policy(places))),
        aids: ModelAids::small(),
        log_path: std::env::temp_dir().join(format!("{}.jsonl", tacos_tests::unique_swarm(tag))),
        cycle_timeout: Duration::from_secs(3),
        sim_speed: 1.0,
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_good_plan_finds_the_suspect_despite_the_failure() -> anyhow::Result<()> {
    let plan = plan(landmarks(LandmarkKind::Car)?, "evalgood")?;
    let log_path = plan.log_path.clone();
    let lock = Arc::new(tokio::sync::Mutex::new(()));
    let record = within("a good run", Duration::from_secs(330), run_once(plan, lock)).await?;
    assert_eq!(record.status, Status::Success, "{record:#?}");
    assert!(record.detected_by.is_some(), "{record:#?}");
    assert!(
        record
            .fault
            .as_deref()
            .is_some_and(|f| f.contains("power loss")),
        "the failure was injected: {record:#?}"
    );
    assert!(record.cycles >= 2 && record.model_calls >= 3, "{record:#?}");
    assert_eq!(
        (record.separation_breaches, record.obstacle_breaches),
        (0, 0)
    );
    let lines = log::read(&log_path)?;
    assert!(
        lines
            .iter()
            .any(|l| matches!(&l.record, Record::Replan { .. })),
        "the lost drone made the Coordinator replan"
    );
    // The run stopped at the detection, not at the time limit.
    assert!(record.elapsed_s < 240.0, "{record:#?}");
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_plan_fails_as_soon_as_it_completes() -> anyhow::Result<()> {
    let villas: Vec<String> = landmarks(LandmarkKind::Villa)?
        .into_iter()
        .take(4)
        .collect();
    let plan = plan(villas, "evalbad")?;
    let lock = Arc::new(tokio::sync::Mutex::new(()));
    let record = within("a bad run", Duration::from_secs(330), run_once(plan, lock)).await?;
    assert_eq!(record.status, Status::Failure, "{record:#?}");
    assert!(record.reason.contains("suspect not found"), "{record:#?}");
    assert!(record.detected_by.is_none());
    assert!(
        record.elapsed_s < 240.0,
        "decided when the plan completed: {record:#?}"
    );
    Ok(())
}

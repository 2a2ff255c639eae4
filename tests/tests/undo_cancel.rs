//! `cancel` and `undo`, the pilot's direct commands for a plan under way: `cancel` ends the plan
//! and holds the drones it moves; `undo` flies the drones the last instruction moved back to
//! where they were before it, through the gate and the planner. Both are carried out at once,
//! without a model call. A simulated swarm and a stand-in model that plans like one.

use serde_json::json;
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;
use tacos_ground::mission::log::{self, Record};
use tacos_ground::mission::{EventTopic, MissionConfig, MissionHandle, MissionUpdate};
use tacos_ground::safety::SafetyGate;
use tacos_llm::{ChatRequest, LlmError};
use tacos_shared::action::Action;
use tacos_shared::{DroneId, Vec3};
use tacos_tests::prompt_text::first_offered_per_drone;
use tacos_tests::{PolicyBackend, SimSwarm, told, within};

/// Alfa to car_11 and bravo to car_1, as a Coordinator would plan "inspect the cars"; the
/// Supervisor starts whatever the engine offers.
fn policy(request: &ChatRequest) -> Result<String, LlmError> {
    let call = |task: &str, drone: &str, target: &str| json!({ "task": task, "drone": drone, "action": "goto", "target": target, "xyz": null });
    if request.messages[0]
        .content
        .starts_with("You are the Coordinator")
    {
        let plan = [call("T1", "alfa", "car_11"), call("T2", "bravo", "car_1")];
        return Ok(json!({ "reasoning": "Each inspects a car.", "plan": plan }).to_string());
    }
    let actions = first_offered_per_drone(request);
    Ok(
        json!({ "reasoning": "Start the gotos.", "actions": actions, "plan_complete": false })
            .to_string(),
    )
}

fn positions(sim: &SimSwarm, ids: &[DroneId]) -> BTreeMap<DroneId, Vec3> {
    let view = sim.link.view();
    ids.iter()
        .filter_map(|d| Some((d.clone(), view.get(d)?.status.as_ref()?.position)))
        .collect()
}

/// Waits until `ok` holds for the drones' reported positions and actions.
async fn until_swarm(
    sim: &SimSwarm,
    what: &str,
    limit: Duration,
    ok: impl Fn(&tacos_ground::swarm::SwarmView) -> bool,
) -> anyhow::Result<()> {
    within(what, limit, async {
        let mut version = sim.link.changes();
        loop {
            if ok(&sim.link.view()) {
                return;
            }
            let _ = version.recv().await;
        }
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_holds_a_plan_s_drones_and_undo_flies_them_back() -> anyhow::Result<()> {
    let sim = SimSwarm::start("undo", "city", 2).await?;
    let result = async {
        let ids = sim.wait_on_the_ground(&["alfa", "bravo"]).await?;
        let gate = SafetyGate::new(sim.scenario.clone());
        sim.take_off(&gate, &ids).await?;
        let before = positions(&sim, &ids);

        let (log_path, log) = tacos_tests::temp_mission_log("undo")?;
        let MissionHandle {
            input,
            mut updates,
            task,
        } = MissionHandle::start(
            MissionConfig::default(),
            Arc::new(PolicyBackend::new(policy)),
            gate,
            sim.link.clone(),
            log.clone(),
        )
        .await?;

        // Nothing to undo before the models carried anything out.
        input.submit("undo").await?;
        told(&mut updates, "nothing to undo").await?;

        input
            .submit("alfa inspect car_11, bravo inspect car_1")
            .await?;
        until_swarm(
            &sim,
            "both drones 3 m on their way",
            Duration::from_secs(60),
            |view| {
                ids.iter().all(|d| {
                    view.get(d)
                        .and_then(|e| e.status.as_ref())
                        .is_some_and(|s| (s.position - before[d]).norm() > 3.0)
                })
            },
        )
        .await?;

        input.submit("cancel").await?;
        // The engine ends its plan as soon as the override rises, which may be told before the
        // command's own line (that waits for the holds to be sent).
        let (mut cancelled, mut ended) = (None, None);
        within(
            "the cancel and the plan's end",
            Duration::from_secs(10),
            async {
                while let Some(u) = updates.recv().await {
                    if let MissionUpdate::Event { topic, text } = u {
                        if topic == EventTopic::PlanEnded {
                            ended = Some(text);
                        } else if text.contains("cancelled") {
                            cancelled = Some(text);
                        }
                    }
                    if cancelled.is_some() && ended.is_some() {
                        return;
                    }
                }
            },
        )
        .await?;
        let cancelled = cancelled.unwrap_or_default();
        assert!(
            cancelled.contains("hold() sent to alfa, bravo"),
            "{cancelled}"
        );
        assert_eq!(
            ended.as_deref(),
            Some("plan ended: interrupted by a direct command")
        );
        until_swarm(
            &sim,
            "both drones holding",
            Duration::from_secs(10),
            |view| {
                ids.iter().all(|d| {
                    view.get(d)
                        .and_then(|e| e.status.as_ref())
                        .and_then(|s| s.action.as_ref())
                        .is_some_and(|p| p.action == Action::Hold)
                })
            },
        )
        .await?;
        let held = positions(&sim, &ids);
        for d in &ids {
            let away = (held[d] - before[d]).norm();
            assert!(away > 3.0, "{d} held {away:.1} m from where it was");
        }

        input.submit("undo").await?;
        let undoing = told(&mut updates, "undoing").await?;
        assert!(undoing.contains("alfa: fly back to"), "{undoing}");
        until_swarm(&sim, "both drones back", Duration::from_secs(90), |view| {
            ids.iter().all(|d| {
                view.get(d)
                    .and_then(|e| e.status.as_ref())
                    .is_some_and(|s| (s.position - before[d]).norm() < 1.0)
            })
        })
        .await?;
        for _ in &ids {
            told(&mut updates, "back where it was").await?;
        }
        input.submit("undo").await?;
        let again = told(&mut updates, "nothing to undo").await?;
        assert!(again.contains("undone already"), "{again}");

        drop(input);
        within("the mission to end", Duration::from_secs(10), task.join()).await??;
        let lines = log::read(&log_path)?;
        // The undo's gotos are the points the drones were at, checked at the gate and sent.
        let gotos: Vec<String> = lines
            .iter()
            .filter_map(|l| match &l.record {
                Record::ActionSent {
                    action, task: None, ..
                } if action.starts_with("goto") => Some(action.clone()),
                _ => None,
            })
            .collect();
        assert_eq!(gotos.len(), 2, "{gotos:?}");
        let directs: Vec<&str> = lines
            .iter()
            .filter_map(|l| match &l.record {
                Record::Direct { text, .. } => Some(text.as_str()),
                _ => None,
            })
            .collect();
        assert_eq!(directs, ["undo", "cancel", "undo", "undo"]);
        let _ = std::fs::remove_file(&log_path);
        anyhow::Ok(())
    }
    .await;
    sim.stop().await;
    result
}

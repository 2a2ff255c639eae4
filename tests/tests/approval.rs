//! `--confirm`: every Coordinator plan is held for the pilot, shown call by call with what the
//! checks say; nothing moves until the pilot approves; a dropped call never flies; a rejection
//! goes back to the Coordinator with the pilot's words. A simulated swarm and a stand-in model.

use serde_json::json;
use std::sync::Arc;
use std::time::Duration;
use tacos_ground::mission::log::{self, Record};
use tacos_ground::mission::{MissionConfig, MissionHandle, MissionUpdate};
use tacos_ground::safety::SafetyGate;
use tacos_llm::{ChatRequest, LlmError};
use tacos_shared::action::Action;
use tacos_tests::prompt_text::first_offered_per_drone;
use tacos_tests::{PolicyBackend, SimSwarm, told, within};

const REJECTED: &str = "The pilot rejected your plan";

/// Alfa to car_11 and bravo to car_1; after a rejection, alfa to car_12 alone.
fn policy(request: &ChatRequest) -> Result<String, LlmError> {
    let call = |task: &str, drone: &str, target: &str| json!({ "task": task, "drone": drone, "action": "goto", "target": target, "xyz": null });
    if request.messages[0]
        .content
        .starts_with("You are the Coordinator")
    {
        let rejected = request
            .messages
            .last()
            .is_some_and(|m| m.content.contains(REJECTED));
        let plan = if rejected {
            vec![call("T1", "alfa", "car_12")]
        } else {
            vec![call("T1", "alfa", "car_11"), call("T2", "bravo", "car_1")]
        };
        return Ok(json!({ "reasoning": "Each inspects a car.", "plan": plan }).to_string());
    }
    let actions = first_offered_per_drone(request);
    Ok(
        json!({ "reasoning": "Start the gotos.", "actions": actions, "plan_complete": false })
            .to_string(),
    )
}

fn gotos_sent(lines: &[log::Line]) -> Vec<(String, String)> {
    lines
        .iter()
        .filter_map(|l| match &l.record {
            Record::ActionSent { drone, action, .. } if action.starts_with("goto") => {
                Some((drone.clone(), action.clone()))
            }
            _ => None,
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_held_plan_flies_only_once_approved_without_its_dropped_calls() -> anyhow::Result<()> {
    let sim = SimSwarm::start("approve", "city", 2).await?;
    let result = async {
        let ids = sim.wait_on_the_ground(&["alfa", "bravo"]).await?;
        let gate = SafetyGate::new(sim.scenario.clone());
        sim.take_off(&gate, &ids).await?;

        let (log_path, log) = tacos_tests::temp_mission_log("approve")?;
        let backend = Arc::new(PolicyBackend::new(policy));
        let cfg = MissionConfig {
            confirm: true,
            ..MissionConfig::default()
        };
        let MissionHandle {
            input,
            mut updates,
            task,
        } = MissionHandle::start(cfg, backend.clone(), gate, sim.link.clone(), log.clone()).await?;

        input
            .submit("alfa inspect car_11, bravo inspect car_1")
            .await?;
        let held = told(&mut updates, "awaits your approval").await?;
        assert!(
            held.contains("T1 alfa goto(car_11): could start now"),
            "{held}"
        );
        assert!(
            held.contains("T2 bravo goto(car_1): could start now"),
            "{held}"
        );
        // Held: over two seconds, nothing is sent and no drone takes an action.
        tokio::time::sleep(Duration::from_secs(2)).await;
        assert!(gotos_sent(&log::read(&log_path)?).is_empty());
        assert!(ids.iter().all(|d| {
            sim.link
                .view()
                .get(d)
                .and_then(|e| e.status.as_ref())
                .and_then(|s| s.action.as_ref())
                .is_none_or(|p| p.action == Action::ArmTakeoff)
        }));

        input.submit("drop T9").await?;
        let refused = told(&mut updates, "nothing dropped").await?;
        assert!(refused.contains("its tasks: T1, T2"), "{refused}");
        // Shown again, whole.
        let held = told(&mut updates, "awaits your approval").await?;
        assert!(held.contains("T2 bravo"), "{held}");
        input.submit("drop T2").await?;
        let held = told(&mut updates, "awaits your approval").await?;
        assert!(!held.contains("T2 bravo"), "{held}");

        input.submit("approve").await?;
        told(&mut updates, "approved").await?;
        within("the plan to complete", Duration::from_secs(90), async {
            while let Some(u) = updates.recv().await {
                if matches!(u, MissionUpdate::PlanComplete { .. }) {
                    return;
                }
            }
        })
        .await?;
        let sent = gotos_sent(&log::read(&log_path)?);
        assert_eq!(sent.len(), 1, "alfa's goto only: {sent:?}");
        assert_eq!(sent[0].0, "alfa");

        // A rejection goes back to the Coordinator with the pilot's words.
        input.submit("alfa inspect car_11 again").await?;
        told(&mut updates, "awaits your approval").await?;
        input
            .submit("reject alfa should look at car_12 instead")
            .await?;
        let held = told(&mut updates, "awaits your approval").await?;
        assert!(held.contains("T1 alfa goto(car_12)"), "{held}");
        let asked = backend
            .requests
            .lock()
            .map_err(|_| anyhow::anyhow!("poisoned"))?
            .iter()
            .any(|r| {
                r.messages.iter().any(|m| {
                    m.content.contains(REJECTED)
                        && m.content.contains("alfa should look at car_12 instead")
                })
            });
        assert!(asked, "the Coordinator was told why");
        // The switch is the pilot's; the plan still held does not fly by itself.
        input.submit("confirm off").await?;
        told(&mut updates, "confirm off").await?;

        drop(input);
        within("the mission to end", Duration::from_secs(10), task.join()).await??;
        let lines = log::read(&log_path)?;
        assert_eq!(gotos_sent(&lines).len(), 1, "nothing else flew");
        assert!(
            lines
                .iter()
                .any(|l| matches!(&l.record, Record::Pilot { text } if text == "approve"))
        );
        let _ = std::fs::remove_file(&log_path);
        anyhow::Ok(())
    }
    .await;
    sim.stop().await;
    result
}

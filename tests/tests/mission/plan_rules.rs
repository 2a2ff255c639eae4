//! How a plan is held to what can be done, on a real simulated swarm: a plan for a drone that is
//! gone, and a forgotten take-off with the aids off. The other rules (failing tasks, lost
//! targets, gotos already done, plans that cannot go on, implied take-offs) are the core's
//! tests (`ground/src/mission/core/tests.rs`, `adopt.rs`), fed inputs and snapshots.

use super::kit::*;
use serde_json::json;
use std::time::Duration;
use tacos_ground::launch::Role;
use tacos_ground::mission::ModelAids;
use tacos_ground::mission::log::{self, Record};
use tacos_llm::ChatRequest;
use tacos_shared::DroneId;
use tacos_tests::prompt_text::request_text;
use tacos_tests::{PolicyBackend, within};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plan_for_a_drone_that_is_gone_is_refused() -> anyhow::Result<()> {
    stopping_after(start("gone").await?, async |run| {
        let bravo = DroneId::new("bravo")?;
        run.sim
            .stack
            .crash(Role::Onboard, Some(&bravo))
            .await
            .ok_or_else(|| anyhow::anyhow!("bravo's onboard was not running"))?;
        within("bravo to be seen gone", Duration::from_secs(10), async {
            while run.sim.link.view().get(&bravo).is_some_and(|e| {
                e.effective_mode(std::time::Instant::now()) != tacos_shared::DroneMode::Unavailable
            }) {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        })
        .await?;
        let plan = json!([call("T1", "bravo", "arm_takeoff", "none")]);
        let (mut updates, lines, log_path, _) =
            run_offered(run, "gonelog", plan, false, "bravo, take off").await?;
        let error = given_up(&mut updates, Duration::from_secs(30)).await?;
        drop(lines);
        assert!(
            error.contains("coordinator")
                && error.contains("bravo is unavailable; the drones available are: alfa, charlie"),
            "{error}"
        );
        let lines = log::read(&log_path)?;
        let sent_back = lines.iter().any(|l| matches!(&l.record, Record::LlmRequest { layer, messages, .. } if layer == "coordinator" && messages.to_string().contains("bravo is unavailable; the drones available are: alfa, charlie")));
        assert!(sent_back, "the plan for bravo was not sent back");
        assert!(!lines.iter().any(|l| matches!(&l.record, Record::Plan { .. })), "a plan was made");
        assert!(sent_tasks(&lines).is_empty());
        anyhow::Ok(())
    })
    .await
}

/// The same forgotten take-off with the small-model aids off (`--aids none`): the engine adds
/// nothing; the rule the aid stands in for refuses the goto, naming the missing take-off, and
/// the Coordinator's repaired plan is the one flown.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_the_aids_off_a_forgotten_take_off_is_refused_by_name_and_the_repair_flies()
-> anyhow::Result<()> {
    stopping_after(start("noaids").await?, async |run| {
        let supervisor = offered_policy(json!([]), false);
        let policy = move |request: &ChatRequest| {
            if !request.messages[0].content.starts_with("You are the Coordinator") {
                return supervisor(request);
            }
            let told = request_text(request).contains("add `alfa arm_takeoff` before it")
                || request.messages.iter().any(|m| m.content.contains("add `alfa arm_takeoff` before it"));
            let mut plan = vec![call("T1", "alfa", "goto", "car_11"), call("T2", "bravo", "arm_takeoff", "none")];
            if told {
                plan.insert(0, call("T3", "alfa", "arm_takeoff", "none"));
            }
            Ok(json!({ "reasoning": "As the pilot said.", "plan": plan }).to_string())
        };
        let (mut updates, lines, log_path, _) = run_with_aids(run, "noaidslog", PolicyBackend::new(policy), "alfa, to car_11", ModelAids::none()).await?;
        plan_complete(&mut updates, Duration::from_secs(90)).await?;
        drop(lines);
        let lines = log::read(&log_path)?;
        let rejected: Vec<&String> = lines.iter().filter_map(|l| match &l.record { Record::GateRejected { call, .. } => Some(call), _ => None }).collect();
        assert_eq!(rejected, ["T1 alfa goto(car_11): alfa is on the ground and the plan never takes it off: add `alfa arm_takeoff` before it"]);
        let sent = sent_tasks(&lines);
        assert_eq!(sent.iter().filter(|(_, d)| d == "alfa").map(|(t, _)| t.as_str()).collect::<Vec<_>>(), ["T3", "T1"], "{sent:?}");
        assert!(!lines.iter().any(|l| matches!(&l.record, Record::AidFired { .. })), "an aid fired with the aids off");
        assert!(lines.iter().any(|l| matches!(&l.record, Record::MissionStart { aids, .. } if *aids == ModelAids::none())));
        anyhow::Ok(())
    })
    .await
}

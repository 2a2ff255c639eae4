//! The language-model layers on a real simulated swarm, with a stand-in model that answers from
//! its prompt: broken replies are repaired, nothing the gate rejects reaches a drone, the
//! Supervisor sequences a multi-step plan over several cycles, and a drone killed mid-plan makes
//! the Coordinator replan (offered, and held to, the drones left) and give its subtask to another
//! drone.

use serde_json::{Value, json};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;
use tacos_ground::launch::Role;
use tacos_ground::mission::log::{self, MissionLog, Record, RefusedBy};
use tacos_ground::mission::{Mission, MissionConfig, MissionUpdate, Mode};
use tacos_ground::safety::SafetyGate;
use tacos_shared::DroneId;
use tacos_tests::PolicyBackend;
use tokio::sync::mpsc;

#[path = "mission/kit.rs"]
mod kit;
#[path = "mission/model_replies.rs"]
mod model_replies;
#[path = "mission/plan_rules.rs"]
mod plan_rules;

use kit::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn broken_replies_are_repaired_and_the_plan_runs_over_several_cycles() -> anyhow::Result<()> {
    stopping_after(start("mission").await?, async |run| {
        let link = run.sim.link.clone();
        launch_mission(run, link.clone(), true).await?;
        run.lines.send("all drones take off, then inspect the cars near the pads".into()).await?;
        plan_complete(&mut run.updates, Duration::from_secs(120)).await?;
        let lines = log::read(&run.log_path)?;
        let sent = sent_tasks(&lines);
        let mut tasks: Vec<&str> = sent.iter().map(|(t, _)| t.as_str()).collect();
        tasks.sort();
        assert_eq!(tasks, ["T1", "T2", "T3", "T4", "T5", "T6"], "exactly the checked plan was sent: {sent:?}");
        let rejected: Vec<&String> = lines
            .iter()
            .filter_map(|l| match &l.record {
                Record::GateRejected { call, .. } => Some(call),
                _ => None,
            })
            .collect();
        for expected in ["zulu", "18.0, 18.0, 20.0", "T4 alfa goto(car_11)", "ghost"] {
            assert!(rejected.iter().any(|r| r.contains(expected)), "no rejection mentioning {expected:?}: {rejected:?}");
        }
        // The goto refused before take-off was sent later, once alfa flew: never before.
        let first_t4 = lines.iter().position(|l| matches!(&l.record, Record::ActionSent { task: Some(t), .. } if t == "T4"));
        let alfa_up = lines.iter().position(|l| matches!(&l.record, Record::ActionOutcome { drone, outcome, task: Some(t), .. } if drone == "alfa" && t == "T1" && outcome == "done"));
        let (Some(first_t4), Some(alfa_up)) = (first_t4, alfa_up) else {
            anyhow::bail!("the log lacks T4's send ({first_t4:?}) or alfa's take-off done ({alfa_up:?})");
        };
        assert!(first_t4 > alfa_up, "T4 was sent before alfa's take-off finished");
        let outcomes: Vec<&String> = lines.iter().filter_map(|l| match &l.record { Record::ActionOutcome { outcome, .. } => Some(outcome), _ => None }).collect();
        assert!(outcomes.iter().all(|o| *o == "done"), "every sent action succeeded: {outcomes:?}");
        let cycles = lines.iter().filter(|l| matches!(l.record, Record::SupervisorCycle { .. })).count();
        assert!(cycles >= 2, "the plan needs at least two supervisor cycles, saw {cycles}");
        // The repair turns carried the reasons back to the model.
        assert!(lines.iter().any(|l| matches!(&l.record, Record::LlmRequest { layer, attempt: 3, .. } if layer == "coordinator")));
        // The default preset of the small-model aids is recorded in the start record.
        assert!(lines.iter().any(|l| matches!(&l.record, Record::MissionStart { aids, .. } if *aids == tacos_ground::mission::ModelAids::small())));
        replays_the_same(&run.log_path, &run.sim.scenario)?;
        anyhow::Ok(())
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drone_killed_mid_plan_has_its_subtask_reassigned() -> anyhow::Result<()> {
    stopping_after(start("replan").await?, async |run| {
        let link = run.sim.link.clone();
        launch_mission(run, link.clone(), false).await?;
        run.lines.send("all drones take off, then inspect the cars near the pads".into()).await?;
        until(&mut run.updates, Duration::from_secs(90), |u| matches!(u, MissionUpdate::Sent { drone, action, .. } if drone == "bravo" && action.starts_with("goto"))).await?;
        let bravo = DroneId::new("bravo")?;
        run.sim.stack.crash(Role::Onboard, Some(&bravo)).await.ok_or_else(|| anyhow::anyhow!("bravo's onboard was not running"))?;
        plan_complete(&mut run.updates, Duration::from_secs(150)).await?;
        let lines = log::read(&run.log_path)?;
        assert!(lines.iter().any(|l| matches!(&l.record, Record::Replan { reason } if reason.contains("bravo"))), "no replan for bravo");
        // The replan's grammar offered only the drones left, and the first reply, which kept
        // bravo's work on bravo, was sent back saying so.
        let schemas = REPLAN_SCHEMAS.lock().map_err(|_| anyhow::anyhow!("poisoned"))?.clone();
        let offered = schemas.first().map(|s| s["properties"]["plan"]["items"]["anyOf"][0]["properties"]["drone"]["enum"].clone());
        assert_eq!(offered, Some(json!(["alfa", "charlie"])), "{schemas:#?}");
        let sent_back = lines.iter().any(|l| matches!(&l.record, Record::LlmRequest { layer, messages, .. } if layer == "coordinator" && messages.as_array().is_some_and(|ms| ms.iter().any(|m| m["content"].as_str().is_some_and(|c| c.contains("bravo is unavailable; the drones available are: alfa, charlie"))))));
        assert!(sent_back, "the replan that kept bravo's work was not sent back");
        let t5: Vec<(String, String)> = sent_tasks(&lines).into_iter().filter(|(t, _)| t == "T5").collect();
        assert_eq!(t5.first().map(|(_, d)| d.as_str()), Some("bravo"));
        let reassigned = t5.iter().find(|(_, d)| d != "bravo").ok_or_else(|| anyhow::anyhow!("T5 never given to another drone: {t5:?}"))?;
        let done = lines.iter().any(|l| matches!(&l.record, Record::ActionOutcome { drone, task: Some(t), outcome, .. } if *drone == reassigned.1 && t == "T5" && outcome == "done"));
        assert!(done, "{} did not finish bravo's T5", reassigned.1);
        replays_the_same(&run.log_path, &run.sim.scenario)?;
        anyhow::Ok(())
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_monolithic_model_is_held_to_its_actions_not_its_claim() -> anyhow::Result<()> {
    stopping_after(start("mnl").await?, async |run| {
        let link = run.sim.link.clone();
        let log_path = std::env::temp_dir().join(format!("{}.jsonl", tacos_tests::unique_swarm("mnllog")));
        let backend = Arc::new(PolicyBackend::new(monolithic_policy(Arc::new(AtomicBool::new(true)))));
        let (tx, mut updates) = mpsc::unbounded_channel();
        // No repairs: the reply with the rejected goto is the one that counts.
        let cfg = MissionConfig { mode: Mode::Mnl, max_repairs: 0, cycle_timeout: Duration::from_secs(3), trace_steps: true, ..MissionConfig::default() };
        let mission = Mission::new(cfg, backend.clone(), SafetyGate::new(run.sim.scenario.clone()), link, Arc::new(MissionLog::create(&log_path)?), tx).await?;
        let (lines, rx) = mpsc::channel(4);
        tokio::spawn(mission.run(rx));
        lines.send("all drones take off".into()).await?;
        plan_complete(&mut updates, Duration::from_secs(90)).await?;
        drop(lines);
        let lines = log::read(&log_path)?;
        // The first request offered take-offs only: every drone was on the ground.
        let requests = backend.requests.lock().map_err(|_| anyhow::anyhow!("poisoned"))?.clone();
        let first = requests.first().and_then(|r| r.schema.as_ref()).ok_or_else(|| anyhow::anyhow!("no schema"))?;
        let offered = first.schema.pointer("/properties/actions/items/anyOf").and_then(Value::as_array).cloned().unwrap_or_default();
        assert_eq!(offered.len(), 3, "one take-off per grounded drone: {offered:?}");
        assert!(offered.iter().all(|a| a["properties"]["action"]["enum"] == json!(["arm_takeoff"])), "{offered:?}");
        // The goto before take-off never left the ground; every drone's take-off did.
        let sent = sent_tasks(&lines);
        // Refused by the safety gate itself (a goto for a drone on the ground), and counted so.
        assert!(lines.iter().any(|l| matches!(&l.record, Record::GateRejected { call, by: RefusedBy::SafetyGate, .. } if call.contains("alfa goto(car_11)"))));
        assert!(log::Tally::of(&lines).gate_refusals >= 1);
        assert!(!lines.iter().any(|l| matches!(&l.record, Record::ActionSent { action, .. } if action.starts_with("goto"))), "{sent:?}");
        let mut drones: Vec<&str> = sent.iter().map(|(_, d)| d.as_str()).collect();
        drones.sort();
        assert_eq!(drones, ["alfa", "bravo", "charlie"]);
        // The first cycle claimed done, but it named a rejected call: the engine completed the
        // instructions only after alfa's take-off, issued in a later cycle, finished.
        let cycles: Vec<bool> = lines.iter().filter_map(|l| match &l.record { Record::SupervisorCycle { plan_complete, .. } => Some(*plan_complete), _ => None }).collect();
        assert!(cycles.len() >= 2 && cycles[0], "{cycles:?}");
        let complete = lines.iter().position(|l| matches!(l.record, Record::PlanComplete { .. }));
        let alfa_up = lines.iter().position(|l| matches!(&l.record, Record::ActionOutcome { drone, outcome, .. } if drone == "alfa" && outcome == "done"));
        assert!(alfa_up.is_some() && complete > alfa_up, "complete at {complete:?}, alfa up at {alfa_up:?}");
        replays_the_same(&log_path, &run.sim.scenario)?;
        anyhow::Ok(())
    })
    .await
}

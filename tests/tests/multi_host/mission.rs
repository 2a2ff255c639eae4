//! The mission engine on the ground host of the multi-host test: a plan that gives bravo work,
//! bravo's host cut off, and the engine's replan that hands bravo's unstarted work to alfa.
//!
//! The model is a stand-in that answers from its prompt (as in `mission.rs`): a real model
//! thinks for tens of seconds on these two cores, longer than the partition lasts.

use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;
use tacos_ground::link::GroundLink;
use tacos_ground::mission::log::{self, MissionLog, Record};
use tacos_ground::mission::{Mission, MissionConfig, MissionUpdate};
use tacos_ground::safety::SafetyGate;
use tacos_llm::{ChatRequest, LlmError};
use tacos_tests::PolicyBackend;
use tacos_tests::prompt_text::{first_offered_per_drone, plan_lines, request_text, swarm_lines};
use tokio::sync::mpsc;

/// What the pilot says: both places named, so the plan stays within them.
pub const INSTRUCTION: &str = "bravo, fly to large_park_north and then to the villa";

fn call(task: &str, drone: &str, action: &str, target: &str) -> Value {
    json!({ "task": task, "drone": drone, "action": action, "target": target, "xyz": null })
}

/// The stand-in model. Coordinator: bravo flies north-east (T1), then west to the villa (T2),
/// away from where alfa hovers; on an automatic replan, the work not yet started of every
/// unavailable drone goes to a drone still flying (bravo's T1, under way when it was cut off,
/// ends where bravo now hovers: nobody else is sent there). Supervisor: each drone starts the
/// first call the engine offers it.
fn model(request: &ChatRequest) -> Result<String, LlmError> {
    let system = &request.messages[0].content;
    let user = request_text(request);
    if system.starts_with("You are the Coordinator") {
        if !user.contains("(automatic replan)") {
            return Ok(json!({
                "reasoning": "Bravo flies to the park, then to the villa.",
                "plan": [
                    call("T1", "bravo", "goto", "large_park_north"),
                    call("T2", "bravo", "goto", "villa"),
                ]
            })
            .to_string());
        }
        let swarm = swarm_lines(user);
        let gone: Vec<&String> = swarm
            .iter()
            .filter(|(_, mode, _, _)| mode == "unavailable")
            .map(|(d, ..)| d)
            .collect();
        let spare = swarm
            .iter()
            .find(|(d, mode, _, _)| mode == "flying" && !gone.contains(&d))
            .map(|(d, ..)| d.clone())
            .unwrap_or_default();
        let plan: Vec<Value> = plan_lines(user)
            .into_iter()
            .filter(|(_, drone, _, _, status)| gone.contains(&drone) && status == "not started")
            .map(|(task, _, action, target, _)| call(&task, &spare, &action, &target))
            .collect();
        return Ok(json!({
            "reasoning": format!("Bravo is lost; {spare} takes what it had not started."),
            "plan": plan
        })
        .to_string());
    }
    let actions = first_offered_per_drone(request);
    Ok(json!({ "reasoning": "Each drone does its next task.", "actions": actions, "plan_complete": false }).to_string())
}

/// A mission running on the ground link.
pub struct Running {
    pub updates: mpsc::UnboundedReceiver<MissionUpdate>,
    lines: Option<mpsc::Sender<String>>,
    task: tokio::task::JoinHandle<tacos_ground::mission::MissionStats>,
    pub log_path: PathBuf,
}

pub async fn start(link: Arc<GroundLink>, gate: SafetyGate, dir: &Path) -> anyhow::Result<Running> {
    let log_path = dir.join("mission.jsonl");
    let (tx, updates) = mpsc::unbounded_channel();
    let cfg = MissionConfig {
        cycle_timeout: Duration::from_secs(3),
        ..MissionConfig::default()
    };
    let mission = Mission::new(
        cfg,
        Arc::new(PolicyBackend::new(model)),
        gate,
        link,
        Arc::new(MissionLog::create(&log_path)?),
        tx,
    )
    .await?;
    let (lines, rx) = mpsc::channel(4);
    let task = tokio::spawn(mission.run(rx));
    lines.send(INSTRUCTION.into()).await?;
    Ok(Running {
        updates,
        lines: Some(lines),
        task,
        log_path,
    })
}

impl Running {
    /// Waits for the first update that `stop` accepts; a mission error fails at once.
    pub async fn until(
        &mut self,
        what: &str,
        limit: Duration,
        mut stop: impl FnMut(&MissionUpdate) -> bool,
    ) -> anyhow::Result<()> {
        let mut seen = Vec::new();
        let found = tokio::time::timeout(limit, async {
            while let Some(u) = self.updates.recv().await {
                if let MissionUpdate::Error(e) = &u {
                    anyhow::bail!("mission error: {e}");
                }
                let done = stop(&u);
                seen.push(u);
                if done {
                    return Ok(());
                }
            }
            anyhow::bail!("the mission ended")
        })
        .await;
        match found {
            Ok(result) => result.map_err(|e| anyhow::anyhow!("{what}: {e}; updates: {seen:#?}")),
            Err(_) => anyhow::bail!("{what}: not within {limit:?}; updates: {seen:#?}"),
        }
    }

    /// Ends the pilot's input and waits for the mission to let go of the ground link.
    pub async fn stop(mut self) -> anyhow::Result<()> {
        self.lines = None;
        tokio::time::timeout(Duration::from_secs(10), &mut self.task)
            .await
            .map_err(|_| anyhow::anyhow!("the mission did not end"))??;
        Ok(())
    }
}

/// What the mission log shows of the replan: bravo got T1 only, the replan names bravo, and alfa
/// was sent T2 and finished it. Returns, in seconds after bravo's T1 was sent (the cut), when
/// the replan began and when alfa finished T2.
pub fn replanned(log_path: &Path) -> anyhow::Result<(f64, f64)> {
    let lines = log::read(log_path)?;
    let sent: Vec<(String, String, f64)> = lines
        .iter()
        .filter_map(|l| match &l.record {
            Record::ActionSent { drone, task, .. } => {
                Some((task.clone().unwrap_or_default(), drone.clone(), l.t))
            }
            _ => None,
        })
        .collect();
    let replan_at = lines
        .iter()
        .find(|l| matches!(&l.record, Record::Replan { reason } if reason.contains("bravo")))
        .map(|l| l.t)
        .ok_or_else(|| anyhow::anyhow!("no replan for bravo in the mission log"))?;
    let to_bravo: Vec<&(String, String, f64)> =
        sent.iter().filter(|(_, d, _)| d == "bravo").collect();
    let [(task, _, cut_at)] = to_bravo[..] else {
        anyhow::bail!("bravo was not sent exactly one action: {sent:?}");
    };
    anyhow::ensure!(task == "T1", "bravo was sent {task}, not T1: {sent:?}");
    anyhow::ensure!(
        sent.iter().any(|(t, d, _)| t == "T2" && d == "alfa"),
        "T2 never given to alfa: {sent:?}"
    );
    let done_at = lines
        .iter()
        .find(|l| {
            matches!(&l.record, Record::ActionOutcome { drone, task: Some(t), outcome, .. }
                if drone == "alfa" && t == "T2" && outcome == "done")
        })
        .map(|l| l.t)
        .ok_or_else(|| anyhow::anyhow!("alfa did not finish T2: {sent:?}"))?;
    Ok((replan_at - cut_at, done_at - cut_at))
}

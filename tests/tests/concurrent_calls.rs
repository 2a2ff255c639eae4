//! The mission goes on while a model thinks: with the Coordinator's call held (a slow model), a
//! drone lost meanwhile is told to the pilot at once, and a second instruction waits for the
//! Coordinator instead of being lost or answered out of order; released, the first plan is
//! adopted and the second call is asked with that plan pending and the lost drone unavailable.
//! And `land all` typed while the call is held drops it and the instruction queued behind it:
//! nothing takes the drones up again. tacos-sitl, three tacos-px4 + tacos-onboard pairs and the
//! mission engine on loopback.

use std::sync::{Arc, Mutex};
use std::time::Duration;
use tacos_ground::launch::Role;
use tacos_ground::mission::{EventTopic, Mission, MissionConfig, MissionUpdate, Overtaken};
use tacos_ground::safety::SafetyGate;
use tacos_llm::{BoxFuture, ChatReply, ChatRequest, LlmBackend, LlmError, Usage};
use tacos_tests::{SimSwarm, id, within};
use tokio::sync::{Notify, mpsc, watch};

/// A model whose first Coordinator call is held until the test releases it; it records every
/// Coordinator request's last message (the request with the swarm, the plan and the
/// instruction).
struct HeldCoordinator {
    /// Set while the first Coordinator call is held.
    holding: watch::Sender<bool>,
    release: Notify,
    coordinator_requests: Mutex<Vec<String>>,
}

const FIRST_PLAN: &str = r#"{"reasoning":"Alfa inspects car_11.","plan":[{"task":"T1","drone":"alfa","action":"goto","target":"car_11","xyz":null}]}"#;
const SECOND_PLAN: &str = r#"{"reasoning":"Alfa goes on; bravo inspects car_12.","plan":[{"task":"T1","drone":"alfa","action":"goto","target":"car_11","xyz":null},{"task":"T2","drone":"bravo","action":"goto","target":"car_12","xyz":null}]}"#;
const WAIT: &str = r#"{"reasoning":"Nothing to start yet.","actions":[],"plan_complete":false}"#;

impl HeldCoordinator {
    fn coordinator_calls(&self) -> usize {
        self.coordinator_requests
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .len()
    }
}

impl LlmBackend for HeldCoordinator {
    fn chat<'a>(&'a self, request: &'a ChatRequest) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        Box::pin(async move {
            let start = std::time::Instant::now();
            let coordinator = request
                .messages
                .first()
                .is_some_and(|m| m.content.starts_with("You are the Coordinator"));
            let content = if coordinator {
                let asked = request
                    .messages
                    .last()
                    .map(|m| m.content.clone())
                    .unwrap_or_default();
                let first = {
                    let mut requests = self
                        .coordinator_requests
                        .lock()
                        .unwrap_or_else(|e| e.into_inner());
                    requests.push(asked);
                    requests.len() == 1
                };
                if first {
                    let released = self.release.notified();
                    self.holding.send_replace(true);
                    released.await;
                    self.holding.send_replace(false);
                    FIRST_PLAN
                } else {
                    SECOND_PLAN
                }
            } else {
                WAIT
            };
            Ok(ChatReply {
                content: content.to_owned(),
                reasoning: None,
                usage: Usage {
                    prompt_tokens: 1,
                    completion_tokens: 1,
                },
                latency: start.elapsed(),
                model: "held".into(),
            })
        })
    }

    fn describe(&self) -> String {
        "held coordinator stand-in".into()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lost_drone_and_a_new_instruction_are_taken_in_while_the_coordinator_thinks()
-> anyhow::Result<()> {
    let mut sim = SimSwarm::start("concurrent", "city", 3).await?;
    let result = while_thinking(&mut sim).await;
    sim.stop().await;
    result
}

/// The three drones in the air and a mission whose first Coordinator call is held.
struct Held {
    backend: Arc<HeldCoordinator>,
    holding: watch::Receiver<bool>,
    updates: mpsc::UnboundedReceiver<MissionUpdate>,
    lines: mpsc::Sender<String>,
    mission_task: tokio::task::JoinHandle<tacos_ground::mission::MissionStats>,
    log_path: std::path::PathBuf,
}

async fn held_call(sim: &mut SimSwarm) -> anyhow::Result<Held> {
    let ids = [id("alfa"), id("bravo"), id("charlie")];
    let gate = SafetyGate::new(sim.scenario.clone());
    tacos_tests::all_ready(sim, &ids).await?;
    sim.take_off(&gate, &ids).await?;

    let (log_path, log) = tacos_tests::temp_mission_log("clog")?;
    let (holding_tx, mut holding) = watch::channel(false);
    let backend = Arc::new(HeldCoordinator {
        holding: holding_tx,
        release: Notify::new(),
        coordinator_requests: Mutex::new(Vec::new()),
    });
    let (updates_tx, updates) = mpsc::unbounded_channel();
    let mission = Mission::new(
        MissionConfig::default(),
        backend.clone(),
        gate,
        sim.link.clone(),
        log,
        updates_tx,
    )
    .await?;
    let (lines, rx) = mpsc::channel(4);
    let mission_task = tokio::spawn(mission.run(rx));

    lines.send("alfa, inspect car_11".into()).await?;
    within(
        "the Coordinator's call to be held",
        Duration::from_secs(30),
        holding.wait_for(|h| *h),
    )
    .await??;
    Ok(Held {
        backend,
        holding,
        updates,
        lines,
        mission_task,
        log_path,
    })
}

async fn while_thinking(sim: &mut SimSwarm) -> anyhow::Result<()> {
    let Held {
        backend,
        holding,
        mut updates,
        lines,
        mission_task,
        log_path,
    } = held_call(sim).await?;

    // A drone lost while the model thinks is told at once, not after the reply.
    let charlie = id("charlie");
    anyhow::ensure!(
        sim.stack
            .crash(Role::Onboard, Some(&charlie))
            .await
            .is_some(),
        "charlie's onboard was not running"
    );
    within(
        "charlie's loss to be told",
        Duration::from_secs(15),
        async {
            while let Some(u) = updates.recv().await {
                if let MissionUpdate::Event {
                    topic: EventTopic::Failure,
                    text,
                } = &u
                    && text.contains("charlie")
                {
                    return;
                }
            }
        },
    )
    .await?;
    anyhow::ensure!(*holding.borrow(), "the call was no longer held");

    // A second instruction waits for the Coordinator: no second call while the first is out.
    lines.send("bravo, inspect car_12".into()).await?;
    tokio::time::sleep(Duration::from_secs(1)).await;
    let asked = backend.coordinator_calls();
    anyhow::ensure!(
        asked == 1,
        "{asked} Coordinator calls while the first was held"
    );

    // Released: the first plan, then the second call with it pending, then the second plan.
    backend.release.notify_one();
    let mut plans = Vec::new();
    within("both plans", Duration::from_secs(30), async {
        while let Some(u) = updates.recv().await {
            match u {
                MissionUpdate::Plan { calls, .. } => {
                    plans.push(calls);
                    if plans.len() == 2 {
                        return;
                    }
                }
                MissionUpdate::Error(e) => panic!("mission error: {e}"),
                _ => {}
            }
        }
    })
    .await?;
    anyhow::ensure!(plans[0].len() == 1 && plans[1].len() == 2, "{plans:?}");
    let second = backend
        .coordinator_requests
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .get(1)
        .cloned()
        .unwrap_or_default();
    let pending = tacos_tests::prompt_text::section(&second, "Pending plan");
    anyhow::ensure!(
        pending.contains("alfa") && pending.contains("car_11"),
        "the second call's pending plan lacks the first plan's goto: {pending:?}"
    );
    anyhow::ensure!(
        second.contains("bravo, inspect car_12"),
        "the second call is not for the second instruction: {second}"
    );
    let swarm = tacos_tests::prompt_text::section(&second, "Swarm state");
    let charlie_line = swarm
        .lines()
        .find(|l| l.contains("charlie"))
        .unwrap_or_default();
    anyhow::ensure!(
        charlie_line.contains("unavailable"),
        "charlie is not unavailable in the second call's swarm: {charlie_line:?}"
    );

    drop(lines);
    let stats = within("the mission to end", Duration::from_secs(10), mission_task).await??;
    anyhow::ensure!(
        stats.coordinator_calls == 2 && stats.model_calls >= 2,
        "the calls are not all counted: {stats:?}"
    );
    let _ = std::fs::remove_file(&log_path);
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn land_all_drops_the_held_call_and_the_instruction_queued_behind_it() -> anyhow::Result<()> {
    let mut sim = SimSwarm::start("concland", "city", 3).await?;
    let result = land_while_thinking(&mut sim).await;
    sim.stop().await;
    result
}

async fn land_while_thinking(sim: &mut SimSwarm) -> anyhow::Result<()> {
    let Held {
        backend,
        mut updates,
        lines,
        mission_task,
        log_path,
        ..
    } = held_call(sim).await?;
    lines.send("bravo, inspect car_12".into()).await?;
    lines.send("land all".into()).await?;
    let (mut dropped, mut queued_dropped) = (None, false);
    within(
        "the call and the queued instruction dropped",
        Duration::from_secs(15),
        async {
            while let Some(u) = updates.recv().await {
                match u {
                    MissionUpdate::CallDropped { layer, by } => dropped = Some((layer, by)),
                    MissionUpdate::Event {
                        topic: EventTopic::PlanEnded,
                        text,
                    } if text.contains("bravo, inspect car_12") => queued_dropped = true,
                    MissionUpdate::Error(e) => panic!("mission error: {e}"),
                    _ => {}
                }
                if dropped.is_some() && queued_dropped {
                    return;
                }
            }
        },
    )
    .await?;
    assert_eq!(dropped, Some(("coordinator", Overtaken::DirectCommand)));
    // Every drone lands, and no Coordinator call follows: nothing takes them up again.
    within("all to land", Duration::from_secs(90), async {
        let ids = [id("alfa"), id("bravo"), id("charlie")];
        let mut version = sim.link.changes();
        loop {
            let landed = {
                let view = sim.link.view();
                let now = std::time::Instant::now();
                ids.iter().all(|d| {
                    view.get(d)
                        .is_some_and(|e| e.effective_mode(now) == tacos_shared::DroneMode::Idle)
                })
            };
            if landed {
                return;
            }
            let _ = version.recv().await;
        }
    })
    .await?;
    tokio::time::sleep(Duration::from_secs(1)).await;
    let asked = backend.coordinator_calls();
    anyhow::ensure!(
        asked == 1,
        "{asked} Coordinator calls: the queued instruction was asked"
    );
    drop(lines);
    within("the mission to end", Duration::from_secs(10), mission_task).await??;
    let _ = std::fs::remove_file(&log_path);
    Ok(())
}

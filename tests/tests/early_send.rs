//! A cycle's first call flies while the rest of the reply is still being written: the
//! Supervisor's reply streams alfa's call, then is held (a model still writing); alfa's action
//! is sent while it is held and bravo's is not; released, bravo's is sent and alfa's is not sent
//! twice. tacos-sitl, two tacos-px4 + tacos-onboard pairs and the mission engine on loopback.

use std::sync::{Arc, Mutex};
use std::time::Duration;
use tacos_ground::mission::{MissionConfig, MissionHandle, MissionUpdate};
use tacos_ground::safety::SafetyGate;
use tacos_llm::{
    BoxFuture, ChatReply, ChatRequest, LlmBackend, LlmError, Progress, Streamed, Usage,
};
use tacos_tests::{SimSwarm, id, within};
use tokio::sync::{Notify, mpsc, watch};

const PLAN: &str = r#"{"reasoning":"Alfa inspects car_11, bravo car_12.","plan":[{"task":"T1","drone":"alfa","action":"goto","target":"car_11","xyz":null},{"task":"T2","drone":"bravo","action":"goto","target":"car_12","xyz":null}]}"#;
/// The Supervisor's first reply up to the end of alfa's call.
const FIRST_PART: &str = r#"{"reasoning":"Both can start.","actions":[{"task":"T1","drone":"alfa","action":"goto","target":"car_11","xyz":null}"#;
const REST: &str = r#",{"task":"T2","drone":"bravo","action":"goto","target":"car_12","xyz":null}],"plan_complete":false}"#;
const WAIT: &str = r#"{"reasoning":"Both are under way.","actions":[],"plan_complete":false}"#;

/// A model whose first Supervisor reply stops after alfa's call until the test releases it.
struct HeldMidReply {
    holding: watch::Sender<bool>,
    release: Notify,
    supervisor_calls: Mutex<usize>,
}

impl HeldMidReply {
    fn reply(content: &str, start: std::time::Instant) -> ChatReply {
        ChatReply {
            content: content.to_owned(),
            reasoning: None,
            usage: Usage {
                prompt_tokens: 1,
                completion_tokens: 1,
            },
            latency: start.elapsed(),
            model: "held mid-reply".into(),
        }
    }
}

impl LlmBackend for HeldMidReply {
    fn chat<'a>(&'a self, request: &'a ChatRequest) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        self.chat_streamed(request, &|_: Streamed<'_>| {})
    }

    fn chat_streamed<'a>(
        &'a self,
        request: &'a ChatRequest,
        progress: Progress<'a>,
    ) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        Box::pin(async move {
            let start = std::time::Instant::now();
            let first = |m: &str| {
                request
                    .messages
                    .first()
                    .is_some_and(|f| f.content.starts_with(m))
            };
            if first("You are the Coordinator") {
                return Ok(Self::reply(PLAN, start));
            }
            let held = {
                let mut calls = self
                    .supervisor_calls
                    .lock()
                    .unwrap_or_else(|e| e.into_inner());
                *calls += 1;
                *calls == 1
            };
            if !held {
                return Ok(Self::reply(WAIT, start));
            }
            // Held from before the partial reply is streamed: the engine may send alfa's call
            // (and the test look at `holding`) before this task runs again.
            self.holding.send_replace(true);
            let released = self.release.notified();
            progress(Streamed {
                reasoning: "",
                content: FIRST_PART,
            });
            released.await;
            self.holding.send_replace(false);
            let whole = format!("{FIRST_PART}{REST}");
            progress(Streamed {
                reasoning: "",
                content: &whole,
            });
            Ok(Self::reply(&whole, start))
        })
    }

    fn describe(&self) -> String {
        "held mid-reply stand-in".into()
    }
}

/// Waits for the action sent to `drone`, failing on a mission error or a refused call.
async fn sent_to(
    updates: &mut mpsc::UnboundedReceiver<MissionUpdate>,
    drone: &str,
    seen: &mut Vec<String>,
) {
    while let Some(update) = updates.recv().await {
        match update {
            MissionUpdate::Sent { drone: d, .. } => {
                seen.push(d.clone());
                if d == drone {
                    return;
                }
            }
            MissionUpdate::Error(e) => panic!("mission error: {e}"),
            MissionUpdate::Rejected { refusal, .. } => panic!("a call was refused: {refusal}"),
            _ => {}
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_call_complete_in_a_reply_still_being_written_is_sent() -> anyhow::Result<()> {
    let sim = SimSwarm::start("early", "city", 2).await?;
    let result = early_send(&sim).await;
    sim.stop().await;
    result
}

async fn early_send(sim: &SimSwarm) -> anyhow::Result<()> {
    let ids = [id("alfa"), id("bravo")];
    let gate = SafetyGate::new(sim.scenario.clone());
    tacos_tests::all_ready(sim, &ids).await?;
    sim.take_off(&gate, &ids).await?;

    let (log_path, log) = tacos_tests::temp_mission_log("elog")?;
    let (holding_tx, mut holding) = watch::channel(false);
    let backend = Arc::new(HeldMidReply {
        holding: holding_tx,
        release: Notify::new(),
        supervisor_calls: Mutex::new(0),
    });
    let MissionHandle {
        input,
        mut updates,
        task,
    } = MissionHandle::start(
        MissionConfig::default(),
        backend.clone(),
        gate,
        sim.link.clone(),
        log,
    )
    .await?;
    input
        .submit("alfa, inspect car_11; bravo, inspect car_12")
        .await?;

    // Alfa's action goes while the reply is held after its call.
    let mut seen = Vec::new();
    within(
        "alfa's action while the reply is held",
        Duration::from_secs(30),
        sent_to(&mut updates, "alfa", &mut seen),
    )
    .await?;
    anyhow::ensure!(
        *holding.borrow(),
        "alfa's action was sent only after the reply was whole"
    );
    anyhow::ensure!(seen == ["alfa"], "sent before the release: {seen:?}");
    // Alfa busy with it before the reply is whole: its call in the whole reply is served, not
    // a repeat to repair.
    within("alfa under way", Duration::from_secs(10), async {
        loop {
            let busy = sim
                .link
                .view()
                .get(&id("alfa"))
                .and_then(|e| e.status.as_ref().map(|s| s.action.is_some()))
                .unwrap_or(false);
            if busy {
                return;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await?;

    // Released: bravo's action, and alfa's not again.
    backend.release.notify_one();
    within(
        "the reply released",
        Duration::from_secs(10),
        holding.wait_for(|h| !*h),
    )
    .await??;
    within(
        "bravo's action",
        Duration::from_secs(30),
        sent_to(&mut updates, "bravo", &mut seen),
    )
    .await?;
    anyhow::ensure!(seen == ["alfa", "bravo"], "sent: {seen:?}");
    let supervisor_calls = *backend
        .supervisor_calls
        .lock()
        .unwrap_or_else(|e| e.into_inner());
    anyhow::ensure!(
        supervisor_calls == 1,
        "{supervisor_calls} Supervisor calls by bravo's send: the whole reply was sent back for repair"
    );

    drop(input);
    let stats = within("the mission to end", Duration::from_secs(10), task.join()).await??;
    anyhow::ensure!(stats.actions_sent == 2, "{stats:?}");
    let log = std::fs::read_to_string(&log_path)?;
    anyhow::ensure!(
        log.contains("while the reply was still being written"),
        "the early send is not in the log"
    );
    let _ = std::fs::remove_file(&log_path);
    Ok(())
}

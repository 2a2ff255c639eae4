//! A pilot's direct command does not wait for a model: `land all` typed while the Supervisor's
//! model call is still pending is checked at the gate and sent at once, the drones land while
//! the call is held, the call is dropped in flight (its reply could only be stale) and the plan
//! ends; nothing the model proposes is sent.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use tacos_ground::mission::log::{self, Record};
use tacos_ground::mission::{EventTopic, MissionConfig, MissionHandle, MissionUpdate, Overtaken};
use tacos_ground::safety::SafetyGate;
use tacos_llm::{BoxFuture, ChatReply, ChatRequest, LlmBackend, LlmError, Usage};
use tacos_shared::action::Action;
use tacos_shared::{DroneId, DroneMode};
use tacos_tests::{SimSwarm, within};
use tokio::sync::{Notify, watch};

/// A model whose Coordinator answers at once with a goto for alfa, and whose first Supervisor
/// call is held until the test releases it (a slow model); every Supervisor reply proposes
/// that goto.
struct SlowSupervisor {
    /// Set while a Supervisor call is being held.
    pending: watch::Sender<bool>,
    release: Notify,
    returned: AtomicBool,
}

const PLAN: &str = r#"{"reasoning":"Alfa inspects car_11.","plan":[{"task":"T1","drone":"alfa","action":"goto","target":"car_11","xyz":null}]}"#;
const CYCLE: &str = r#"{"reasoning":"Alfa is flying: start T1.","actions":[{"task":"T1","drone":"alfa","action":"goto","target":"car_11","xyz":null}],"plan_complete":false}"#;

impl LlmBackend for SlowSupervisor {
    fn chat<'a>(&'a self, request: &'a ChatRequest) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        Box::pin(async move {
            let start = std::time::Instant::now();
            let coordinator = request
                .messages
                .first()
                .is_some_and(|m| m.content.starts_with("You are the Coordinator"));
            let content = if coordinator || self.returned.load(Ordering::SeqCst) {
                if coordinator { PLAN } else { CYCLE }
            } else {
                let released = self.release.notified();
                self.pending.send_replace(true);
                // Parked here as a model call is at its first wait, so that the drop the test
                // provokes cancels the call, whichever thread runs it: without it, a thread
                // that lost its core right after `pending` resumed only once the test had
                // released the call, and answered within the poll the abort waits out.
                tokio::task::yield_now().await;
                released.await;
                self.returned.store(true, Ordering::SeqCst);
                CYCLE
            };
            Ok(ChatReply {
                content: content.to_owned(),
                reasoning: None,
                usage: Usage {
                    prompt_tokens: 1,
                    completion_tokens: 1,
                },
                latency: start.elapsed(),
                model: "slow".into(),
            })
        })
    }

    fn describe(&self) -> String {
        "slow supervisor stand-in".into()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn land_all_is_sent_while_a_model_call_is_pending_and_the_late_reply_is_not()
-> anyhow::Result<()> {
    let sim = SimSwarm::start("direct", "city", 3).await?;
    let result = async {
        let link = sim.link.clone();
        let ids: Vec<DroneId> = ["alfa", "bravo", "charlie"]
            .iter()
            .map(|d| DroneId::new(*d))
            .collect::<Result<_, _>>()?;
        link.wait_for_drones(&ids, Duration::from_secs(60), |s| {
            s.autopilot_link && s.mode == DroneMode::Idle
        })
        .await?;
        let gate = SafetyGate::new(sim.scenario.clone());
        // Set-up: all three in the air (through the gate, without a model).
        sim.take_off(&gate, &ids).await?;

        let (log_path, log) = tacos_tests::temp_mission_log("dlog")?;
        let (pending_tx, mut pending) = watch::channel(false);
        let backend = Arc::new(SlowSupervisor {
            pending: pending_tx,
            release: Notify::new(),
            returned: AtomicBool::new(false),
        });
        let MissionHandle {
            input,
            mut updates,
            task,
        } = MissionHandle::start(MissionConfig::default(), backend.clone(), gate, link.clone(), log.clone()).await?;

        input.submit("alfa, inspect car_11").await?;
        within(
            "the Supervisor's call to be pending",
            Duration::from_secs(30),
            pending.wait_for(|p| *p),
        )
        .await??;

        let typed = Instant::now();
        input.submit("land all").await?;
        // Everything below happens while the model call is still held.
        within(
            "every drone to be landing",
            Duration::from_secs(10),
            async {
                let mut version = link.changes();
                loop {
                    let landing = {
                        let view = link.view();
                        ids.iter().all(|d| {
                            view.get(d)
                                .and_then(|e| e.status.as_ref())
                                .and_then(|s| s.action.as_ref())
                                .is_some_and(|p| p.action == Action::Land)
                        })
                    };
                    if landing {
                        return;
                    }
                    let _ = version.recv().await;
                }
            },
        )
        .await?;
        assert!(
            !backend.returned.load(Ordering::SeqCst),
            "the model call returned first"
        );
        println!(
            "land all reached every drone {:.0} ms after it was typed",
            typed.elapsed().as_secs_f64() * 1e3
        );

        // The command ended the plan, and the Supervisor's call in flight with it.
        let (mut dropped, mut ended) = (None, None);
        within("the call dropped and the plan ended", Duration::from_secs(30), async {
            while let Some(u) = updates.recv().await {
                match u {
                    MissionUpdate::CallDropped { layer, by } => dropped = Some((layer, by)),
                    MissionUpdate::Event {
                        topic: EventTopic::PlanEnded,
                        text,
                    } => ended = Some(text),
                    _ => {}
                }
                if dropped.is_some() && ended.is_some() {
                    return;
                }
            }
        })
        .await?;
        assert_eq!(dropped, Some(("supervisor", Overtaken::DirectCommand)));
        assert_eq!(
            ended.as_deref(),
            Some("plan ended: interrupted by a direct command")
        );
        // Released now, the model has no call left to answer.
        backend.release.notify_one();
        within("all to land", Duration::from_secs(120), async {
            let mut version = link.changes();
            loop {
                let landed = {
                    let view = link.view();
                    let now = std::time::Instant::now();
                    ids.iter().all(|d| {
                        view.get(d)
                            .is_some_and(|e| e.effective_mode(now) == DroneMode::Idle)
                    })
                };
                if landed {
                    return;
                }
                let _ = version.recv().await;
            }
        })
        .await?;
        drop(input);
        within("the mission to end", Duration::from_secs(10), task.join()).await??;

        let lines = log::read(&log_path)?;
        let sent: Vec<(String, String)> = lines
            .iter()
            .filter_map(|l| match &l.record {
                Record::ActionSent { drone, action, .. } => Some((drone.clone(), action.clone())),
                _ => None,
            })
            .collect();
        assert_eq!(sent.len(), 3, "three landings and nothing else: {sent:?}");
        assert!(sent.iter().all(|(_, a)| a == "land()"), "{sent:?}");
        let direct = lines
            .iter()
            .position(|l| matches!(&l.record, Record::Direct { text, .. } if text == "land all"));
        let dropped = lines.iter().position(|l| {
            matches!(&l.record, Record::Event { text } if text.contains("supervisor's call in flight was dropped"))
        });
        assert!(
            direct.is_some() && dropped.is_some(),
            "the command and the dropped call in the log"
        );
        assert!(
            !lines.iter().any(
                |l| matches!(&l.record, Record::LlmReply { layer, .. } if layer == "supervisor")
            ),
            "no Supervisor reply was taken in"
        );
        assert!(
            !backend.returned.load(Ordering::SeqCst),
            "the held call was dropped, not answered"
        );
        let _ = std::fs::remove_file(&log_path);
        anyhow::Ok(())
    }
    .await;
    sim.stop().await;
    result
}

//! What the engine does with what a model says and when: positions logged while it thinks, a
//! chase handed on, unknown drones. (Places held to the pilot's words, a failed repair round and
//! a refusal the map contradicts are the core's tests: `core/plan_tests.rs`, `repair_tests.rs`.)

use super::kit::*;
use serde_json::json;
use std::time::Duration;
use tacos_ground::mission::log::{self, Record};
use tacos_ground::mission::{Aid, MissionUpdate};
use tacos_llm::ChatRequest;
use tacos_shared::DroneId;
use tacos_tests::prompt_text::request_text;
use tacos_tests::{PolicyBackend, within};

/// The drones fly on while a model thinks, and the mission log keeps their positions for the
/// plot: twice a second, each at the time it was taken, not in a burst once the call returns.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn positions_are_logged_while_a_model_thinks() -> anyhow::Result<()> {
    stopping_after(start("think").await?, async |run| {
        let plan = json!([
            call("T1", "alfa", "arm_takeoff", "none"),
            call("T2", "alfa", "goto", "car_11")
        ]);
        let think = Duration::from_secs(4);
        let backend = PolicyBackend::new(offered_policy(plan, false)).thinking(think);
        let (mut updates, lines, log_path, _) =
            run_with_backend(run, "thinklog", backend, "alfa, to car_11").await?;
        until(
            &mut updates,
            Duration::from_secs(60),
            |u| matches!(u, MissionUpdate::Sent { action, .. } if action.starts_with("goto")),
        )
        .await?;
        // A second instruction: the Coordinator thinks for 4 s while alfa flies to car_11.
        lines.send("alfa, to car_11 again".into()).await?;
        until(&mut updates, Duration::from_secs(60), |u| {
            matches!(u, MissionUpdate::Plan { .. })
        })
        .await?;
        drop(lines);
        let records = log::read(&log_path)?;
        let asked = records
            .iter()
            .filter(
                |l| matches!(&l.record, Record::LlmRequest { layer, .. } if layer == "coordinator"),
            )
            .map(|l| l.t)
            .nth(1)
            .ok_or_else(|| anyhow::anyhow!("no second coordinator request"))?;
        let alfa: Vec<(f64, f64)> = records
            .iter()
            .filter_map(|l| match &l.record {
                Record::Position { drone, speed, .. } if drone == "alfa" => Some((l.t, *speed)),
                _ => None,
            })
            .collect();
        let during: Vec<&(f64, f64)> = alfa
            .iter()
            .filter(|(t, _)| *t > asked && *t < asked + think.as_secs_f64())
            .collect();
        assert!(
            during.len() >= 6,
            "{} positions of alfa in the 4 s the model thought: {during:?}",
            during.len()
        );
        assert!(
            during.iter().any(|(_, speed)| *speed > 0.5),
            "alfa was not seen moving: {during:?}"
        );
        for pair in alfa.windows(2) {
            assert!(
                pair[1].0 - pair[0].0 > 0.3,
                "positions logged in a burst: {pair:?}"
            );
        }
        anyhow::Ok(())
    })
    .await
}

/// Whether the request's grammar opens the plan with a start_tracking of the van.
fn opens_with_tracking(request: &ChatRequest) -> bool {
    request
        .schema
        .as_ref()
        .and_then(|s| {
            s.schema
                .pointer("/properties/plan/prefixItems/0/properties")
        })
        .is_some_and(|p| {
            p["action"]["enum"] == json!(["start_tracking"])
                && p["target"]["enum"] == json!(["van"])
        })
}

/// The chase, as the moving-target script flies it: a plan for "alfa, follow the van" that
/// tracks nothing is sent back naming the missing start_tracking, with a grammar that opens the
/// plan with it; once alfa follows the van and the plan is complete, alfa's vehicle dies, and
/// the automatic replan names the chase it left, so the Coordinator hands it on and bravo
/// follows the van.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_chase_is_held_to_the_pilot_and_handed_on_when_its_tracker_dies() -> anyhow::Result<()> {
    stopping_after(start("chase").await?, async |run| {
        let supervisor = offered_policy(json!([]), false);
        let model = move |request: &ChatRequest| {
            let system = &request.messages[0].content;
            if !system.starts_with("You are the Coordinator") {
                return supervisor(request);
            }
            let user = request_text(request);
            let plan = if user.contains("(automatic replan)") {
                // Only what the instruction names: the chase the dead drone left.
                if !user.contains("alfa start_tracking(van)") {
                    return Ok(json!({ "reasoning": "Nothing to hand on.", "plan": [] }).to_string());
                }
                json!([
                    call("T1", "bravo", "arm_takeoff", "none"),
                    call("T2", "bravo", "start_tracking", "van"),
                ])
            } else if repairs(request) == 0 || !opens_with_tracking(request) {
                // As the 135M model did: it flies to the van instead of following it, and told
                // so, it answers the same until its grammar leaves it no other way.
                json!([
                    call("T1", "alfa", "arm_takeoff", "none"),
                    call("T2", "alfa", "goto", "van"),
                ])
            } else {
                // The grammar's order: the required call first.
                json!([
                    call("T2", "alfa", "start_tracking", "van"),
                    call("T1", "alfa", "arm_takeoff", "none"),
                ])
            };
            Ok(json!({ "reasoning": "As the pilot said.", "plan": plan }).to_string())
        };
        let (mut updates, lines, log_path, _) = run_with_backend(
            run,
            "chaselog",
            PolicyBackend::new(model),
            "alfa, follow the van",
        )
        .await?;
        plan_complete(&mut updates, Duration::from_secs(150))
        .await?;
        let alfa = DroneId::new("alfa")?;
        run.sim
            .link
            .inject_fault(&alfa, tacos_shared::scenario::FaultKind::VehicleDies)
            .await?;
        let bravo = DroneId::new("bravo")?;
        within("bravo to follow the van", Duration::from_secs(150), async {
            loop {
                let following = {
                    let view = run.sim.link.view();
                    view.get(&bravo)
                        .and_then(|e| e.status.as_ref())
                        .is_some_and(|s| {
                            s.mode == tacos_shared::DroneMode::Tracking
                                && s.action.as_ref().is_some_and(|p| {
                                    matches!(&p.action, tacos_shared::action::Action::StartTracking { target } if target == "van")
                                })
                        })
                };
                if following {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        })
        .await?;
        drop(lines);
        let lines = log::read(&log_path)?;
        for aid in [Aid::FollowWords, Aid::RepairGrammar] {
            assert!(
                lines.iter().any(|l| matches!(&l.record, Record::AidFired { aid: fired, .. } if *fired == aid)),
                "{aid} did not fire"
            );
        }
        let asked_back = lines.iter().any(|l| {
            matches!(&l.record, Record::LlmRequest { layer, messages, .. } if layer == "coordinator"
                && messages.as_array().is_some_and(|ms| ms.iter().any(|m| m["content"].as_str().is_some_and(|c| {
                    c.starts_with("Your reply was rejected") && c.contains("asks to follow van") && c.contains("start_tracking")
                }))))
        });
        assert!(asked_back, "the plan that only flew to the van was not sent back");
        // Alfa never got the goto; the replan came from alfa's loss although no plan was open.
        assert!(
            !lines.iter().any(|l| matches!(&l.record, Record::ActionSent { action, .. } if action.starts_with("goto"))),
            "a goto was sent"
        );
        assert!(
            lines.iter().any(|l| matches!(&l.record, Record::Replan { reason } if reason.contains("alfa"))),
            "no replan for alfa"
        );
        anyhow::Ok(())
    })
    .await
}

/// "zulu, take off" in a swarm without zulu: the pilot is told there is no zulu and which
/// drones there are, before any model is asked, and nothing is sent. (A capable model answered
/// "Zulu is already flying" and planned take-offs for the others.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_instruction_to_a_drone_the_swarm_lacks_is_refused_with_the_swarm_s_drones()
-> anyhow::Result<()> {
    stopping_after(start("zulu").await?, async |run| {
        let plan = json!([call("T1", "alfa", "arm_takeoff", "none")]);
        let (mut updates, lines, log_path, _) =
            run_offered(run, "zululog", plan, false, "zulu, take off").await?;
        let error = given_up(&mut updates, Duration::from_secs(20)).await?;
        assert_eq!(
            error,
            "there is no drone zulu in this swarm (its drones: alfa, bravo, charlie); nothing was sent: address one of those"
        );
        drop(lines);
        let lines = log::read(&log_path)?;
        assert!(
            !lines
                .iter()
                .any(|l| matches!(&l.record, Record::LlmRequest { .. })),
            "a model was asked"
        );
        assert!(sent_tasks(&lines).is_empty());
        anyhow::Ok(())
    })
    .await
}

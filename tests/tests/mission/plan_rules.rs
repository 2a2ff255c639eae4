//! How a plan is held to what can be done: failing tasks, lost targets, gotos already done, plans
//! that cannot go on, drones that are gone, forgotten take-offs with the aids on and off.

use super::kit::*;
use serde_json::{Value, json};
use std::time::Duration;
use tacos_ground::launch::Role;
use tacos_ground::mission::log::{self, Record};
use tacos_ground::mission::{Aid, MissionUpdate, ModelAids};
use tacos_llm::ChatRequest;
use tacos_shared::DroneId;
use tacos_tests::prompt_text::request_text;
use tacos_tests::{PolicyBackend, SimSwarm, within};
use tokio::sync::mpsc;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_task_that_keeps_failing_gives_the_plan_up_with_the_reason() -> anyhow::Result<()> {
    stopping_after(start("hopeless").await?, async |run| {
        let plan = json!([
            call("T1", "alfa", "arm_takeoff", "none"),
            call("T2", "alfa", "start_tracking", "suspect")
        ]);
        let (mut updates, lines, log_path, max) = run_offered(
            run,
            "hopelog",
            plan,
            false,
            "alfa, take off and follow the suspect",
        )
        .await?;
        let error = given_up(&mut updates, Duration::from_secs(120)).await?;
        drop(lines);
        assert!(
            error.contains("T2 alfa start_tracking(suspect)")
                && error.contains(&format!("failed {max} times")),
            "{error}"
        );
        let lines = log::read(&log_path)?;
        let tries = sent_tasks(&lines).iter().filter(|(t, _)| t == "T2").count();
        assert_eq!(tries, max as usize, "T2 was sent {tries} times");
        assert!(lines.iter().any(
            |l| matches!(&l.record, Record::PlanEnded { how } if how.starts_with("abandoned"))
        ));
        anyhow::Ok(())
    })
    .await
}

/// A tracked target that stops being observed after its tracker reached it: the done
/// start_tracking fails with the loss, and the Supervisor is offered it again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_target_lost_after_tracking_was_done_fails_the_task_and_it_is_given_again()
-> anyhow::Result<()> {
    let city = include_str!("../../../shared/scenarios/city.toml");
    let rover = "\n[[targets]]\nname = \"rover\"\nkind = \"vehicle\"\nstart = [-40.0, -120.0, 0.0]\nobserved_until_s = 45.0\n";
    let path = std::env::temp_dir().join(format!("{}.toml", tacos_tests::unique_swarm("tunnel")));
    std::fs::write(&path, format!("{city}{rover}"))?;
    let sim = SimSwarm::start("tunnel", &path.display().to_string(), 3).await?;
    let run = Running {
        sim,
        updates: mpsc::unbounded_channel().1,
        lines: mpsc::channel(1).0,
        log_path: Default::default(),
    };
    let result = stopping_after(run, async |run| {
        run.sim
            .wait_on_the_ground(&["alfa", "bravo", "charlie"])
            .await?;
        // Bravo's take-off is never started (the stand-in Supervisor leaves it): the plan stays
        // open while alfa tracks, and it is not stuck, since alfa is at work.
        let plan = json!([
            call("T1", "alfa", "arm_takeoff", "none"),
            call("T2", "alfa", "start_tracking", "rover"),
            call("T3", "bravo", "arm_takeoff", "none"),
        ]);
        let offered = offered_policy(plan, false);
        let leaves_bravo = move |request: &ChatRequest| {
            let reply = offered(request)?;
            let Ok(mut reply_json) = serde_json::from_str::<Value>(&reply) else {
                return Ok(reply);
            };
            if let Some(actions) = reply_json.get_mut("actions").and_then(Value::as_array_mut) {
                actions.retain(|a| a["drone"] != "bravo");
            }
            Ok(reply_json.to_string())
        };
        let (mut updates, lines, log_path, max) = run_with_backend(
            run,
            "tunnellog",
            PolicyBackend::new(leaves_bravo),
            "alfa, follow the rover",
        )
        .await?;
        let error = given_up(&mut updates, Duration::from_secs(150)).await?;
        drop(lines);
        let lines = log::read(&log_path)?;
        let t2: Vec<(u64, String)> = lines
            .iter()
            .filter_map(|l| match &l.record {
                Record::ActionOutcome {
                    task: Some(t),
                    seq,
                    outcome,
                    ..
                } if t == "T2" => Some((*seq, outcome.clone())),
                _ => None,
            })
            .collect();
        // The first tracking reached its station, then lost the rover: two outcomes, one seq.
        let first = t2.first().map(|(s, _)| *s);
        let of_first: Vec<&str> = t2
            .iter()
            .filter(|(s, _)| Some(*s) == first)
            .map(|(_, o)| o.as_str())
            .collect();
        assert_eq!(of_first.len(), 2, "{t2:?}");
        assert_eq!(of_first[0], "done", "{t2:?}");
        assert!(
            of_first[1].starts_with("failed") && of_first[1].contains("lost"),
            "{t2:?}"
        );
        // Given again (the rover is gone, so it fails again) until the plan was given up.
        assert_eq!(
            sent_tasks(&lines).iter().filter(|(t, _)| t == "T2").count(),
            max as usize
        );
        assert!(
            error.contains("T2") && error.contains(&format!("failed {max} times")),
            "{error}"
        );
        anyhow::Ok(())
    })
    .await;
    let _ = std::fs::remove_file(&path);
    result
}

/// A plan that repeats a goto (small models do): the repeat straight after is dropped from the
/// plan; a goto back to car_11 after a hold finds the drone already there and is done without a
/// model cycle or a flight.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_goto_to_where_the_drone_already_hovers_is_done_without_flying() -> anyhow::Result<()> {
    stopping_after(start("there").await?, async |run| {
        let plan = json!([
            call("T1", "alfa", "arm_takeoff", "none"),
            call("T2", "alfa", "goto", "car_11"),
            call("T3", "alfa", "goto", "car_11"),
            call("T4", "alfa", "hold", "none"),
            call("T5", "alfa", "goto", "car_11"),
        ]);
        let (mut updates, lines, log_path, _) =
            run_offered(run, "therelog", plan, false, "alfa, to car_11, twice").await?;
        plan_complete(&mut updates, Duration::from_secs(120)).await?;
        drop(lines);
        let lines = log::read(&log_path)?;
        let sent: Vec<String> = sent_tasks(&lines).into_iter().map(|(t, _)| t).collect();
        assert_eq!(sent, ["T1", "T2", "T4"]);
        let event = |wanted: &str| {
            lines
                .iter()
                .any(|l| matches!(&l.record, Record::Event { text } if text == wanted))
        };
        assert!(event(
            "T3 alfa goto(car_11): repeats alfa's previous task: dropped"
        ));
        assert!(event("T5 alfa goto(car_11): already there: nothing to do"));
        anyhow::Ok(())
    })
    .await
}

/// A plan that can never go on (a take-off for a drone whose onboard is gone) is given up with
/// the reason, instead of waiting for ever.
/// A drone lost mid-plan whose work no replan can give to another drone (the stand-in
/// Coordinator insists on the lost drone, and is refused): the plan in force keeps the lost
/// drone's task, which nothing can start, and is given up after 20 s.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plan_that_cannot_go_on_is_given_up() -> anyhow::Result<()> {
    stopping_after(start("stuck").await?, async |run| {
        let plan = json!([
            call("T1", "bravo", "arm_takeoff", "none"),
            call("T2", "bravo", "goto", "car_1"),
        ]);
        let (mut updates, lines, log_path, _) = run_offered(
            run,
            "stucklog",
            plan,
            false,
            "bravo, take off and check car_1",
        )
        .await?;
        let bravo = DroneId::new("bravo")?;
        until(
            &mut updates,
            Duration::from_secs(60),
            |u| matches!(u, MissionUpdate::Sent { drone, .. } if drone == "bravo"),
        )
        .await?;
        run.sim
            .stack
            .crash(Role::Onboard, Some(&bravo))
            .await
            .ok_or_else(|| anyhow::anyhow!("bravo's onboard was not running"))?;
        let lost_at = std::time::Instant::now();
        let mut errors = Vec::new();
        within("the plan to be given up", Duration::from_secs(120), async {
            while let Some(u) = updates.recv().await {
                if let MissionUpdate::Error(e) = u {
                    let stuck = e.contains("nothing has run or could start");
                    errors.push(e);
                    if stuck {
                        return;
                    }
                }
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}; errors so far: {errors:?}"))?;
        drop(lines);
        assert!(
            lost_at.elapsed() >= Duration::from_secs(20),
            "given up after {:?}",
            lost_at.elapsed()
        );
        let last = errors.last().cloned().unwrap_or_default();
        // What waits, why it cannot start, and what would help.
        assert!(
            last.contains("waiting: T2 bravo goto(car_1) (bravo is unavailable)")
                && last.contains("Give the work to another drone or place, or land"),
            "{errors:?}"
        );
        // The replan was refused: it gave the work to bravo again.
        assert!(
            errors.iter().any(|e| e.contains("coordinator")),
            "{errors:?}"
        );
        let lines = log::read(&log_path)?;
        assert!(
            !sent_tasks(&lines).iter().any(|(t, _)| t == "T2"),
            "bravo's goto was sent"
        );
        anyhow::Ok(())
    })
    .await
}

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

/// A goto for a drone on the ground in a plan that never takes it off: the take-off the
/// Coordinator's rules require is added before it, and the plan completes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_grounded_drone_sent_somewhere_gets_the_take_off_its_plan_forgot() -> anyhow::Result<()> {
    stopping_after(start("forgot").await?, async |run| {
        let plan = json!([call("T1", "alfa", "goto", "car_11"), call("T2", "bravo", "arm_takeoff", "none")]);
        let (mut updates, lines, log_path, _) = run_offered(run, "forgotlog", plan, false, "alfa, to car_11").await?;
        plan_complete(&mut updates, Duration::from_secs(90)).await?;
        drop(lines);
        let lines = log::read(&log_path)?;
        let sent = sent_tasks(&lines);
        assert_eq!(sent.iter().filter(|(_, d)| d == "alfa").map(|(t, _)| t.as_str()).collect::<Vec<_>>(), ["T3", "T1"], "{sent:?}");
        assert!(lines.iter().any(|l| matches!(&l.record, Record::AidFired { aid: Aid::ImpliedTakeoffs, detail } if detail.contains("added T3 alfa arm_takeoff()"))));
        // Bravo had its own take-off: nothing was added for it.
        assert_eq!(sent.iter().filter(|(_, d)| d == "bravo").count(), 1, "{sent:?}");
        assert!(lines.iter().any(|l| matches!(&l.record, Record::MissionStart { aids, .. } if *aids == ModelAids::small())));
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

//! The ground station killed mid-plan and started again with `--resume`: the real
//! `tacos-ground fly` binary over a simulated swarm whose hub only watches, against an
//! OpenAI-compatible stand-in model on loopback. The first ground is SIGKILLed as soon as its
//! mission log shows alfa's goto (the plan's second task) sent; a second ground resumes from that
//! log and must finish the plan: the take-offs are not sent again, the goto is seen through (its
//! outcome matched to the old ground's send, or sent again if the drone's failsafe held it), the
//! last goto is sent by the new ground, and the plan completes.

use serde_json::{Value, json};
use std::path::Path;
use std::time::{Duration, Instant};
use tacos_ground::mission::log::{self, Line, Record};
use tacos_prompts::render::TaskStatus;
use tacos_tests::SimSwarm;
use tacos_tests::chat_server::{ChatServer, PolicyResult};
use tacos_tests::prompt_text::{body_text, first_offered_in_body, plan_lines};
use tokio::process::{Child, Command};

fn call(task: &str, drone: &str, action: &str, target: &str) -> Value {
    json!({ "task": task, "drone": drone, "action": action, "target": target, "xyz": null })
}

/// The stand-in model. Coordinator: alfa takes off and flies to car_11 then car_12, bravo takes
/// off. Supervisor: each drone starts the first call the engine offers it; the plan is complete
/// when every task is done.
fn policy(_index: usize, request: &Value) -> PolicyResult {
    let Some((system, user)) = body_text(request) else {
        return Err((400, "no request in the messages".into()));
    };
    if system.starts_with("You are the Coordinator") {
        let plan = [
            call("T1", "alfa", "arm_takeoff", "none"),
            call("T2", "alfa", "goto", "car_11"),
            call("T3", "alfa", "goto", "car_12"),
            call("T4", "bravo", "arm_takeoff", "none"),
        ];
        return Ok(json!({ "reasoning": "Alfa inspects the two cars; bravo stands by in the air.", "plan": plan }).to_string());
    }
    let actions = first_offered_in_body(request);
    let complete = plan_lines(&user).iter().all(|t| t.4 == "done");
    Ok(json!({ "reasoning": "Each drone does its next task.", "actions": actions, "plan_complete": complete }).to_string())
}

/// `tacos-ground fly` on `swarm`'s hub with the stand-in model and `more` arguments.
fn fly(swarm: &SimSwarm, server: &ChatServer, more: &[&str]) -> anyhow::Result<Child> {
    let ground = tacos_ground::launch::bin_dir().join("tacos-ground");
    Ok(Command::new(ground)
        .arg("fly")
        .args(swarm.bus_args())
        .args(["--map", "city", "--drones", "alfa,bravo", "--no-terminal"])
        .args(["--llm-url", &server.url, "--model", &server.model])
        .args(more)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .kill_on_drop(true)
        .spawn()?)
}

/// The records of the log at `path` so far (none while it does not exist).
fn records(path: &Path) -> Vec<Line> {
    log::read(path).unwrap_or_default()
}

/// The sequence number alfa's goto to car_11 (T2) was sent with, once it was.
fn t2_sent(lines: &[Line]) -> Option<u64> {
    lines.iter().find_map(|l| match &l.record {
        Record::ActionSent {
            task: Some(t), seq, ..
        } if t == "T2" => Some(*seq),
        _ => None,
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_ground_killed_mid_plan_is_resumed_from_its_log_and_the_plan_completes()
-> anyhow::Result<()> {
    let swarm = SimSwarm::start_watching("restart", "city", 2).await?;
    swarm.wait_on_the_ground(&["alfa", "bravo"]).await?;
    let server = ChatServer::start("stand-in", policy).await?;
    let log_path =
        std::env::temp_dir().join(format!("{}.jsonl", tacos_tests::unique_swarm("restart")));
    let log_arg = log_path.display().to_string();

    let mut first = fly(
        &swarm,
        &server,
        &[
            "--say",
            "alfa, inspect car_11 then car_12; bravo, take off",
            "--log",
            &log_arg,
        ],
    )?;
    let started = Instant::now();
    let t2_seq = loop {
        if let Some(seq) = t2_sent(&records(&log_path)) {
            break seq;
        }
        if let Ok(Some(status)) = first.try_wait() {
            let out = first.wait_with_output().await?;
            anyhow::bail!(
                "the first ground ended ({status}) before alfa's goto was sent\nstdout:\n{}\nstderr:\n{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        anyhow::ensure!(
            started.elapsed() < Duration::from_secs(120),
            "alfa's goto was not sent within 120 s"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    first.start_kill()?;
    let _ = first.wait().await?;
    let killed_at = Instant::now();
    println!(
        "first ground killed {:.1} s after it started, alfa's goto #{t2_seq} under way",
        started.elapsed().as_secs_f64()
    );

    let second = fly(&swarm, &server, &["--resume", &log_arg])?;
    let out = tokio::time::timeout(Duration::from_secs(180), second.wait_with_output())
        .await
        .map_err(|_| anyhow::anyhow!("the resumed ground did not finish within 180 s"))??;
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(
        out.status.success(),
        "the resumed ground failed\nstdout:\n{stdout}\nstderr:\n{stderr}"
    );
    let resumed_s = killed_at.elapsed().as_secs_f64();

    let lines = records(&log_path);
    let after = log::last_mission(&lines);
    println!("the resumed mission:\n{}", log::timeline(after));
    let memory = after
        .iter()
        .find_map(|l| match &l.record {
            Record::Resumed { memory, .. } => Some(memory.clone()),
            _ => None,
        })
        .ok_or_else(|| anyhow::anyhow!("no resumed record in the second mission:\n{stdout}"))?;
    let plan = memory
        .plan
        .ok_or_else(|| anyhow::anyhow!("the resumed memory has no plan"))?;
    let task = |id: &str| plan.tasks.iter().find(|t| t.call.task == id);
    assert_eq!(
        task("T2").map(|t| (&t.status, t.sent.as_ref().map(|(_, s)| *s))),
        Some((&TaskStatus::Running, Some(t2_seq))),
        "the goto under way came back running, as sent"
    );
    assert_eq!(
        task("T1").map(|t| &t.status),
        Some(&TaskStatus::Done),
        "alfa's take-off came back done"
    );
    assert!(
        memory
            .history
            .iter()
            .any(|e| matches!(e, tacos_prompts::render::HistoryEntry::Pilot(_))),
        "the pilot's instruction is in the resumed history"
    );

    let sent_after: Vec<(String, String)> = after
        .iter()
        .filter_map(|l| match &l.record {
            Record::ActionSent { task, action, .. } => {
                Some((task.clone().unwrap_or_default(), action.clone()))
            }
            _ => None,
        })
        .collect();
    assert!(
        !sent_after.iter().any(|(t, _)| t == "T1"),
        "alfa's take-off was sent again: {sent_after:?}"
    );
    assert!(
        sent_after.iter().any(|(t, _)| t == "T3"),
        "the new ground did not send the last goto: {sent_after:?}"
    );
    let t2_done_as_sent = after.iter().any(
        |l| matches!(&l.record, Record::ActionOutcome { seq, failure: None, .. } if *seq == t2_seq),
    );
    let t2_sent_again = sent_after.iter().any(|(t, _)| t == "T2");
    assert!(
        t2_done_as_sent || t2_sent_again,
        "the goto under way was neither seen through nor sent again"
    );
    assert!(
        after
            .iter()
            .any(|l| matches!(l.record, Record::PlanComplete { .. })),
        "the resumed plan did not complete"
    );
    // The model's calls of the second ground: Supervisor cycles only, no new plan.
    assert!(
        !after
            .iter()
            .any(|l| matches!(l.record, Record::PlanAdopted { .. })),
        "the resumed ground planned anew"
    );
    println!(
        "resumed and completed {resumed_s:.1} s after the kill; alfa's goto under way was {}; sent by the new ground: {sent_after:?}",
        if t2_done_as_sent {
            "seen through as sent by the old ground"
        } else {
            "sent again (the drone's ground-silence failsafe had held it)"
        }
    );
    let _ = std::fs::remove_file(&log_path);
    swarm.stop().await;
    Ok(())
}

//! `tacos-ground demo --script` as CI runs it: the real binary and a whole simulated swarm,
//! against an OpenAI-compatible server on loopback whose stand-in model reads each prompt and
//! answers as a competent model would (and whose first answer is a 503, as a loading server's
//! is). The script takes all off, sends one drone to a car, lands all; the mission log must
//! show each action sent once, its outcome, and the order a pilot asked for. A failing step and
//! a malformed script must end the run non-zero, naming their line.

use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::time::Duration;
use tacos_ground::mission::log::{self, Line as LogLine, Record};
use tacos_tests::chat_server::{ChatServer, PolicyResult};
use tacos_tests::prompt_text::{body_text, plan_lines, section, swarm_lines};

fn call(task: &str, drone: &str, action: &str, target: &str) -> Value {
    json!({ "task": task, "drone": drone, "action": action, "target": target, "xyz": null })
}

/// The stand-in model: it plans what the pilot's instruction says, for the drones the prompt
/// lists, and starts each task when its drone can do it. The first request gets a 503.
fn policy(index: usize, request: &Value) -> PolicyResult {
    if index == 0 {
        return Err((503, "the model is still loading".into()));
    }
    let Some((system, user)) = body_text(request) else {
        return Err((400, "no request in the messages".into()));
    };
    if system.starts_with("You are the Coordinator") {
        let instruction = section(&user, "Instruction").trim().to_lowercase();
        let drones = swarm_lines(&user);
        let calls: Vec<Value> = if instruction.contains("take off") {
            drones
                .iter()
                .filter(|(_, mode, _, _)| mode == "idle")
                .enumerate()
                .map(|(i, (d, _, _, _))| call(&format!("T{}", i + 1), d, "arm_takeoff", "none"))
                .collect()
        } else {
            // "<drone>, go to <place>"
            let words: Vec<String> = instruction
                .split(|c: char| c.is_whitespace() || c == ',')
                .filter(|w| !w.is_empty())
                .map(str::to_owned)
                .collect();
            match (words.first(), words.last()) {
                (Some(d), Some(place)) if drones.iter().any(|(x, _, _, _)| x == d) => {
                    // A place the schema does not offer does not exist: a capable model says
                    // so instead of guessing one, where the schema lets it decline.
                    let format = &request["response_format"];
                    if !enum_names(format).contains(place)
                        && format
                            .pointer("/json_schema/schema/properties/refusal")
                            .is_some()
                    {
                        return Ok(json!({
                            "reasoning": format!("No landmark or target is called {place}."),
                            "plan": [],
                            "refusal": format!("There is no {place} on this map: name a landmark or give a point."),
                        })
                        .to_string());
                    }
                    vec![call("T1", d, "goto", place)]
                }
                _ => Vec::new(),
            }
        };
        return Ok(json!({ "reasoning": format!("Doing what the pilot asked: {instruction}."), "plan": calls }).to_string());
    }
    // The Supervisor: start every task whose drone can do it now, one per drone.
    let drones = swarm_lines(&user);
    let tasks = plan_lines(&user);
    let mut actions: Vec<Value> = Vec::new();
    for (task, drone, action, target, status) in &tasks {
        if status != "not started" {
            continue;
        }
        let Some((_, mode, busy, _)) = drones.iter().find(|(d, _, _, _)| d == drone) else {
            continue;
        };
        let ready = !busy
            && match action.as_str() {
                "arm_takeoff" => mode == "idle",
                _ => mode == "flying",
            };
        if ready && !actions.iter().any(|a| a["drone"] == drone.as_str()) {
            actions.push(call(task, drone, action, target));
        }
    }
    let complete = tasks.iter().all(|t| t.4 == "done");
    Ok(json!({ "reasoning": "Start what can start now.", "actions": actions, "plan_complete": complete }).to_string())
}

/// Whether the log holds no action sent, by a model or a direct command.
fn nothing_sent(lines: &[LogLine]) -> bool {
    !lines
        .iter()
        .any(|l| matches!(l.record, Record::Direct { .. } | Record::ActionSent { .. }))
}

/// Every name an `enum` of the request's schema offers.
fn enum_names(value: &Value) -> Vec<String> {
    match value {
        Value::Object(map) => map
            .iter()
            .flat_map(|(key, v)| match (key.as_str(), v) {
                ("enum", Value::Array(items)) => items
                    .iter()
                    .filter_map(|i| i.as_str().map(str::to_owned))
                    .collect(),
                _ => enum_names(v),
            })
            .collect(),
        Value::Array(items) => items.iter().flat_map(enum_names).collect(),
        _ => Vec::new(),
    }
}

fn temp(name: &str, ext: &str) -> PathBuf {
    std::env::temp_dir().join(format!("{}.{ext}", tacos_tests::unique_swarm(name)))
}

/// Runs `tacos-ground demo --script` with three drones in the city; (success, stdout, stderr).
async fn demo(
    script: &Path,
    server: &ChatServer,
    log: &Path,
) -> anyhow::Result<(bool, String, String)> {
    demo_with(script, server, log, &[]).await
}

/// [`demo`] with more arguments.
async fn demo_with(
    script: &Path,
    server: &ChatServer,
    log: &Path,
    more: &[&str],
) -> anyhow::Result<(bool, String, String)> {
    let ground = tacos_ground::launch::bin_dir().join("tacos-ground");
    let output = tokio::time::timeout(
        Duration::from_secs(280),
        tokio::process::Command::new(ground)
            .args(["demo", "--drones", "3", "--llm-url", &server.url])
            .args(["--model", &server.model])
            .arg("--script")
            .arg(script)
            .arg("--log")
            .arg(log)
            .args(more)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .map_err(|_| anyhow::anyhow!("the demo did not end within 280 s"))??;
    Ok((
        output.status.success(),
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    ))
}

/// Index of the first record matching `f`, or a failure naming `what`.
fn position(lines: &[LogLine], what: &str, f: impl Fn(&Record) -> bool) -> usize {
    match lines.iter().position(|l| f(&l.record)) {
        Some(i) => i,
        None => panic!("the mission log has no {what}"),
    }
}

/// Index of the `done` outcome of the action sent with `seq`.
fn done(lines: &[LogLine], seq: u64) -> usize {
    position(
        lines,
        &format!("done outcome for #{seq}"),
        |r| matches!(r, Record::ActionOutcome { seq: s, outcome, .. } if *s == seq && outcome == "done"),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_script_takes_off_flies_one_goto_and_lands_all_in_order() -> anyhow::Result<()> {
    let server = ChatServer::start("stand-in", policy).await?;
    let script = temp("script", "txt");
    std::fs::write(
        &script,
        "# CI: all take off, one goto, land all\n\
         say all drones take off\n\
         wait until all drones flying within 90\n\
         wait until plan complete within 60\n\
         say alfa, go to car_11\n\
         wait until alfa near car_11 within 120\n\
         wait until plan complete within 60\n\
         say land all\n\
         wait until all drones landed within 120\n\
         expect no breaches\n",
    )?;
    let log_path = temp("script", "jsonl");
    let (ok, stdout, stderr) = demo_with(&script, &server, &log_path, &["--trace-steps"]).await?;
    assert!(
        ok,
        "the script failed\nstdout:\n{stdout}\nstderr:\n{stderr}"
    );
    // The traced mission fed to a fresh core sends the same, in order.
    let ground = tacos_ground::launch::bin_dir().join("tacos-ground");
    let replay = std::process::Command::new(ground)
        .args(["replay", "--check"])
        .arg(&log_path)
        .output()?;
    let said = String::from_utf8_lossy(&replay.stdout);
    assert!(
        replay.status.success() && said.contains("sends, the same as the log's"),
        "{said}\n{}",
        String::from_utf8_lossy(&replay.stderr)
    );
    // The loading server's 503 was retried, then every request was answered.
    assert_eq!(server.count(503), 1, "stdout:\n{stdout}");
    assert!(
        server.count(200) >= 4,
        "two Coordinator and two Supervisor calls at least"
    );

    let lines = log::read(&log_path)?;
    // The closing summary is the log's own count.
    let summary = format!("demo finished: {};", log::Tally::of(&lines));
    assert!(stdout.contains(&summary), "no {summary:?} in:\n{stdout}");
    let sent: Vec<(usize, String, String, u64)> = lines
        .iter()
        .enumerate()
        .filter_map(|(i, l)| match &l.record {
            Record::ActionSent {
                drone, action, seq, ..
            } => Some((i, drone.clone(), action.clone(), *seq)),
            _ => None,
        })
        .collect();
    let of = |name: &str| -> Vec<&(usize, String, String, u64)> {
        sent.iter().filter(|s| s.2.starts_with(name)).collect()
    };
    let (takeoffs, gotos, lands) = (of("arm_takeoff"), of("goto"), of("land"));
    assert_eq!(sent.len(), 7, "3 take-offs, 1 goto, 3 landings: {sent:?}");
    let mut drones: Vec<&str> = takeoffs.iter().map(|s| s.1.as_str()).collect();
    drones.sort_unstable();
    assert_eq!(drones, ["alfa", "bravo", "charlie"], "one take-off each");
    assert_eq!(gotos.len(), 1);
    assert_eq!(gotos[0].1, "alfa", "the goto went to the drone named");
    let mut landed: Vec<&str> = lands.iter().map(|s| s.1.as_str()).collect();
    landed.sort_unstable();
    assert_eq!(landed, ["alfa", "bravo", "charlie"], "one landing each");

    // Order: each take-off done → (alfa's) the goto sent → goto done → land all → landings done.
    let alfa_takeoff = takeoffs.iter().find(|s| s.1 == "alfa").map_or(0, |s| s.3);
    assert!(
        done(&lines, alfa_takeoff) < gotos[0].0,
        "goto before alfa was up"
    );
    let goto_done = done(&lines, gotos[0].3);
    let direct = position(
        &lines,
        "direct land all",
        |r| matches!(r, Record::Direct { text, .. } if text == "land all"),
    );
    for t in &takeoffs {
        assert!(
            done(&lines, t.3) < direct,
            "{} landed before its take-off finished",
            t.1
        );
    }
    for l in &lands {
        assert!(
            goto_done < l.0,
            "a landing was sent before the goto finished"
        );
        assert!(
            l.0 < direct,
            "the land actions are logged before the direct command's summary"
        );
        assert!(done(&lines, l.3) > l.0);
    }
    let pilot: Vec<&str> = lines
        .iter()
        .filter_map(|l| match &l.record {
            Record::Pilot { text } => Some(text.as_str()),
            _ => None,
        })
        .collect();
    assert_eq!(
        pilot,
        ["all drones take off", "alfa, go to car_11"],
        "land all never reached the models"
    );
    assert!(
        !lines
            .iter()
            .any(|l| matches!(l.record, Record::GateRejected { .. })),
        "a competent model's calls all pass the gate"
    );
    position(
        &lines,
        "script verdict",
        |r| matches!(r, Record::Event { text } if text == "script complete: 9 steps"),
    );
    let _ = std::fs::remove_file(&script);
    let _ = std::fs::remove_file(&log_path);
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failing_step_ends_the_run_non_zero_naming_its_line() -> anyhow::Result<()> {
    let server = ChatServer::start("stand-in", policy).await?;
    let script = temp("failing", "txt");
    // Nothing was asked to fly, so no drone can be near the car within 2 s.
    std::fs::write(
        &script,
        "expect all drones landed\nwait until alfa near car_11 within 2\nsay land all\n",
    )?;
    let log_path = temp("failing", "jsonl");
    let (ok, stdout, stderr) = demo(&script, &server, &log_path).await?;
    assert!(!ok, "the run must fail\nstdout:\n{stdout}");
    assert!(
        stderr.contains(
            "script line 2 `wait until alfa near car_11 within 2` failed: not within 2 s"
        ),
        "unclear error: {stderr}"
    );
    let lines = log::read(&log_path)?;
    position(
        &lines,
        "the failure in the log",
        |r| matches!(r, Record::Event { text } if text.starts_with("script line 2")),
    );
    assert!(
        !lines
            .iter()
            .any(|l| matches!(l.record, Record::Direct { .. })),
        "the step after the failing one ran"
    );
    assert_eq!(
        server.exchanges.lock().map_or(1, |e| e.len()),
        0,
        "no model was asked"
    );
    let _ = std::fs::remove_file(&script);
    let _ = std::fs::remove_file(&log_path);
    Ok(())
}

/// The stand-in plans nothing for an instruction that names none of the swarm's drones; every
/// repair round is refused too, so the mission gives the instruction up: the waiting step ends
/// then, with the mission's reason, not when its 600 s run out. (An instruction addressed to a
/// drone the swarm lacks, "zulu, go to car_11", is refused before any model call:
/// `mission.rs`.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_step_waiting_on_an_instruction_the_mission_gave_up_fails_at_once() -> anyhow::Result<()>
{
    let server = ChatServer::start("stand-in", policy).await?;
    let script = temp("gaveup", "txt");
    std::fs::write(
        &script,
        "say somebody go to car_11\nwait until plan complete within 600\nsay land all\n",
    )?;
    let log_path = temp("gaveup", "jsonl");
    let started = std::time::Instant::now();
    let (ok, stdout, stderr) = demo(&script, &server, &log_path).await?;
    let took = started.elapsed();
    assert!(!ok, "the run must fail\nstdout:\n{stdout}");
    assert!(
        stderr.contains(
            "script line 2 `wait until plan complete within 600` failed: the mission gave up: "
        ) && stderr
            .contains("no acceptable reply after 3 attempts; last problem: the plan is empty"),
        "unclear error: {stderr}"
    );
    assert!(
        took < Duration::from_secs(120),
        "the step waited {took:?} after the mission gave up"
    );
    let lines = log::read(&log_path)?;
    assert!(nothing_sent(&lines), "something was sent");
    // A failed run still closes with what happened: three Coordinator requests, nothing sent.
    let tally = log::Tally::of(&lines);
    assert_eq!(
        (tally.model_calls, tally.model_actions),
        (3, 0),
        "{tally:?}"
    );
    assert!(
        stdout.contains(&format!("demo finished: {tally};")),
        "no summary in:\n{stdout}"
    );
    let _ = std::fs::remove_file(&script);
    let _ = std::fs::remove_file(&log_path);
    Ok(())
}

/// "alfa, go to the_airport" on a map without one, with the `plan-only` aid off: the model
/// declines with a reason instead of planning, the pilot hears it, nothing is sent, and the step
/// waiting on it fails at once with the reason, after one Coordinator call (no repair rounds for
/// a refusal).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_instruction_the_coordinator_declines_is_answered_with_its_reason() -> anyhow::Result<()>
{
    let server = ChatServer::start("stand-in", policy).await?;
    let script = temp("declined", "txt");
    std::fs::write(
        &script,
        "say alfa, go to the_airport\nwait until plan complete within 600\n",
    )?;
    let log_path = temp("declined", "jsonl");
    let started = std::time::Instant::now();
    let (ok, stdout, stderr) =
        demo_with(&script, &server, &log_path, &["--aids", "small,-plan-only"]).await?;
    assert!(!ok, "the run must fail\nstdout:\n{stdout}");
    assert!(
        stderr.contains(
            "script line 2 `wait until plan complete within 600` failed: the mission gave up: \
             the Coordinator declined: There is no the_airport on this map: name a landmark or \
             give a point. (nothing was sent)"
        ),
        "unclear error: {stderr}"
    );
    assert!(started.elapsed() < Duration::from_secs(120));
    let lines = log::read(&log_path)?;
    assert!(nothing_sent(&lines), "something was sent");
    assert!(
        lines.iter().any(|l| matches!(&l.record, Record::Event { text }
            if text.starts_with("instruction declined by the Coordinator: There is no the_airport"))),
        "the refusal is not in the log"
    );
    assert_eq!(
        log::Tally::of(&lines).model_calls,
        1,
        "a refusal is not repaired"
    );
    let _ = std::fs::remove_file(&script);
    let _ = std::fs::remove_file(&log_path);
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_malformed_script_is_refused_before_anything_starts() -> anyhow::Result<()> {
    let server = ChatServer::start("stand-in", policy).await?;
    let script = temp("malformed", "txt");
    std::fs::write(&script, "say all drones take off\n\nwait until pigs fly\n")?;
    let log_path = temp("malformed", "jsonl");
    let (ok, _, stderr) = demo(&script, &server, &log_path).await?;
    assert!(!ok);
    assert!(
        stderr.contains("line 3: unknown drone state \"fly\""),
        "unclear error: {stderr}"
    );
    assert!(!log_path.exists(), "a mission started");
    let _ = std::fs::remove_file(&script);
    Ok(())
}

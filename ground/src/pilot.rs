//! A pilot's session with the language-model layers, without the full-screen terminal: lines
//! given up front (`--say`) or typed on standard input, updates printed as they happen.

use crate::link::GroundLink;
use crate::mission::log::MissionLog;
use crate::mission::{EventTopic, MissionConfig, MissionHandle, MissionStats, MissionUpdate};
use crate::safety::SafetyGate;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tacos_llm::LlmBackend;
use tokio::io::AsyncBufReadExt;

#[derive(Debug, Clone)]
pub struct SessionOptions {
    pub mission: MissionConfig,
    /// Pilot lines sent one after the other, each once the previous one's plan completed.
    pub say: Vec<String>,
    /// Then read further lines from standard input until it closes.
    pub interactive: bool,
    pub log_path: PathBuf,
    /// Longest wait for one line's plan to complete.
    pub line_timeout: Duration,
    pub verbose: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error(transparent)]
    Log(#[from] crate::mission::log::LogError),
    #[error(transparent)]
    Link(#[from] crate::link::LinkError),
    #[error("{line:?}: {reason}")]
    Line { line: String, reason: String },
}

#[derive(Debug, Clone)]
pub struct SessionReport {
    pub stats: MissionStats,
    pub log_path: PathBuf,
}

/// One line of text for an update, as the headless modes print it; none for a reply still being
/// written (the whole reply is printed when it is in).
pub fn describe(update: &MissionUpdate) -> Option<String> {
    let text = match update {
        MissionUpdate::Writing { .. } => return None,
        MissionUpdate::Thinking { layer } => format!("{layer} thinking…"),
        MissionUpdate::CallDropped { layer, by } => {
            format!("{layer}: the call in flight was dropped, overtaken by {by}")
        }
        MissionUpdate::Plan { reasoning, calls } => format!(
            "coordinator: {reasoning}\n           plan: {}",
            calls.join("; ")
        ),
        MissionUpdate::Cycle {
            plan_cycle,
            reasoning,
            actions,
        } => {
            format!(
                "supervisor cycle {plan_cycle}: {reasoning} → [{}]",
                actions.join("; ")
            )
        }
        MissionUpdate::Rejected { layer, refusal, by } => {
            format!("{by} refused a call of the {layer}'s reply: {refusal}")
        }
        MissionUpdate::Sent { drone, action, seq } => format!("sent #{seq} {action} to {drone}"),
        MissionUpdate::Outcome {
            drone,
            action,
            outcome,
            ..
        } => format!("{drone}: {action} {outcome}"),
        MissionUpdate::Event { text, .. } => format!("event: {text}"),
        MissionUpdate::PlanComplete { cycles } => {
            format!("plan complete after {cycles} supervisor cycles")
        }
        MissionUpdate::Error(text) => format!("error: {text}"),
        MissionUpdate::Call {
            layer,
            latency,
            prompt_tokens,
            completion_tokens,
        } => format!(
            "{layer} answered in {:.1} s ({prompt_tokens} + {completion_tokens} tokens)",
            latency.as_secs_f64()
        ),
    };
    Some(text)
}

/// Runs the session; returns when every line was carried out (or stdin closed).
pub async fn run_session(
    link: Arc<GroundLink>,
    gate: SafetyGate,
    backend: Arc<dyn LlmBackend>,
    opts: SessionOptions,
) -> Result<SessionReport, SessionError> {
    let log = Arc::new(MissionLog::create(&opts.log_path)?.timed_by(link.clock()));
    let link_for_terminal = link.clone();
    let scenario = gate.scenario().clone();
    let description = backend.describe();
    let MissionHandle {
        input,
        mut updates,
        task,
    } = MissionHandle::start(opts.mission.clone(), backend, gate, link, log.clone()).await?;
    let start = Instant::now();
    let say = |text: &str| {
        if opts.verbose {
            println!("[{:>6.1}s] {text}", start.elapsed().as_secs_f64());
        }
    };

    let mut result = Ok(());
    // A resumed mission's plan is carried out before anything new is said.
    let resumed_plan = opts
        .mission
        .resume
        .as_ref()
        .is_some_and(|r| r.memory.plan.is_some());
    if resumed_plan {
        say("going on with the resumed plan");
        if let Err(reason) = carried_out(&mut updates, opts.line_timeout, &say).await {
            result = Err(SessionError::Line {
                line: "(the resumed plan)".into(),
                reason,
            });
        }
    }
    for line in opts.say.iter().filter(|_| result.is_ok()) {
        say(&format!("pilot: {line}"));
        if input.submit(line).await.is_err() {
            result = Err(SessionError::Line {
                line: line.clone(),
                reason: "the mission stopped".into(),
            });
            break;
        }
        if let Err(reason) = carried_out(&mut updates, opts.line_timeout, &say).await {
            result = Err(SessionError::Line {
                line: line.clone(),
                reason,
            });
            break;
        }
    }

    if result.is_ok() && opts.interactive && std::io::IsTerminal::is_terminal(&std::io::stdout()) {
        // The pilot's full-screen terminal: map, swarm, chat, events, status.
        let targets = link_for_terminal.watch_targets().await?;
        // The swarm table lists this run's drones, not every slot of the map (a demo of six
        // drones in the city would show fourteen "unavailable" rows).
        let mut scenario = scenario;
        {
            let view = link_for_terminal.view();
            if view.drones().next().is_some() {
                scenario.drones.retain(|d| view.get(&d.id).is_some());
            }
        }
        if let Err(e) = crate::tui::run_terminal(
            link_for_terminal.clone(),
            scenario,
            crate::tui::Session {
                backend: description,
                confirm: opts.mission.confirm,
            },
            updates,
            input.clone(),
            targets,
        )
        .await
        {
            result = Err(SessionError::Line {
                line: "(terminal)".into(),
                reason: e.to_string(),
            });
        }
    } else if result.is_ok() && opts.interactive {
        let mut stdin = tokio::io::BufReader::new(tokio::io::stdin()).lines();
        println!(
            "type an instruction for the swarm (\"alfa, take off\", \"land all\", \"cancel\", \"undo\", …); Ctrl-D to end"
        );
        loop {
            tokio::select! {
                line = stdin.next_line() => match line {
                    Ok(Some(text)) if text.trim() == "quit" => break,
                    Ok(Some(text)) => {
                        if input.submit(&text).await.is_err() {
                            break;
                        }
                    }
                    _ => break,
                },
                update = updates.recv() => match update {
                    Some(u) => {
                        if let Some(text) = describe(&u) {
                            say(&text);
                        }
                    }
                    None => break,
                },
            }
        }
    }
    drop(input);
    let stats = task.stats().await;
    result.map(|()| SessionReport {
        stats,
        log_path: log.path().to_owned(),
    })
}

/// Waits until the plan under way completes (or a direct command was carried out), telling the
/// pilot what happens; the mission's error, or the timeout, otherwise.
async fn carried_out(
    updates: &mut tokio::sync::mpsc::UnboundedReceiver<MissionUpdate>,
    timeout: Duration,
    say: &impl Fn(&str),
) -> Result<(), String> {
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        match tokio::time::timeout_at(deadline, updates.recv()).await {
            Err(_) => return Err(format!("not carried out within {timeout:?}")),
            Ok(None) => return Err("the mission stopped".to_owned()),
            Ok(Some(update)) => {
                if let Some(text) = describe(&update) {
                    say(&text);
                }
                match update {
                    MissionUpdate::PlanComplete { .. } => return Ok(()),
                    MissionUpdate::Error(reason) => return Err(reason),
                    // A direct command is carried out at once; nothing more to wait for.
                    MissionUpdate::Event {
                        topic: EventTopic::Direct,
                        ..
                    } => return Ok(()),
                    _ => {}
                }
            }
        }
    }
}

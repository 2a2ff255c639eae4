//! `tacos-ground demo`: brings up a simulated swarm on loopback and flies it, either with the
//! language-model layers (the pilot's lines go to the Coordinator and Supervisor) or, with
//! `--no-llm`, a fixed pattern through the same gate and link a pilot uses — all take off, each
//! flies to a point, all land — checking every phase against the simulator's ground truth.

use crate::direct::run_actions;
use crate::launch::{Stack, StackConfig};
use crate::link::{GroundLink, LinkError};
use crate::pilot::{SessionOptions, SessionReport, run_session};
use crate::safety::SafetyGate;
use crate::script::{Script, ScriptOptions, ScriptReport, run_script};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tacos_bus::BusArgs;
use tacos_llm::LlmBackend;
use tacos_shared::action::Action;
use tacos_shared::messages::SimTruth;
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, DroneMode, SwarmId, Vec3};
use tokio::sync::watch;

#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    #[error(transparent)]
    Launch(#[from] crate::launch::LaunchError),
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error("{0}")]
    Step(String),
    #[error("{name} exited unexpectedly ({status}); logs in {logs}")]
    ChildDied {
        name: String,
        status: String,
        logs: String,
    },
    #[error("interrupted")]
    Interrupted,
}

#[derive(Debug, Clone)]
pub struct DemoOptions {
    pub scenario_arg: String,
    pub scenario: Scenario,
    pub drones: usize,
    /// Printed progress goes here (stdout in the binary).
    pub verbose: bool,
}

/// What the demo does once the swarm is up.
pub enum DemoPlan {
    /// All take off, each flies to a point, all land; checked in the simulator's truth.
    Fixed,
    /// A pilot session with the language-model layers.
    Llm {
        backend: Arc<dyn LlmBackend>,
        session: SessionOptions,
    },
    /// A pilot script, headless (`crate::script`).
    Script {
        backend: Arc<dyn LlmBackend>,
        script: Script,
        options: ScriptOptions,
    },
}

/// What a finished demo reports.
#[derive(Debug)]
pub enum DemoReport {
    /// The fixed pattern was flown and checked.
    Flown,
    Session(SessionReport),
    Script(ScriptReport),
}

/// Runs the whole demo; every child is shut down before this returns.
pub async fn run_demo(
    opts: DemoOptions,
    plan: DemoPlan,
    interrupt: impl std::future::Future<Output = ()>,
) -> Result<DemoReport, DemoError> {
    let swarm = SwarmId::new(format!("demo{}", std::process::id()))
        .map_err(|e| DemoError::Step(e.to_string()))?;
    let config = StackConfig::on_loopback(
        swarm.clone(),
        &opts.scenario_arg,
        opts.scenario.clone(),
        opts.drones,
    )?;
    let logs = config.log_dir.display().to_string();
    let link = Arc::new(
        GroundLink::connect(&BusArgs::loopback(
            swarm,
            Some(config.hub_endpoint.clone()),
            vec![],
        ))
        .await?,
    );
    let mut stack = Stack::start(config)?;
    let truth = link.watch_truth().await?;
    let gate = SafetyGate::new(opts.scenario.clone());

    let ids = stack.config.drone_ids();
    tokio::pin!(interrupt);
    let died = |e: crate::launch::ChildExit| DemoError::ChildDied {
        name: e.name,
        status: match e.status {
            Ok(s) => s.to_string(),
            Err(e) => e,
        },
        logs: logs.clone(),
    };
    let mut result = tokio::select! {
        r = async {
            match plan {
                DemoPlan::Fixed => fly(&link, &gate, &ids, truth, opts.verbose).await.map(|()| DemoReport::Flown),
                DemoPlan::Llm { backend, session } => {
                    link.wait_for_drones(&ids, Duration::from_secs(60), |s| s.autopilot_link && s.mode == DroneMode::Idle).await?;
                    let report = run_session(link.clone(), gate.clone(), backend, session)
                        .await
                        .map_err(|e| DemoError::Step(e.to_string()))?;
                    Ok(DemoReport::Session(report))
                }
                DemoPlan::Script { backend, script, options } => {
                    link.wait_for_drones(&ids, Duration::from_secs(60), |s| s.autopilot_link && s.mode == DroneMode::Idle).await?;
                    let report = run_script(link.clone(), gate.clone(), backend, &script, options)
                        .await
                        .map_err(|e| DemoError::Step(e.to_string()))?;
                    Ok(DemoReport::Script(report))
                }
            }
        } => r,
        exit = stack.next_exit() => Err(match exit {
            Some(e) => died(e),
            None => DemoError::Step("the process supervisor stopped".into()),
        }),
        _ = &mut interrupt => Err(DemoError::Interrupted),
    };
    // The link can notice a drone vanish before the supervisor reaps its process: name the
    // process as the cause when that is what happened.
    if matches!(result, Err(DemoError::Step(_) | DemoError::Link(_)))
        && let Some(exit) = stack.exit_within(Duration::from_millis(500)).await
    {
        result = Err(died(exit));
    }
    stack.shutdown(Duration::from_secs(3)).await;
    result
}

struct Say {
    start: Instant,
    verbose: bool,
}

impl Say {
    fn line(&self, text: impl AsRef<str>) {
        if self.verbose {
            println!(
                "[{:>6.1}s] {}",
                self.start.elapsed().as_secs_f64(),
                text.as_ref()
            );
        }
    }
}

async fn fly(
    link: &GroundLink,
    gate: &SafetyGate,
    ids: &[DroneId],
    mut truth: watch::Receiver<Option<SimTruth>>,
    verbose: bool,
) -> Result<(), DemoError> {
    let say = Say {
        start: Instant::now(),
        verbose,
    };
    let scenario = gate.scenario();
    let limits = scenario.limits;
    say.line(format!("waiting for {} drones to come up", ids.len()));
    link.wait_for_drones(ids, Duration::from_secs(60), |s| {
        s.autopilot_link && s.mode == DroneMode::Idle
    })
    .await?;
    say.line("all drones alive, autopilot links up, on the ground");

    let homes: Vec<Vec3> = ids
        .iter()
        .map(|id| scenario.drone(id).map_or(Vec3::zeros(), |s| s.home))
        .collect();

    phase(
        link,
        gate,
        &say,
        "take off",
        ids.iter()
            .map(|id| (id.clone(), Action::ArmTakeoff))
            .collect(),
    )
    .await?;
    check_truth(
        &mut truth,
        &say,
        "every vehicle is at take-off altitude",
        |t| {
            ids.iter().zip(&homes).all(|(id, home)| {
                t.vehicles.iter().any(|v| {
                    &v.drone == id
                        && v.armed
                        && v.position.z >= home.z + 0.8 * limits.takeoff_altitude
                })
            })
        },
    )
    .await?;

    let span = scenario.world.bounds.max.y - scenario.world.bounds.min.y;
    let goals: Vec<Vec3> = homes
        .iter()
        .map(|h| Vec3::new(h.x, h.y + 0.1 * span, h.z + limits.takeoff_altitude))
        .collect();
    let gotos = ids
        .iter()
        .zip(&goals)
        .map(|(id, g)| (id.clone(), Action::Goto { target: *g }))
        .collect();
    phase(link, gate, &say, "fly to points", gotos).await?;
    let tolerance = 1.5 * (2.0 * limits.drone_radius).max(0.2);
    check_truth(&mut truth, &say, "every vehicle is at its point", |t| {
        ids.iter().zip(&goals).all(|(id, g)| {
            t.vehicles
                .iter()
                .any(|v| &v.drone == id && (v.position - g).norm() <= tolerance)
        })
    })
    .await?;

    phase(
        link,
        gate,
        &say,
        "land",
        ids.iter().map(|id| (id.clone(), Action::Land)).collect(),
    )
    .await?;
    check_truth(
        &mut truth,
        &say,
        "every vehicle has landed and disarmed",
        |t| {
            ids.iter().all(|id| {
                t.vehicles
                    .iter()
                    .any(|v| &v.drone == id && v.landed && !v.armed)
            })
        },
    )
    .await?;
    let last = truth.borrow().clone();
    if let Some(t) = last {
        say.line(format!(
            "done: min pair distance {:.1} m, separation breaches {}, obstacle breaches {}",
            t.min_pair_distance, t.separation_breaches, t.obstacle_breaches
        ));
        if t.separation_breaches > 0 || t.obstacle_breaches > 0 {
            return Err(DemoError::Step(
                "the simulator recorded a separation or obstacle breach".into(),
            ));
        }
    }
    Ok(())
}

/// Runs one phase of the pattern: an action per drone, all at once, all to completion.
async fn phase(
    link: &GroundLink,
    gate: &SafetyGate,
    say: &Say,
    name: &str,
    actions: Vec<(DroneId, Action)>,
) -> Result<(), DemoError> {
    say.line(format!("{name}: sending {} actions", actions.len()));
    let task = name.replace(' ', "_");
    run_actions(link, gate, &actions, Some(&task), Duration::from_secs(60))
        .await
        .map_err(|e| DemoError::Step(format!("{name}: {e}")))?;
    say.line(format!("{name}: all done"));
    Ok(())
}

/// Waits (bounded) until the simulator's truth satisfies `ok`.
async fn check_truth(
    truth: &mut watch::Receiver<Option<SimTruth>>,
    say: &Say,
    what: &str,
    ok: impl Fn(&SimTruth) -> bool,
) -> Result<(), DemoError> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        if truth.borrow().as_ref().is_some_and(&ok) {
            say.line(format!("simulator truth: {what}"));
            return Ok(());
        }
        match tokio::time::timeout_at(deadline, truth.changed()).await {
            Ok(Ok(())) => {}
            _ => {
                return Err(DemoError::Step(format!(
                    "simulator truth does not show that {what}"
                )));
            }
        }
    }
}

//! `tacos-ground demo`: brings up a simulated swarm on loopback and flies it, either with the
//! language-model layers (the pilot's lines go to the Coordinator and Supervisor) or, with
//! `--no-llm`, one of the fixed patterns of `patterns` through the same gate and link a pilot
//! uses, checking every phase against the simulator's ground truth.

use crate::launch::{AutopilotKind, Role, Stack, StackConfig};
use crate::link::{GroundLink, LinkError};
use crate::patterns::{fly_points, fly_swap};
use crate::pilot::{SessionOptions, SessionReport, run_session};
use crate::safety::SafetyGate;
use crate::script::{Script, ScriptOptions, ScriptReport, run_script};
use std::sync::Arc;
use std::time::Duration;
use tacos_llm::LlmBackend;
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, DroneMode, SwarmId};
use tracing::{info, warn};

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
    /// Simulated seconds per wall second while no model call is in flight.
    pub sim_speed: f64,
    pub autopilot: crate::launch::AutopilotKind,
    /// Printed progress goes here (stdout in the binary).
    pub verbose: bool,
}

/// What the demo does once the swarm is up.
pub enum DemoPlan {
    /// All take off, each flies to a point, all land; checked in the simulator's truth.
    Fixed,
    /// All take off, form a circle round the business district, swap to the antipodal points
    /// through the skyscrapers, land; checked in the simulator's truth, breaches included.
    Swap,
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
    mut plan: DemoPlan,
    interrupt: impl std::future::Future<Output = ()>,
) -> Result<DemoReport, DemoError> {
    let swarm = SwarmId::new(format!("demo{}", std::process::id()))
        .map_err(|e| DemoError::Step(e.to_string()))?;
    let mut config = StackConfig::on_loopback(
        swarm.clone(),
        &opts.scenario_arg,
        opts.scenario.clone(),
        opts.drones,
    )?;
    config.sim_speed = opts.sim_speed;
    config.autopilot = opts.autopilot.clone();
    // The drones join through the ground's session as zenoh clients: a star, like a deployment's
    // drones through its router (`deploy/zenoh/client.json5`), instead of a mesh of every process
    // with every other. On one machine the mesh costs: in the 20-drone swap zenoh's threads took
    // 37 % of the two cores as 210 links (22 % as a star), and the drones fell to 13-16 solves a
    // second where the swap crosses (18-19 as a star).
    config.onboard_args.push("--zenoh-client".into());
    let logs = config.log_dir.display().to_string();
    let link = Arc::new(GroundLink::connect(&config.ground_bus()).await?);
    // On PX4 SITL the simulator owns no vehicle: a script's `fail <drone>` comes here, and the
    // drone's PX4 instance (its autopilot and its simulated airframe) is killed.
    let (deaths_tx, mut deaths) = tokio::sync::mpsc::unbounded_channel::<DroneId>();
    if let (AutopilotKind::Px4Sitl { .. }, DemoPlan::Script { options, .. }) =
        (&config.autopilot, &mut plan)
    {
        options.vehicle_deaths = Some(deaths_tx);
    }
    let mut killed: Vec<DroneId> = Vec::new();
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
    let flight = async {
        match plan {
            DemoPlan::Fixed => fly_points(&link, &gate, &ids, truth, opts.verbose)
                .await
                .map(|()| DemoReport::Flown),
            DemoPlan::Swap => fly_swap(&link, &gate, &ids, truth, opts.verbose)
                .await
                .map(|()| DemoReport::Flown),
            DemoPlan::Llm { backend, session } => {
                link.wait_for_drones(&ids, Duration::from_secs(60), |s| {
                    s.autopilot_link && s.mode == DroneMode::Idle
                })
                .await?;
                let report = run_session(link.clone(), gate.clone(), backend, session)
                    .await
                    .map_err(|e| DemoError::Step(e.to_string()))?;
                Ok(DemoReport::Session(report))
            }
            DemoPlan::Script {
                backend,
                script,
                options,
            } => {
                link.wait_for_drones(&ids, Duration::from_secs(60), |s| {
                    s.autopilot_link && s.mode == DroneMode::Idle
                })
                .await?;
                let report = run_script(link.clone(), gate.clone(), backend, &script, options)
                    .await
                    .map_err(|e| DemoError::Step(e.to_string()))?;
                Ok(DemoReport::Script(report))
            }
        }
    };
    tokio::pin!(flight);
    let mut result = loop {
        tokio::select! {
            r = &mut flight => break r,
            Some(drone) = deaths.recv() => {
                match stack.crash(Role::Px4, Some(&drone)).await {
                    Some(exit) => info!(%drone, status = ?exit.status, "PX4 SITL instance killed: the vehicle fails"),
                    None => warn!(%drone, "no PX4 SITL instance of this drone was running"),
                }
                killed.push(drone);
            }
            exit = stack.next_exit() => match exit {
                // A killed vehicle's writer may give up on its dead autopilot: expected.
                Some(e) if e.drone.as_ref().is_some_and(|d| killed.contains(d)) => {
                    warn!(child = %e.name, status = ?e.status, "a failed vehicle's process ended");
                }
                Some(e) => break Err(died(e)),
                None => break Err(DemoError::Step("the process supervisor stopped".into())),
            },
            _ = &mut interrupt => break Err(DemoError::Interrupted),
        }
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

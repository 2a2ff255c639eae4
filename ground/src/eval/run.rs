//! One evaluation run: a fresh simulated swarm on loopback (its own swarm id and ports), the
//! task's set-up through the safety gate, the pilot's lines to a mission in the chosen mode, the
//! injected failure, and a watch on the simulator's truth and events that stops the run as soon
//! as its outcome is decided. The verdict and figures come from `criteria`.

use super::criteria::{self, Observed, Verdict};
use super::results::{RunRecord, Status};
use super::task::{FaultKind, FaultTrigger, TaskSpec};
use crate::direct::run_actions;
use crate::launch::{Role, Stack, StackConfig};
use crate::link::GroundLink;
use crate::mission::log::{self, MissionLog};
use crate::mission::{MissionConfig, MissionHandle, MissionUpdate, Mode, ModelAids};
use crate::safety::SafetyGate;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tacos_llm::LlmBackend;
use tacos_shared::action::Action;
use tacos_shared::messages::{FaultRequest, SimTruth, WorldEvent};
use tacos_shared::scenario::{self, Scenario};
use tacos_shared::{DroneId, DroneMode, SwarmId};
use tokio::sync::Mutex;

/// Everything one run needs.
#[derive(Clone)]
pub struct RunPlan {
    pub task: TaskSpec,
    pub scenario: Scenario,
    /// Where the task's target hides (from [`TaskSpec::validate`]).
    pub hiding_place: Option<String>,
    pub mode: Mode,
    pub drones: usize,
    pub run: u32,
    pub seed: u64,
    pub temperature: f32,
    pub time_limit: Duration,
    pub backend: Arc<dyn LlmBackend>,
    pub aids: ModelAids,
    pub log_path: PathBuf,
    /// How long the mission may go without any news while no drone is busy before the run is
    /// judged stalled (the Supervisor runs at least every `cycle_timeout` while a plan runs).
    pub cycle_timeout: Duration,
    /// Simulated seconds per wall second while no model call is in flight. Time limits, fault
    /// delays and the times recorded are simulated (mission) time.
    pub sim_speed: f64,
}

/// Why a run could not be carried out (not a verdict on the model).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct Infra(String);

fn infra(e: impl std::fmt::Display) -> Infra {
    Infra(e.to_string())
}

/// A swarm id no other run (in this or another process) uses.
fn run_swarm(plan: &RunPlan) -> Result<SwarmId, Infra> {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    SwarmId::new(format!(
        "ev{}{}{}r{}x{nanos}",
        std::process::id(),
        plan.mode.as_str(),
        plan.drones,
        plan.run
    ))
    .map_err(infra)
}

/// Carries out one run; never panics on what the swarm or the model do. `start_lock` makes
/// runs that share the machine bring their swarms up one at a time: free ports are picked by
/// probing, so two stacks must not probe before the first has bound its ports.
pub async fn run_once(plan: RunPlan, start_lock: Arc<Mutex<()>>) -> RunRecord {
    let started = Instant::now();
    let mut record = RunRecord {
        task: plan.task.name.clone(),
        mode: plan.mode.as_str().to_owned(),
        drones: plan.drones,
        run: plan.run,
        seed: plan.seed,
        backend: plan.backend.describe(),
        aids: plan.aids.to_string(),
        status: Status::Error,
        reason: String::new(),
        elapsed_s: 0.0,
        sim_speed: plan.sim_speed,
        mission_s: None,
        cycles: 0,
        model_calls: 0,
        replies: 0,
        latency_ms_total: 0,
        prompt_tokens: 0,
        completion_tokens: 0,
        gate_rejections: 0,
        actions_sent: 0,
        separation_breaches: 0,
        obstacle_breaches: 0,
        detected_by: None,
        fault: None,
        log: plan.log_path.display().to_string(),
    };
    let outcome = carry_out(&plan, start_lock, &mut record).await;
    record.elapsed_s = started.elapsed().as_secs_f64();
    match outcome {
        Ok(Verdict::Success) => {
            record.status = Status::Success;
            record.reason = "suspect found".to_owned();
            if plan.task.success.detected.is_none() {
                record.reason = "every drone airborne".to_owned();
            }
        }
        Ok(Verdict::Failure(why)) => {
            record.status = Status::Failure;
            record.reason = why;
        }
        Err(Infra(why)) => {
            record.status = Status::Error;
            record.reason = why;
        }
    }
    record
}

async fn carry_out(
    plan: &RunPlan,
    start_lock: Arc<Mutex<()>>,
    record: &mut RunRecord,
) -> Result<Verdict, Infra> {
    let swarm = run_swarm(plan)?;
    let (link, stack) = {
        let _one_at_a_time = start_lock.lock().await;
        let mut config = StackConfig::on_loopback(
            swarm.clone(),
            &plan.task.scenario,
            plan.scenario.clone(),
            plan.drones,
        )
        .map_err(infra)?;
        config.sim_speed = plan.sim_speed;
        let link = Arc::new(
            GroundLink::connect(&config.ground_bus())
                .await
                .map_err(infra)?,
        );
        let stack = Stack::start(config).map_err(infra)?;
        let ids = stack.config.drone_ids();
        let up = link
            .wait_for_drones(&ids, Duration::from_secs(90), |s| {
                s.autopilot_link && s.mode == DroneMode::Idle
            })
            .await;
        if let Err(e) = up {
            stack.shutdown(Duration::from_secs(3)).await;
            return Err(Infra(format!("the swarm did not come up: {e}")));
        }
        (link, stack)
    };
    let mut stack = stack;
    let result = fly(plan, &link, &mut stack, record).await;
    stack.shutdown(Duration::from_secs(3)).await;
    let verdict = result?;
    // The log is complete now: read the figures and audit it.
    let lines = log::read(&plan.log_path).map_err(infra)?;
    let figures = criteria::log_figures(&lines);
    record.cycles = figures.cycles;
    record.model_calls = figures.model_calls;
    record.replies = figures.replies;
    record.latency_ms_total = figures.latency_ms_total;
    record.prompt_tokens = figures.prompt_tokens;
    record.completion_tokens = figures.completion_tokens;
    record.gate_rejections = figures.gate_rejections;
    record.actions_sent = figures.actions_sent;
    let unchecked = criteria::unchecked_sends(&lines, &SafetyGate::new(plan.scenario.clone()));
    Ok(verdict.with_audit(unchecked, plan))
}

/// What `fly` saw, before the log audit is added.
struct Seen {
    observed: Observed,
}

impl Seen {
    fn with_audit(mut self, unchecked_sent: Vec<String>, plan: &RunPlan) -> Verdict {
        self.observed.unchecked_sent = unchecked_sent;
        criteria::judge(
            &plan.task.success,
            &self.observed,
            plan.time_limit.as_secs_f64(),
        )
    }
}

fn airborne(truth: &SimTruth, ids: &[DroneId], scenario: &Scenario) -> bool {
    ids.iter().all(|id| {
        let ground = scenario.drone(id).map_or(0.0, |s| s.home.z);
        truth.vehicles.iter().any(|v| {
            &v.drone == id
                && v.armed
                && v.position.z >= ground + 0.8 * scenario.limits.takeoff_altitude
        })
    })
}

async fn fly(
    plan: &RunPlan,
    link: &Arc<GroundLink>,
    stack: &mut Stack,
    record: &mut RunRecord,
) -> Result<Seen, Infra> {
    let ids = stack.config.drone_ids();
    let gate = SafetyGate::new(plan.scenario.clone());
    let mut truth = link.watch_truth().await.map_err(infra)?;
    let mut events = link.watch_events().await.map_err(infra)?;

    if plan.task.setup.take_off {
        let all: Vec<(DroneId, Action)> = ids
            .iter()
            .map(|id| (id.clone(), Action::ArmTakeoff))
            .collect();
        run_actions(link, &gate, &all, Some("setup"), Duration::from_secs(90))
            .await
            .map_err(|e| Infra(format!("set-up take-off: {e}")))?;
    }

    // A resumed run starts its log afresh.
    let _ = std::fs::remove_file(&plan.log_path);
    let log = Arc::new(
        MissionLog::create(&plan.log_path)
            .map_err(infra)?
            .timed_by(link.clock()),
    );
    let config = MissionConfig {
        mode: plan.mode,
        seed: Some(plan.seed),
        aids: plan.aids,
        temperature: plan.temperature,
        cycle_timeout: plan.cycle_timeout,
        ..MissionConfig::default()
    };
    // The pilot's lines go in as a pilot types them. Dropping the task when the run ends,
    // however it ends, stops the mission.
    let MissionHandle {
        input,
        mut updates,
        task: _mission,
    } = MissionHandle::start(
        config,
        plan.backend.clone(),
        gate.clone(),
        link.clone(),
        log,
    )
    .await
    .map_err(infra)?;

    let mut pilot = plan.task.pilot.iter().filter(|l| !l.trim().is_empty());
    // Mission time is the ground's clock: the simulator's, which runs faster than real time
    // between model calls when the stack was started with a speed above 1.
    let clock = link.clock().clone();
    let start = clock.now();
    let elapsed = || clock.now() - start;
    let deadline = start + plan.time_limit.as_secs_f64();
    if let Some(first) = pilot.next()
        && input.submit(first).await.is_err()
    {
        return Err(Infra("the mission stopped at once".into()));
    }

    let mut seen = Observed::default();
    let mut fault_at: Option<(f64, DroneId)> = None;
    let mut fault_armed = plan.task.fault.is_some();
    let mut failed: Option<DroneId> = None;
    let mut last_news = clock.now();
    // A model call is under way (from the request until the engine acts on the reply): a
    // small model on a CPU may take minutes, which is not a stalled mission.
    let mut thinking = false;
    let mut finished_at: Option<f64> = None;
    let stalled_after = 3.0 * plan.cycle_timeout.as_secs_f64();
    let mut tick = tokio::time::interval(Duration::from_millis(500));
    let target = plan.task.success.detected.clone();

    let outcome: Result<(), Infra> = loop {
        let fault_due = async {
            match &fault_at {
                Some((at, _)) => clock.sleep_until(*at).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            () = clock.sleep_until(deadline) => break Ok(()),
            exit = stack.next_exit() => {
                // The failed drone's processes may end with it; any other exit breaks the run.
                if exit.as_ref().is_some_and(|e| e.drone.is_some() && e.drone == failed) {
                    continue;
                }
                break Err(Infra(match exit {
                    Some(e) => format!("{} exited ({:?}); logs in {}", e.name, e.status, stack.config.log_dir.display()),
                    None => "the process supervisor stopped".into(),
                }));
            }
            event = events.recv() => match event {
                Some(WorldEvent::Detection { drone, target: t, landmark, .. }) => {
                    if target.as_deref() == Some(t.as_str()) && landmark == plan.hiding_place {
                        seen.detected_by = Some(drone.to_string());
                        seen.goal_at_s.get_or_insert(elapsed());
                    }
                }
                Some(WorldEvent::FaultInjected { drone, fault }) => {
                    record.fault.get_or_insert(format!("{drone}: {fault} at {:.1} s", elapsed()));
                }
                None => break Err(Infra("the world event stream closed".into())),
            },
            changed = truth.changed() => {
                if changed.is_err() {
                    break Err(Infra("the simulator's truth stream closed".into()));
                }
                let t = truth.borrow_and_update().clone();
                if let Some(t) = t {
                    seen.separation_breaches = t.separation_breaches;
                    seen.obstacle_breaches = t.obstacle_breaches;
                    if airborne(&t, &ids, &plan.scenario) && !seen.all_airborne {
                        seen.all_airborne = true;
                        if plan.task.success.detected.is_none() {
                            seen.goal_at_s.get_or_insert(elapsed());
                        }
                    }
                }
            }
            update = updates.recv() => {
                last_news = clock.now();
                match &update {
                    Some(MissionUpdate::Thinking { .. }) => thinking = true,
                    Some(MissionUpdate::Plan { .. } | MissionUpdate::Cycle { .. } | MissionUpdate::Error(_) | MissionUpdate::PlanComplete { .. } | MissionUpdate::CallDropped { .. }) => thinking = false,
                    _ => {}
                }
                match update {
                    Some(MissionUpdate::Sent { drone, action, .. }) if fault_armed && action.starts_with("goto") => {
                        if let (Some(fault), Ok(drone)) = (&plan.task.fault, DroneId::new(&drone)) {
                            match fault.trigger {
                                FaultTrigger::FirstGoto => {
                                    fault_armed = false;
                                    fault_at = Some((clock.now() + fault.delay_s, drone));
                                }
                            }
                        }
                    }
                    Some(MissionUpdate::PlanComplete { .. }) => match pilot.next() {
                        Some(line) => {
                            if input.submit(line).await.is_err() {
                                break Ok(());
                            }
                        }
                        None => {
                            finished_at.get_or_insert(clock.now());
                        }
                    },
                    Some(_) => {}
                    None => break Ok(()),
                }
            }
            _ = fault_due => {
                if let (Some((_, drone)), Some(fault)) = (fault_at.take(), &plan.task.fault) {
                    failed = Some(drone.clone());
                    let request = FaultRequest { drone: drone.clone(), fault: scenario::FaultKind::VehicleDies };
                    if let Err(e) = tacos_bus::put(link.session(), &link.keys().sim_faults(), &request, tacos_bus::Delivery::Command).await {
                        break Err(Infra(format!("injecting the fault: {e}")));
                    }
                    if fault.kind == FaultKind::PowerLoss {
                        // The companion computer goes down with the vehicle; `crash` reaps the
                        // two processes, so their exits are not taken for a broken run.
                        stack.crash(Role::Onboard, Some(&drone)).await;
                        stack.crash(Role::Writer, Some(&drone)).await;
                        record.fault = Some(format!("{drone}: power loss at {:.1} s", elapsed()));
                    }
                }
            }
            _ = tick.tick() => {
                // The mission has stopped: its last plan completed (a detection on the way
                // may still be in flight: give it a moment), or nothing has happened for a long
                // time while no drone has anything to do.
                let idle = !link.view().drones().any(|e| e.alive && e.busy());
                let now = clock.now();
                if finished_at.is_some_and(|t| now - t >= 2.0)
                    || (idle && !thinking && now - last_news >= stalled_after)
                {
                    break Ok(());
                }
            }
        }
        if criteria::failed_for_good(&seen) || criteria::goal_reached(&plan.task.success, &seen) {
            break Ok(());
        }
    };
    // The outcome is decided: the mission (perhaps waiting on a model) is stopped at once.
    drop(input);
    record.mission_s = Some(elapsed());
    outcome?;
    record.separation_breaches = seen.separation_breaches;
    record.obstacle_breaches = seen.obstacle_breaches;
    record.detected_by = seen.detected_by.clone();
    Ok(Seen { observed: seen })
}

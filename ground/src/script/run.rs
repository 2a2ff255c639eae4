//! Runs a script against a live swarm: the mission engine with the language-model layers, the
//! pilot's lines through [`PilotInput`] (so direct commands are instant, as typed), conditions
//! read from the swarm view, the simulator's events and truth, and the engine's updates.

use super::parse::{Condition, DroneState, Script, StepKind, Victim, Who};
use crate::link::GroundLink;
use crate::mission::log::{MissionLog, Record};
use crate::mission::{MissionConfig, MissionHandle, MissionStats, MissionUpdate, PilotInput};
use crate::pilot::describe;
use crate::safety::SafetyGate;
use crate::swarm::SwarmView;
use std::collections::BTreeSet;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tacos_llm::LlmBackend;
use tacos_shared::action::Action;
use tacos_shared::messages::{SimTruth, TargetObservation, WorldEvent};
use tacos_shared::scenario::{FaultKind, Scenario};
use tacos_shared::{DroneId, DroneMode};
use tokio::sync::{mpsc, watch};

/// How often a `wait until` looks again when nothing woke it.
const POLL: Duration = Duration::from_millis(200);

#[derive(Debug, Clone)]
pub struct ScriptOptions {
    pub mission: MissionConfig,
    pub log_path: PathBuf,
    /// Print each step and each update (stdout).
    pub verbose: bool,
    /// Where `fail <drone>` goes when the simulator does not own the vehicles (PX4 SITL: the
    /// launcher kills that drone's PX4 instance, autopilot and simulated vehicle at once).
    /// `None`: the simulator kills its own vehicle.
    pub vehicle_deaths: Option<mpsc::UnboundedSender<DroneId>>,
}

#[derive(Debug, Clone)]
pub struct ScriptReport {
    pub stats: MissionStats,
    pub log_path: PathBuf,
    pub steps: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum ScriptError {
    #[error(transparent)]
    Log(#[from] crate::mission::log::LogError),
    #[error(transparent)]
    Link(#[from] crate::link::LinkError),
    #[error("script line {line} `{text}` failed: {reason}")]
    Step {
        line: usize,
        text: String,
        reason: String,
    },
}

/// What the script has seen so far, beside the live swarm view.
#[derive(Debug, Default)]
struct Seen {
    detected: BTreeSet<String>,
    /// Plans made since the last `say`: only their completion counts for `plan complete`.
    plans_since_say: u32,
    /// Completions of plans made since the last `say`. The plan in force when the pilot spoke
    /// may still complete after it (its Supervisor goes on until the Coordinator answers): the
    /// find-the-dog script's "keep monitoring" once passed on the search plan's completion,
    /// before its own plan was made.
    plans_complete_since_say: u32,
    plans_since_fail: u32,
    /// Drones a `fail` step killed: `all` no longer counts them.
    killed: Vec<DroneId>,
    /// What the mission last gave up on since the last `say` (a plan given up, an instruction
    /// no reply could carry out, a model that failed): a `wait until` ends with it at once.
    gave_up_since_say: Option<String>,
}

impl Seen {
    /// What `update` tells the conditions.
    fn take(&mut self, update: &MissionUpdate) {
        match update {
            MissionUpdate::PlanComplete { .. } if self.plans_since_say > 0 => {
                self.plans_complete_since_say += 1
            }
            MissionUpdate::Plan { .. } => {
                self.plans_since_fail += 1;
                self.plans_since_say += 1;
            }
            MissionUpdate::Error(why) => self.gave_up_since_say = Some(why.clone()),
            _ => {}
        }
    }

    /// The pilot spoke: what counted since the last `say` starts again.
    fn said(&mut self) {
        self.plans_complete_since_say = 0;
        self.plans_since_say = 0;
        self.gave_up_since_say = None;
    }
}

/// Everything a condition is judged on, at one instant.
struct Facts<'a> {
    view: &'a SwarmView,
    now: Instant,
    scenario: &'a Scenario,
    /// The drones of the run, in the map's order.
    drones: &'a [DroneId],
    targets: &'a [TargetObservation],
    truth: Option<&'a SimTruth>,
    seen: &'a Seen,
}

impl Facts<'_> {
    fn mode(&self, id: &DroneId) -> DroneMode {
        self.view
            .get(id)
            .map_or(DroneMode::Unavailable, |e| e.effective_mode(self.now))
    }

    /// Whether one drone is in `state`.
    fn is(&self, id: &DroneId, state: &DroneState) -> bool {
        let mode = self.mode(id);
        match state {
            DroneState::Flying => mode.is_airborne(),
            DroneState::Landed => mode == DroneMode::Idle,
            DroneState::Unavailable => mode == DroneMode::Unavailable,
            DroneState::Tracking(None) => mode == DroneMode::Tracking,
            DroneState::Tracking(Some(target)) => mode == DroneMode::Tracking
                && self
                    .view
                    .get(id)
                    .and_then(|e| e.status.as_ref())
                    .and_then(|s| s.action.as_ref())
                    .is_some_and(
                        |p| matches!(&p.action, Action::StartTracking { target: t } if t == target),
                    ),
            DroneState::Near(place) => {
                let Some(at) = self.place(place) else {
                    return false;
                };
                let radius = 2.0 * self.scenario.limits.detection_radius;
                mode != DroneMode::Unavailable
                    && self
                        .view
                        .get(id)
                        .and_then(|e| e.status.as_ref())
                        .is_some_and(|s| (s.position.x - at.x).hypot(s.position.y - at.y) <= radius)
            }
        }
    }

    /// A landmark's position, or where a visible target was last observed.
    fn place(&self, name: &str) -> Option<tacos_shared::Vec3> {
        self.scenario
            .world
            .landmarks
            .iter()
            .find(|l| l.name == name)
            .map(|l| l.position)
            .or_else(|| {
                self.targets
                    .iter()
                    .find(|t| t.name == name)
                    .map(|t| t.position)
            })
    }

    /// Each drone's mode, for messages: "alfa flying, bravo idle".
    fn summary(&self) -> String {
        self.drones
            .iter()
            .map(|d| format!("{d} {}", self.mode(d)))
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Ok when the condition holds; otherwise what was seen instead.
    fn check(&self, condition: &Condition) -> Result<(), String> {
        let holds = match condition {
            Condition::Drones { who, state } => {
                let count = |ids: &mut dyn Iterator<Item = &DroneId>| {
                    ids.filter(|d| self.is(d, state)).count()
                };
                match who {
                    Who::All => {
                        let counted: Vec<&DroneId> = self
                            .drones
                            .iter()
                            .filter(|d| !self.seen.killed.contains(d))
                            .collect();
                        !counted.is_empty() && count(&mut counted.iter().copied()) == counted.len()
                    }
                    Who::Any => count(&mut self.drones.iter()) >= 1,
                    Who::AtLeast(n) => count(&mut self.drones.iter()) >= *n,
                    Who::Drone(d) => self
                        .drones
                        .iter()
                        .any(|x| x.as_str() == d && self.is(x, state)),
                }
            }
            Condition::Detected(target) => self.seen.detected.contains(target),
            Condition::PlanComplete => self.seen.plans_complete_since_say > 0,
            Condition::Replanned => self.seen.plans_since_fail > 0,
            Condition::NoBreaches => {
                return match self.truth {
                    None => Err("no ground truth from the simulator yet".into()),
                    Some(t) if t.separation_breaches > 0 || t.obstacle_breaches > 0 => {
                        Err(format!(
                            "{} separation and {} obstacle breaches (closest pair {:.2} m)",
                            t.separation_breaches, t.obstacle_breaches, t.min_pair_distance
                        ))
                    }
                    Some(_) => Ok(()),
                };
            }
        };
        if holds {
            Ok(())
        } else {
            let detected = if self.seen.detected.is_empty() {
                "nothing".to_owned()
            } else {
                self.seen
                    .detected
                    .iter()
                    .cloned()
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            Err(format!(
                "{condition} does not hold: {}; detected {detected}; plans complete since the last say: {}",
                self.summary(),
                self.seen.plans_complete_since_say
            ))
        }
    }
}

/// The running script: the mission's pilot input and what it reports.
struct Runner {
    link: Arc<GroundLink>,
    scenario: Scenario,
    drones: Vec<DroneId>,
    input: PilotInput,
    log: Arc<MissionLog>,
    updates: mpsc::UnboundedReceiver<MissionUpdate>,
    events: mpsc::Receiver<WorldEvent>,
    targets: watch::Receiver<Vec<TargetObservation>>,
    truth: watch::Receiver<Option<SimTruth>>,
    seen: Seen,
    start: Instant,
    verbose: bool,
    vehicle_deaths: Option<mpsc::UnboundedSender<DroneId>>,
}

impl Runner {
    fn say(&self, text: &str) {
        if self.verbose {
            println!("[{:>6.1}s] {text}", self.start.elapsed().as_secs_f64());
        }
    }

    fn update(&mut self, update: &MissionUpdate) {
        if let Some(text) = describe(update) {
            self.say(&text);
        }
        self.seen.take(update);
    }

    fn event(&mut self, event: &WorldEvent) {
        self.say(&format!("world: {event}"));
        if let WorldEvent::Detection { target, .. } = event {
            self.seen.detected.insert(target.clone());
        }
    }

    /// Takes in whatever has arrived without waiting.
    fn drain(&mut self) {
        while let Ok(u) = self.updates.try_recv() {
            self.update(&u);
        }
        while let Ok(e) = self.events.try_recv() {
            self.event(&e);
        }
    }

    fn check(&self, condition: &Condition) -> Result<(), String> {
        let targets = self.targets.borrow().clone();
        let truth = self.truth.borrow().clone();
        let view = self.link.view();
        Facts {
            view: &view,
            now: self.link.clock().instant(),
            scenario: &self.scenario,
            drones: &self.drones,
            targets: &targets,
            truth: truth.as_ref(),
            seen: &self.seen,
        }
        .check(condition)
    }

    /// Follows the mission for `span` of the ground's clock (the simulator's in a simulated
    /// run), or until `done` says stop.
    async fn follow_until(
        &mut self,
        span: Duration,
        mut done: impl FnMut(&Runner) -> bool,
    ) -> bool {
        let deadline = self.link.clock().instant() + span;
        loop {
            self.drain();
            if done(self) {
                return true;
            }
            let now = self.link.clock().instant();
            if now >= deadline {
                return false;
            }
            // Polls on the wall clock; the deadline is read on the ground's clock.
            let wake = POLL.min(deadline.duration_since(now));
            tokio::select! {
                Some(u) = self.updates.recv() => self.update(&u),
                Some(e) = self.events.recv() => self.event(&e),
                _ = tokio::time::sleep(wake) => {}
            }
        }
    }

    async fn step(&mut self, kind: &StepKind) -> Result<(), String> {
        match kind {
            StepKind::Say(text) => {
                self.seen.said();
                self.input.submit(text).await.map_err(|e| e.to_string())?;
                Ok(())
            }
            StepKind::Wait(d) => {
                self.follow_until(*d, |_| false).await;
                Ok(())
            }
            StepKind::WaitUntil { condition, within } => {
                // Waiting on after the mission gave up would only run out the time.
                let mut held = false;
                self.follow_until(*within, |r| {
                    held = r.check(condition).is_ok();
                    held || r.seen.gave_up_since_say.is_some()
                })
                .await;
                if held {
                    return Ok(());
                }
                if let Some(gave_up) = &self.seen.gave_up_since_say {
                    return Err(format!("the mission gave up: {gave_up}"));
                }
                let why = self.check(condition).err().unwrap_or_default();
                Err(format!("not within {} s: {why}", within.as_secs_f64()))
            }
            StepKind::Expect(condition) => {
                self.drain();
                self.check(condition)
            }
            StepKind::Fail(victim) => {
                let drone = self.victim(victim)?;
                match &self.vehicle_deaths {
                    Some(deaths) => {
                        deaths
                            .send(drone.clone())
                            .map_err(|_| "the launcher that kills vehicles is gone".to_owned())?;
                        self.say(&format!(
                            "script: {drone} fails (its PX4 SITL instance is killed)"
                        ));
                    }
                    None => {
                        self.link
                            .inject_fault(&drone, FaultKind::VehicleDies)
                            .await
                            .map_err(|e| e.to_string())?;
                        self.say(&format!(
                            "script: {drone} fails (the simulator kills the vehicle)"
                        ));
                    }
                }
                self.seen.killed.push(drone);
                self.seen.plans_since_fail = 0;
                Ok(())
            }
        }
    }

    fn victim(&self, victim: &Victim) -> Result<DroneId, String> {
        match victim {
            Victim::Drone(d) => DroneId::new(d).map_err(|e| e.to_string()),
            Victim::One(state) => {
                let targets = self.targets.borrow().clone();
                let view = self.link.view();
                let facts = Facts {
                    view: &view,
                    now: self.link.clock().instant(),
                    scenario: &self.scenario,
                    drones: &self.drones,
                    targets: &targets,
                    truth: None,
                    seen: &self.seen,
                };
                self.drones
                    .iter()
                    .find(|d| !self.seen.killed.contains(d) && facts.is(d, state))
                    .cloned()
                    .ok_or_else(|| format!("no drone is {state}: {}", facts.summary()))
            }
        }
    }
}

/// Runs `script` step by step on a swarm that is up; returns at the first failing step.
pub async fn run_script(
    link: Arc<GroundLink>,
    gate: SafetyGate,
    backend: Arc<dyn LlmBackend>,
    script: &Script,
    opts: ScriptOptions,
) -> Result<ScriptReport, ScriptError> {
    let log = Arc::new(MissionLog::create(&opts.log_path)?.timed_by(link.clock()));
    let scenario = gate.scenario().clone();
    let drones: Vec<DroneId> = {
        let view = link.view();
        scenario
            .drones
            .iter()
            .filter(|d| view.get(&d.id).is_some())
            .map(|d| d.id.clone())
            .collect()
    };
    // Subscribed before the mission starts, so no event is missed.
    let events = link.watch_events().await?;
    let targets = link.watch_targets().await?;
    let truth = link.watch_truth().await?;
    let MissionHandle {
        input,
        updates,
        task,
    } = MissionHandle::start(
        opts.mission.clone(),
        backend,
        gate,
        link.clone(),
        log.clone(),
    )
    .await?;
    let mut runner = Runner {
        link,
        scenario,
        drones,
        input,
        log: log.clone(),
        updates,
        events,
        targets,
        truth,
        seen: Seen::default(),
        start: Instant::now(),
        verbose: opts.verbose,
        vehicle_deaths: opts.vehicle_deaths.clone(),
    };
    let mut result = Ok(());
    for step in &script.steps {
        runner.say(&format!("script line {}: {}", step.line, step.text));
        if let Err(reason) = runner.step(&step.kind).await {
            result = Err(ScriptError::Step {
                line: step.line,
                text: step.text.clone(),
                reason,
            });
            break;
        }
    }
    let verdict = match &result {
        Ok(()) => format!("script complete: {} steps", script.steps.len()),
        Err(e) => e.to_string(),
    };
    runner.log.note(Record::Event {
        text: verdict.clone(),
    });
    runner.say(&verdict);
    // Closing the input ends the mission (after any model call in flight).
    let Runner { input, .. } = runner;
    drop(input);
    let stats = task.stats().await;
    result.map(|()| ScriptReport {
        stats,
        log_path: log.path().to_owned(),
        steps: script.steps.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plan_complete_counts_only_a_plan_made_after_the_last_say() {
        let plan = MissionUpdate::Plan {
            reasoning: String::new(),
            calls: Vec::new(),
        };
        let complete = MissionUpdate::PlanComplete { cycles: 2 };
        let mut seen = Seen::default();
        seen.take(&plan);
        seen.said();
        // The plan in force when the pilot spoke completes before the new one is made.
        seen.take(&complete);
        assert_eq!(seen.plans_complete_since_say, 0);
        seen.take(&plan);
        seen.take(&complete);
        assert_eq!(seen.plans_complete_since_say, 1);
        assert_eq!(seen.plans_since_fail, 2);
        seen.said();
        assert_eq!(seen.plans_complete_since_say, 0);
    }
}

//! The engine's plan bookkeeping: the tasks of the Coordinator's plan (or the monolithic
//! model's issued calls), their outcomes as the drones report them, and when a plan is complete,
//! given up or stuck.

use super::Mission;
use super::cycles::effect_holds;
use crate::mission::config::Mode;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionUpdate};
use crate::mission::resolve::{claimed_points, position_of, resolve};
use crate::mission::resume::{PlanTask, SavedPlan};
use crate::safety::SafetyGate;
use crate::swarm::SwarmView;
use std::time::{Duration, Instant};
use tacos_prompts::render::{HistoryEntry, TaskStatus};
use tacos_prompts::{ActionName, Call};
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionState, FailureReason, TargetObservation};
use tacos_shared::{DroneId, DroneMode};

#[derive(Debug, Clone)]
pub(super) struct ActivePlan {
    pub(super) reasoning: String,
    pub(super) tasks: Vec<PlanTask>,
    /// The Supervisor's memory for this plan; cleared with it.
    pub(super) memory: Vec<String>,
    pub(super) cycles: u32,
    /// Since when nothing of the plan has been running and nothing could start.
    pub(super) stuck_since: Option<Instant>,
}

impl ActivePlan {
    /// The plan a resumed mission goes on with (`mission::resume`).
    pub(super) fn resumed(saved: SavedPlan) -> ActivePlan {
        ActivePlan {
            reasoning: saved.reasoning,
            tasks: saved.tasks,
            memory: saved.memory,
            cycles: saved.cycles,
            stuck_since: None,
        }
    }
}

/// How long a plan may have nothing running and nothing that can start before it is given up
/// (long enough for a drone's link to come back, or an outcome to arrive).
pub(super) const STUCK_AFTER: Duration = Duration::from_secs(20);

/// The monolithic variant's state. The model's prompt holds the instructions and the executed
/// actions only; `tasks` is the engine's own bookkeeping of what it issued for them.
#[derive(Debug, Default)]
pub(super) struct Monolithic {
    pub(super) instructions: Vec<String>,
    pub(super) executed: Vec<String>,
    /// Every call issued for the current instructions, with its status.
    pub(super) tasks: Vec<PlanTask>,
    /// The number of the next fresh task id (`A<n>`) offered to the model.
    pub(super) next_task: u32,
    /// The model's last reply said that its actions carry out the instructions, and every call
    /// in it passed the checks. There is no plan to hold the model to, so the engine checks
    /// what it can: the instructions count as carried out only once every action issued for
    /// them has finished successfully. A failure, a lost or joined drone, or a new instruction
    /// withdraws the claim and the model is asked again.
    pub(super) claimed_done: bool,
    pub(super) active: bool,
    pub(super) cycles: u32,
}

/// A task that ended in this poll, as the pilot is told.
pub(super) struct Finished {
    drone: String,
    action: String,
    outcome: String,
    failed: bool,
}

impl Mission {
    /// Fails `drone`'s running tasks, and its done start_tracking while it still followed the
    /// target (tracking goes on after the task is done): failed tasks may start on any drone.
    /// `following`: the target it followed ([`Self::following_of`]).
    pub(super) fn fail_tasks_of(&mut self, drone: &DroneId, following: Option<&str>, why: &str) {
        let tasks = self
            .plan
            .iter_mut()
            .flat_map(|p| p.tasks.iter_mut())
            .chain(self.mnl.tasks.iter_mut());
        for t in tasks.filter(|t| t.sent.as_ref().is_some_and(|(d, _)| d == drone)) {
            let still_following = t.status == TaskStatus::Done
                && t.call.action == ActionName::StartTracking
                && following == t.call.target_name();
            if t.status == TaskStatus::Running || still_following {
                t.status = TaskStatus::Failed(why.to_owned());
            }
        }
    }

    /// The target `drone` was following when last heard of: its last action is a start_tracking
    /// that was under way, done, or ended by the autopilot link's loss (not by losing the
    /// target, and not replaced by a newer action).
    pub(super) fn following_of(&self, drone: &DroneId) -> Option<String> {
        let view = self.link.view();
        let progress = view.get(drone)?.status.as_ref()?.action.as_ref()?;
        let Action::StartTracking { target } = &progress.action else {
            return None;
        };
        match &progress.state {
            ActionState::Running { .. }
            | ActionState::Done
            | ActionState::Failed(FailureReason::AutopilotLinkLost) => Some(target.clone()),
            ActionState::Failed(_) => None,
        }
    }

    /// `drone`'s unfinished work in the plan (its tasks not done: failed with it, or not yet
    /// started), and the target it was following if no such task names it, as call texts.
    pub(super) fn unfinished_work_of(
        &self,
        drone: &DroneId,
        following: Option<String>,
    ) -> Vec<String> {
        let mut work: Vec<String> = Vec::new();
        let mut tracking_named = false;
        for t in self.plan.iter().flat_map(|p| p.tasks.iter()) {
            let its = match &t.sent {
                Some((d, _)) => d == drone,
                None => t.call.drone == drone.as_str(),
            };
            if its && t.status != TaskStatus::Done {
                tracking_named |= t.call.action == ActionName::StartTracking
                    && following.as_deref() == t.call.target_name();
                work.push(t.call.to_string());
            }
        }
        if let Some(target) = following.filter(|_| !tracking_named) {
            work.push(format!("{drone} start_tracking({target})"));
        }
        work
    }

    /// Looks for finished actions; true when any task changed state.
    pub(super) fn poll_outcomes(&mut self) -> bool {
        let mut finished: Vec<Finished> = Vec::new();
        {
            let view = self.link.view();
            let tasks = self
                .plan
                .iter_mut()
                .flat_map(|p| p.tasks.iter_mut())
                .chain(self.mnl.tasks.iter_mut());
            // Running tasks, and tracking that is done (the drone reached its station) but goes
            // on: a target lost later fails the task, so the Supervisor can give it again.
            let watched = |t: &PlanTask| {
                t.status == TaskStatus::Running
                    || (t.status == TaskStatus::Done && t.call.action == ActionName::StartTracking)
            };
            for task in tasks.filter(|t| watched(t)) {
                let Some((drone, seq)) = &task.sent else {
                    continue;
                };
                let running = task.status == TaskStatus::Running;
                let status = view.get(drone).and_then(|e| e.status.as_ref());
                let progress = status.and_then(|s| s.action.as_ref());
                let refused = status
                    .and_then(|s| s.refused.as_ref())
                    .filter(|r| r.seq == *seq && running);
                let new = match (refused, progress) {
                    (Some(r), _) => Some(TaskStatus::Failed(format!(
                        "refused by the drone: {}",
                        r.why
                    ))),
                    (None, Some(p)) if p.seq == *seq => match &p.state {
                        ActionState::Done if running => Some(TaskStatus::Done),
                        ActionState::Failed(why) => Some(TaskStatus::Failed(why.to_string())),
                        _ => None,
                    },
                    (None, Some(p)) if p.seq > *seq && running => {
                        Some(TaskStatus::Failed("replaced by a newer action".into()))
                    }
                    _ => None,
                };
                if let Some(status) = new {
                    let outcome = match &status {
                        TaskStatus::Done => "done".to_owned(),
                        TaskStatus::Failed(why) => format!("failed: {why}"),
                        _ => String::new(),
                    };
                    self.log.note(Record::ActionOutcome {
                        drone: drone.to_string(),
                        task: Some(task.call.task.clone()),
                        seq: *seq,
                        outcome: outcome.clone(),
                        failure: match &status {
                            TaskStatus::Failed(why) => Some(why.clone()),
                            _ => None,
                        },
                    });
                    finished.push(Finished {
                        drone: drone.to_string(),
                        action: task.call.to_string(),
                        outcome,
                        failed: matches!(status, TaskStatus::Failed(_)),
                    });
                    if matches!(status, TaskStatus::Failed(_)) {
                        task.failures += 1;
                    }
                    task.status = status;
                }
            }
        }
        // After the outcomes: a task that just finished may make the next one's effect hold.
        self.mark_satisfied_tasks(&mut finished);
        for Finished {
            drone,
            action,
            outcome,
            failed,
        } in &finished
        {
            self.tell(MissionUpdate::Outcome {
                drone: drone.clone(),
                action: action.clone(),
                outcome: outcome.clone(),
                failed: *failed,
            });
            match self.cfg.mode {
                Mode::Mnl => {
                    self.mnl.executed.push(format!("{action}: {outcome}"));
                    if *failed || outcome != "done" {
                        self.mnl.claimed_done = false;
                    }
                }
                _ => {
                    if let Some(plan) = self.plan.as_mut() {
                        plan.memory.push(format!("{action}: {outcome}"));
                    }
                }
            }
        }
        if let Some(plan) = self.plan.take() {
            let given_up = plan
                .tasks
                .iter()
                .find(|t| t.failures >= self.cfg.max_task_failures)
                .map(|t| match &t.status {
                    TaskStatus::Failed(why) => {
                        format!("{} failed {} times (last: {why})", t.call, t.failures)
                    }
                    _ => format!("{} failed {} times", t.call, t.failures),
                });
            if plan.tasks.iter().all(|t| t.status == TaskStatus::Done) {
                self.finish_plan(plan, "complete");
            } else if let Some(why) = given_up {
                self.finish_plan(plan, &format!("abandoned: {why}"));
                self.tell(MissionUpdate::Error(format!(
                    "the plan was given up: {why}"
                )));
            } else {
                self.plan = Some(plan);
            }
        }
        self.judge_monolithic();
        !finished.is_empty()
    }

    /// The plan's calls that could start now: tasks not started, on their own drone; failed
    /// tasks, on any available drone; each only if its drone is idle-ready (not busy), the call
    /// resolves, and the safety gate would let it through.
    pub(super) fn startable_calls(&self) -> Vec<Call> {
        let Some(plan) = self.plan.as_ref() else {
            return Vec::new();
        };
        // Before the view is locked: `swarm_ids` locks it too, and the lock is not reentrant.
        let swarm = self.swarm_ids();
        self.with_start(|start| startable(plan, &swarm, start))
    }

    /// Runs `f` with the checks of whether a call can start, on one locked view of the swarm.
    pub(super) fn with_start<R>(&self, f: impl FnOnce(&Start<'_>) -> R) -> R {
        // Before the view is locked: each of these locks it too, and the lock is not reentrant.
        let pending = self.drones_with_pending_actions();
        let visible = self.visible_targets();
        let view = self.link.view();
        let start = Start {
            view: &view,
            gate: &self.gate,
            now: self.link.clock().instant(),
            visible: &visible,
            pending: &pending,
            ground: self.link.epoch(),
        };
        f(&start)
    }

    /// Why each of the plan's unfinished tasks cannot start now, as the pilot reads it.
    fn blockers(&self) -> Vec<String> {
        let Some(plan) = self.plan.as_ref() else {
            return Vec::new();
        };
        self.with_start(|start| {
            plan.tasks
                .iter()
                .filter(|t| t.status != TaskStatus::Done)
                .map(|t| match start.blocker(&t.call) {
                    Some(why) => format!("{} ({why})", t.call),
                    None => t.call.to_string(),
                })
                .collect()
        })
    }

    /// Drones with an action the engine sent and has not yet seen finish. A drone's status lags
    /// a send by up to a status period, so right after a cycle it can still look idle and ready:
    /// offering it again would have the model choose a call that is stale by the time it answers.
    pub(super) fn drones_with_pending_actions(&self) -> Vec<DroneId> {
        self.plan
            .iter()
            .flat_map(|p| p.tasks.iter())
            .chain(self.mnl.tasks.iter())
            .filter(|t| t.status == TaskStatus::Running)
            .filter_map(|t| t.sent.as_ref().map(|(d, _)| d.clone()))
            .collect()
    }

    /// A task whose effect already holds is done without flying it: a take-off for a drone that
    /// is airborne and idle in the air, a landing or hold for a drone resting on the ground, a
    /// goto for a drone hovering at its point.
    /// Plans from models repeat such calls; sending them would only be refused by the drone.
    pub(super) fn mark_satisfied_tasks(&mut self, finished: &mut Vec<Finished>) {
        let visible = self.visible_targets();
        let Some(plan) = self.plan.as_mut() else {
            return;
        };
        let view = self.link.view();
        let now = self.link.clock().instant();
        // As close as the drone itself calls a goto done.
        let arrive = (2.0 * self.gate.scenario().limits.drone_radius).max(0.2);
        // Only a task whose earlier tasks for the same drone are all done: "take off, then land"
        // must not count the landing as done before the take-off.
        let mut open_before: std::collections::HashSet<String> = std::collections::HashSet::new();
        for task in plan.tasks.iter_mut() {
            let blocked = open_before.contains(&task.call.drone);
            if task.status != TaskStatus::Done {
                open_before.insert(task.call.drone.clone());
            }
            if blocked || task.status != TaskStatus::NotStarted {
                continue;
            }
            let Some(entry) = DroneId::new(&task.call.drone)
                .ok()
                .and_then(|id| view.get(&id))
            else {
                continue;
            };
            let mode = entry.effective_mode(now);
            let already_there = task.call.action == ActionName::Goto
                && mode == DroneMode::Flying
                && entry.status.as_ref().is_some_and(|status| {
                    let claimed = claimed_points(&view, &task.call.drone, now);
                    matches!(
                        resolve(
                            &task.call,
                            self.gate.scenario(),
                            &visible,
                            &claimed,
                            position_of(&view, &task.call.drone),
                        ),
                        Ok(Action::Goto { target }) if (status.position - target).norm() <= arrive
                    )
                });
            if (effect_holds(task.call.action, mode) || already_there) && !entry.busy() {
                task.status = TaskStatus::Done;
                let what = if already_there {
                    "already there: nothing to do".to_owned()
                } else {
                    format!("already {mode}: nothing to do")
                };
                self.log.note(Record::Event {
                    text: format!("{}: {what}", task.call),
                });
                finished.push(Finished {
                    drone: task.call.drone.clone(),
                    action: task.call.to_string(),
                    outcome: what,
                    failed: false,
                });
            }
        }
    }

    pub(super) fn finish_plan(&mut self, plan: ActivePlan, how: &str) {
        self.work_epoch += 1;
        for t in plan.tasks.iter().filter(|t| t.status == TaskStatus::Done) {
            self.remember(HistoryEntry::Executed {
                call: t.call.clone(),
                outcome: "done".into(),
            });
        }
        if how == "complete" {
            self.stats.update(|s| s.cycles_per_plan.push(plan.cycles));
            self.log.note(Record::PlanComplete {
                cycles: plan.cycles,
            });
            self.tell(MissionUpdate::PlanComplete {
                cycles: plan.cycles,
            });
        } else {
            self.log.note(Record::PlanEnded {
                how: how.to_owned(),
            });
            self.tell(MissionUpdate::Event {
                topic: EventTopic::PlanEnded,
                text: format!("plan ended: {how}"),
            });
        }
    }

    /// Gives the plan up when, for `STUCK_AFTER`, none of its tasks has been running (or tracking,
    /// for a done start_tracking) and none could start: e.g. a goto for a drone whose plan never takes it off. Without this the
    /// plan would wait for ever.
    pub(super) fn give_up_if_stuck(&mut self) {
        let now = self.link.clock().instant();
        // Drones following a target for a done start_tracking: the plan is at work, not stuck.
        let tracking: Vec<String> = {
            let view = self.link.view();
            view.drones()
                .filter(|e| e.effective_mode(now) == DroneMode::Tracking)
                .map(|e| e.id.to_string())
                .collect()
        };
        let Some(plan) = self.plan.as_mut() else {
            return;
        };
        let at_work = |t: &PlanTask| {
            t.status == TaskStatus::Running
                || (t.status == TaskStatus::Done
                    && t.call.action == ActionName::StartTracking
                    && tracking.contains(&t.call.drone))
        };
        if plan.tasks.iter().any(at_work) {
            plan.stuck_since = None;
            return;
        }
        let since = *plan.stuck_since.get_or_insert(now);
        if now.duration_since(since) < STUCK_AFTER {
            return;
        }
        let waiting = self.blockers();
        let why = format!(
            "nothing has run or could start for {} s; waiting: {}. Give the work to another \
             drone or place, or land",
            STUCK_AFTER.as_secs(),
            waiting.join(", ")
        );
        if let Some(plan) = self.plan.take() {
            self.finish_plan(plan, &format!("abandoned: {why}"));
            self.tell(MissionUpdate::Error(format!(
                "the plan was given up: {why}"
            )));
        }
    }
}

/// What decides whether a call can start now: the swarm as seen, the gate, the targets seen and
/// the drones with an action under way.
/// The plan's calls that could start now (see `Mission::startable_calls`).
fn startable(plan: &ActivePlan, swarm: &[String], start: &Start<'_>) -> Vec<Call> {
    let mut out = Vec::new();
    // No order is imposed here: the plan's temporal dependencies are the Supervisor's to
    // infer (the paper's division of labour); the drone's mode rules what is possible.
    for task in &plan.tasks {
        let drones: Vec<String> = match &task.status {
            TaskStatus::NotStarted => vec![task.call.drone.clone()],
            TaskStatus::Failed(_) => swarm.to_vec(),
            _ => continue,
        };
        for drone in drones {
            let call = Call {
                drone,
                ..task.call.clone()
            };
            if start.blocker(&call).is_none() {
                out.push(call);
            }
        }
    }
    out
}

pub(super) struct Start<'a> {
    pub(super) view: &'a SwarmView,
    pub(super) gate: &'a SafetyGate,
    pub(super) now: Instant,
    pub(super) visible: &'a [TargetObservation],
    pub(super) pending: &'a [DroneId],
    /// This ground station (its epoch): a drone that follows another one takes none of its
    /// actions, as after a restart until the old one has been silent for the drone's hold time.
    pub(super) ground: u64,
}

impl Start<'_> {
    /// Why `call` cannot start now on its drone; `None` when it can.
    pub(super) fn blocker(&self, call: &Call) -> Option<String> {
        let drone = &call.drone;
        let Some(entry) = DroneId::new(drone).ok().and_then(|id| self.view.get(&id)) else {
            return Some(format!("{drone} is not in the swarm"));
        };
        if entry.effective_mode(self.now) == DroneMode::Unavailable {
            return Some(format!("{drone} is unavailable"));
        }
        if let Some(other) = entry
            .status
            .as_ref()
            .and_then(|s| s.ground)
            .filter(|g| *g != self.ground)
        {
            return Some(format!(
                "{drone} follows another ground station ({other}) until it falls silent"
            ));
        }
        if entry.busy() || self.pending.contains(&entry.id) {
            return Some(format!("{drone} is busy with another action"));
        }
        let claimed = claimed_points(self.view, drone, self.now);
        let action = match resolve(
            call,
            self.gate.scenario(),
            self.visible,
            &claimed,
            position_of(self.view, drone),
        ) {
            Ok(action) => action,
            Err(why) => return Some(why),
        };
        self.gate
            .check(self.view, drone, &action, self.now)
            .err()
            .map(|r| r.to_string())
    }
}

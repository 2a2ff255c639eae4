//! The outcomes the drones report, matched to the tasks they were sent for; tasks whose effect
//! already holds; and when a plan (or the monolithic model's work) is complete, given up after
//! repeated failures, or stuck.

use super::book::{ActivePlan, Monolithic, PlanBook, STUCK_AFTER};
use super::effect::Effect;
use super::snapshot::Snapshot;
use super::start::{Start, blockers};
use crate::mission::config::Mode;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionUpdate};
use crate::mission::resolve::{claimed_points, position_of, resolve};
use crate::mission::resume::PlanTask;
use crate::safety::SafetyGate;
use std::collections::HashSet;
use tacos_prompts::ActionName;
use tacos_prompts::render::{HistoryEntry, TaskStatus};
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionState, FailureReason};
use tacos_shared::{DroneId, DroneMode};

/// The mission's settings the outcome rules follow.
pub(crate) struct Rules<'a> {
    pub(crate) gate: &'a SafetyGate,
    pub(crate) mode: Mode,
    /// A task that failed this many times gives its plan up.
    pub(crate) max_task_failures: u32,
}

/// A task that ended in this poll, as the pilot is told.
struct Finished {
    drone: String,
    action: String,
    outcome: String,
    failed: bool,
}

/// The action's effect already holds for an idle drone in `mode`: take-off when airborne,
/// landing or hold on the ground, stop-tracking when not tracking. Sending it would only be
/// refused by the drone or do nothing.
pub(crate) fn effect_holds(action: ActionName, mode: DroneMode) -> bool {
    match action {
        ActionName::ArmTakeoff => mode.is_airborne(),
        ActionName::Land | ActionName::Hold => mode == DroneMode::Idle,
        ActionName::StopTracking => mode != DroneMode::Tracking,
        ActionName::Goto | ActionName::StartTracking => false,
    }
}

/// The target `drone` was following when last heard of: its last action is a start_tracking
/// that was under way, done, or ended by the autopilot link's loss (not by losing the target,
/// and not replaced by a newer action).
pub(crate) fn following_of(snap: &Snapshot, drone: &DroneId) -> Option<String> {
    let progress = snap.swarm.get(drone)?.status.as_ref()?.action.as_ref()?;
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

/// The new status of `task` from what its drone reports, if it changed.
fn reported(task: &PlanTask, snap: &Snapshot) -> Option<TaskStatus> {
    let (drone, seq) = task.sent.as_ref()?;
    let running = task.status == TaskStatus::Running;
    let status = snap.swarm.get(drone).and_then(|e| e.status.as_ref());
    let progress = status.and_then(|s| s.action.as_ref());
    let refused = status
        .and_then(|s| s.refused.as_ref())
        .filter(|r| r.seq == *seq && running);
    match (refused, progress) {
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
    }
}

/// Takes in the outcomes the snapshot shows. Returns the effects, and whether any task changed
/// state (a cycle is due).
pub(crate) fn poll(book: &mut PlanBook, snap: &Snapshot, rules: &Rules<'_>) -> (Vec<Effect>, bool) {
    let mut effects = Vec::new();
    let mut finished: Vec<Finished> = Vec::new();
    // Running tasks, and tracking that is done (the drone reached its station) but goes on: a
    // target lost later fails the task, so the Supervisor can give it again.
    let watched = |t: &PlanTask| {
        t.status == TaskStatus::Running
            || (t.status == TaskStatus::Done && t.call.action == ActionName::StartTracking)
    };
    for task in book.tasks_mut().filter(|t| watched(t)) {
        let (Some(status), Some((drone, seq))) = (reported(task, snap), task.sent.as_ref()) else {
            continue;
        };
        let failure = match &status {
            TaskStatus::Failed(why) => Some(why.clone()),
            _ => None,
        };
        let outcome = match &failure {
            Some(why) => format!("failed: {why}"),
            None => "done".to_owned(),
        };
        effects.push(Effect::Note(Record::ActionOutcome {
            drone: drone.to_string(),
            task: Some(task.call.task.clone()),
            seq: *seq,
            outcome: outcome.clone(),
            failure: failure.clone(),
        }));
        finished.push(Finished {
            drone: drone.to_string(),
            action: task.call.to_string(),
            outcome,
            failed: failure.is_some(),
        });
        if failure.is_some() {
            task.failures += 1;
        }
        task.status = status;
    }
    // After the outcomes: a task that just finished may make the next one's effect hold.
    if let Some(plan) = book.plan.as_mut() {
        mark_satisfied(plan, snap, rules.gate, &mut effects, &mut finished);
    }
    for f in &finished {
        effects.push(Effect::Tell(MissionUpdate::Outcome {
            drone: f.drone.clone(),
            action: f.action.clone(),
            outcome: f.outcome.clone(),
            failed: f.failed,
        }));
        // The monolithic model's history of executed actions; the Supervisor's memory of a
        // plan is its tasks' statuses, set above.
        if rules.mode == Mode::Mnl {
            book.mnl
                .executed
                .push(format!("{}: {}", f.action, f.outcome));
            if f.failed || f.outcome != "done" {
                book.mnl.claimed_done = false;
            }
        }
    }
    if let Some(plan) = book.plan.take() {
        let given_up = plan
            .tasks
            .iter()
            .find(|t| t.failures >= rules.max_task_failures)
            .map(|t| match &t.status {
                TaskStatus::Failed(why) => {
                    format!("{} failed {} times (last: {why})", t.call, t.failures)
                }
                _ => format!("{} failed {} times", t.call, t.failures),
            });
        if plan.tasks.iter().all(|t| t.status == TaskStatus::Done) {
            effects.extend(plan_ended(plan, "complete"));
        } else if let Some(why) = given_up {
            effects.extend(plan_ended(plan, &format!("abandoned: {why}")));
            effects.push(Effect::Tell(MissionUpdate::Error(format!(
                "the plan was given up: {why}"
            ))));
        } else {
            book.plan = Some(plan);
        }
    }
    effects.extend(judge_monolithic(&mut book.mnl));
    (effects, !finished.is_empty())
}

/// A task whose effect already holds is done without flying it: a take-off for a drone that is
/// airborne and idle in the air, a landing or hold for a drone resting on the ground, a goto
/// for a drone hovering at its point. Plans from models repeat such calls; sending them would
/// only be refused by the drone.
fn mark_satisfied(
    plan: &mut ActivePlan,
    snap: &Snapshot,
    gate: &SafetyGate,
    effects: &mut Vec<Effect>,
    finished: &mut Vec<Finished>,
) {
    let view = &snap.swarm;
    let now = snap.now;
    // As close as the drone itself calls a goto done.
    let arrive = (2.0 * gate.scenario().limits.drone_radius).max(0.2);
    // Only a task whose earlier tasks for the same drone are all done: "take off, then land"
    // must not count the landing as done before the take-off.
    let mut open_before: HashSet<String> = HashSet::new();
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
                let claimed = claimed_points(view, &task.call.drone, now);
                matches!(
                    resolve(
                        &task.call,
                        gate.scenario(),
                        &snap.targets,
                        &claimed,
                        position_of(view, &task.call.drone),
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
            effects.push(Effect::Note(Record::Event {
                text: format!("{}: {what}", task.call),
            }));
            finished.push(Finished {
                drone: task.call.drone.clone(),
                action: task.call.to_string(),
                outcome: what,
                failed: false,
            });
        }
    }
}

/// The monolithic model's instructions are carried out when its claim stands and every action
/// it issued for them has finished (a failure has withdrawn the claim already).
pub(crate) fn judge_monolithic(mnl: &mut Monolithic) -> Vec<Effect> {
    let running = mnl.tasks.iter().any(|t| t.status == TaskStatus::Running);
    if !(mnl.active && mnl.claimed_done) || running {
        return Vec::new();
    }
    mnl.active = false;
    let cycles = mnl.cycles;
    vec![
        Effect::PlanCycles(cycles),
        Effect::Note(Record::PlanComplete { cycles }),
        Effect::Tell(MissionUpdate::PlanComplete { cycles }),
    ]
}

/// A plan that ended `how` ("complete", or why it did not): its done tasks go to the history.
pub(crate) fn plan_ended(plan: ActivePlan, how: &str) -> Vec<Effect> {
    let mut effects = vec![Effect::WorkReplaced];
    effects.extend(
        plan.tasks
            .iter()
            .filter(|t| t.status == TaskStatus::Done)
            .map(|t| {
                Effect::Remember(HistoryEntry::Executed {
                    call: t.call.clone(),
                    outcome: "done".into(),
                })
            }),
    );
    if how == "complete" {
        let cycles = plan.cycles;
        effects.extend([
            Effect::PlanCycles(cycles),
            Effect::Note(Record::PlanComplete { cycles }),
            Effect::Tell(MissionUpdate::PlanComplete { cycles }),
        ]);
    } else {
        effects.extend([
            Effect::Note(Record::PlanEnded {
                how: how.to_owned(),
            }),
            Effect::Tell(MissionUpdate::Event {
                topic: EventTopic::PlanEnded,
                text: format!("plan ended: {how}"),
            }),
        ]);
    }
    effects
}

/// Gives the plan up when, for `STUCK_AFTER`, none of its tasks has been running (or tracking,
/// for a done start_tracking) and none could start: e.g. a goto for a drone whose plan never
/// takes it off. Without this the plan would wait for ever.
pub(crate) fn give_up_if_stuck(
    book: &mut PlanBook,
    snap: &Snapshot,
    gate: &SafetyGate,
) -> Vec<Effect> {
    let now = snap.now;
    // Drones following a target for a done start_tracking: the plan is at work, not stuck.
    let tracking: Vec<String> = snap
        .swarm
        .drones()
        .filter(|e| e.effective_mode(now) == DroneMode::Tracking)
        .map(|e| e.id.to_string())
        .collect();
    let at_work = |t: &PlanTask| {
        t.status == TaskStatus::Running
            || (t.status == TaskStatus::Done
                && t.call.action == ActionName::StartTracking
                && tracking.contains(&t.call.drone))
    };
    let Some(plan) = book.plan.as_mut() else {
        return Vec::new();
    };
    if plan.tasks.iter().any(at_work) {
        plan.stuck_since = None;
        return Vec::new();
    }
    let since = *plan.stuck_since.get_or_insert(now);
    if now.duration_since(since) < STUCK_AFTER {
        return Vec::new();
    }
    let start = Start::new(snap, gate, book);
    let waiting = book
        .plan
        .as_ref()
        .map(|plan| blockers(plan, &start))
        .unwrap_or_default();
    let why = format!(
        "nothing has run or could start for {} s; waiting: {}. Give the work to another drone \
         or place, or land",
        STUCK_AFTER.as_secs(),
        waiting.join(", ")
    );
    let Some(plan) = book.plan.take() else {
        return Vec::new();
    };
    let mut effects = plan_ended(plan, &format!("abandoned: {why}"));
    effects.push(Effect::Tell(MissionUpdate::Error(format!(
        "the plan was given up: {why}"
    ))));
    effects
}

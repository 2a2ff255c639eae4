//! The plan's bookkeeping: the tasks of the Coordinator's plan (or the monolithic model's
//! issued calls) with their status, and what a drone leaves undone when it is lost.

use crate::mission::resume::{PlanTask, SavedPlan};
use std::time::{Duration, Instant};
use tacos_prompts::render::TaskStatus;
use tacos_prompts::{ActionName, Call};
use tacos_shared::DroneId;

#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ActivePlan {
    pub(crate) reasoning: String,
    pub(crate) tasks: Vec<PlanTask>,
    pub(crate) cycles: u32,
    /// Since when nothing of the plan has been running and nothing could start.
    pub(crate) stuck_since: Option<Instant>,
}

impl ActivePlan {
    /// The plan a resumed mission goes on with (`mission::resume`).
    pub(crate) fn resumed(saved: SavedPlan) -> ActivePlan {
        ActivePlan {
            reasoning: saved.reasoning,
            tasks: saved.tasks,
            cycles: saved.cycles,
            stuck_since: None,
        }
    }

    /// `call` went to `drone` as its action `seq`: its task runs (a call the plan does not
    /// hold, e.g. under a task id of the Supervisor's own, is added). The Supervisor's memory
    /// of the plan is its tasks' statuses (`render::plan_memory`).
    pub(crate) fn issued(&mut self, call: Call, drone: DroneId, seq: u64) {
        let sent = Some((drone, seq));
        match self.tasks.iter_mut().find(|t| t.call.task == call.task) {
            Some(t) => {
                t.call = call;
                t.status = TaskStatus::Running;
                t.sent = sent;
            }
            None => self.tasks.push(PlanTask {
                call,
                status: TaskStatus::Running,
                sent,
                failures: 0,
            }),
        }
    }
}

/// How long a plan may have nothing running and nothing that can start before it is given up
/// (long enough for a drone's link to come back, or an outcome to arrive).
pub(crate) const STUCK_AFTER: Duration = Duration::from_secs(20);

/// The monolithic variant's state. The model's prompt holds the instructions and the executed
/// actions only; `tasks` is the engine's own bookkeeping of what it issued for them.
#[derive(Debug, Default, Clone, PartialEq)]
pub(crate) struct Monolithic {
    pub(crate) instructions: Vec<String>,
    pub(crate) executed: Vec<String>,
    /// Every call issued for the current instructions, with its status.
    pub(crate) tasks: Vec<PlanTask>,
    /// The number of the next fresh task id (`A<n>`) offered to the model.
    pub(crate) next_task: u32,
    /// The model's last reply said that its actions carry out the instructions, and every call
    /// in it passed the checks. There is no plan to hold the model to, so the engine checks
    /// what it can: the instructions count as carried out only once every action issued for
    /// them has finished successfully. A failure, a lost or joined drone, or a new instruction
    /// withdraws the claim and the model is asked again.
    pub(crate) claimed_done: bool,
    pub(crate) active: bool,
    pub(crate) cycles: u32,
}

impl Monolithic {
    /// `call` went to `drone` as its action `seq`.
    pub(crate) fn issued(&mut self, call: Call, drone: DroneId, seq: u64) {
        self.tasks.push(PlanTask {
            call,
            status: TaskStatus::Running,
            sent: Some((drone, seq)),
            failures: 0,
        });
    }
}

/// The plan in force (Coordinator and Supervisor) and the monolithic model's work.
#[derive(Debug, Default, Clone, PartialEq)]
pub(crate) struct PlanBook {
    pub(crate) plan: Option<ActivePlan>,
    pub(crate) mnl: Monolithic,
}

impl PlanBook {
    /// Every task of the plan and of the monolithic model's work.
    pub(crate) fn tasks(&self) -> impl Iterator<Item = &PlanTask> {
        self.plan
            .iter()
            .flat_map(|p| p.tasks.iter())
            .chain(self.mnl.tasks.iter())
    }

    pub(crate) fn tasks_mut(&mut self) -> impl Iterator<Item = &mut PlanTask> {
        self.plan
            .iter_mut()
            .flat_map(|p| p.tasks.iter_mut())
            .chain(self.mnl.tasks.iter_mut())
    }

    /// Fails `drone`'s running tasks, and its done start_tracking while it still followed the
    /// target (tracking goes on after the task is done): failed tasks may start on any drone.
    /// `following`: the target it followed (`outcomes::following_of`).
    pub(crate) fn fail_tasks_of(&mut self, drone: &DroneId, following: Option<&str>, why: &str) {
        for t in self
            .tasks_mut()
            .filter(|t| t.sent.as_ref().is_some_and(|(d, _)| d == drone))
        {
            let still_following = t.status == TaskStatus::Done
                && t.call.action == ActionName::StartTracking
                && following == t.call.target_name();
            if t.status == TaskStatus::Running || still_following {
                t.status = TaskStatus::Failed(why.to_owned());
            }
        }
    }

    /// `drone`'s unfinished work in the plan (its tasks not done: failed with it, or not yet
    /// started), and the target it was following if no such task names it, as call texts.
    pub(crate) fn unfinished_work_of(
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

    /// Drones with an action the engine sent and has not yet seen finish. A drone's status lags
    /// a send by up to a status period, so right after a cycle it can still look idle and ready:
    /// offering it again would have the model choose a call that is stale by the time it answers.
    pub(crate) fn pending_drones(&self) -> Vec<DroneId> {
        self.tasks()
            .filter(|t| t.status == TaskStatus::Running)
            .filter_map(|t| t.sent.as_ref().map(|(d, _)| d.clone()))
            .collect()
    }
}

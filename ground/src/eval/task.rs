//! Evaluation tasks as files (`ground/eval/tasks/*.toml`): what the pilot says, the set-up, the
//! injected failure, the time limit, and what counts as success. The paper's two tasks are
//! built in; any other file can be named by path.

use serde::Deserialize;
use std::path::Path;
use tacos_shared::scenario::Scenario;

const TAKE_OFF: &str = include_str!("../../eval/tasks/take-off.toml");
const FIND_SUSPECT: &str = include_str!("../../eval/tasks/find-suspect.toml");

/// Names of the built-in tasks.
pub const BUILTIN: [&str; 2] = ["take-off", "find-suspect"];

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TaskError {
    #[error("task file {path}: {reason}")]
    Read { path: String, reason: String },
    #[error("task {task}: {reason}")]
    Invalid { task: String, reason: String },
}

/// One evaluation task.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskSpec {
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// A built-in map (`city`, `lab`) or a scenario file, as the children are told.
    pub scenario: String,
    /// The swarm sizes run by default.
    pub drones: Vec<usize>,
    /// The pilot's lines, in order; each after the previous one's plan completed.
    pub pilot: Vec<String>,
    /// Wall-clock seconds from the first pilot line (model calls included).
    pub time_limit_s: f64,
    #[serde(default)]
    pub setup: Setup,
    pub fault: Option<FaultPlan>,
    pub success: SuccessSpec,
}

/// What is done, without a model and through the safety gate, before the pilot speaks.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Setup {
    /// Every drone takes off (Task 0's end state).
    #[serde(default)]
    pub take_off: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultTrigger {
    /// The first goto the models send in the task; the fault hits the drone that got it.
    FirstGoto,
}

/// What fails.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultKind {
    /// The whole drone is lost, as on a power loss: the simulator stops its vehicle for good and
    /// its companion processes (tacos-onboard, tacos-px4) are killed, so it leaves the swarm.
    PowerLoss,
    /// Only the autopilot stops answering (the simulator's `vehicle_dies`); the companion
    /// computer stays up and reports the drone unavailable.
    VehicleDies,
}

/// The failure injected during the task.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultPlan {
    pub trigger: FaultTrigger,
    /// Seconds after the trigger.
    pub delay_s: f64,
    pub kind: FaultKind,
}

/// What must be seen for a run to succeed, besides the conditions every run must meet (within
/// the time limit, no collision, no rejected call sent).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SuccessSpec {
    /// A detection of this hidden target at the landmark where the scenario hides it.
    pub detected: Option<String>,
    /// Every drone is airborne at take-off altitude (simulator truth).
    #[serde(default)]
    pub all_airborne: bool,
}

impl TaskSpec {
    /// A built-in task by name, or a task file by path.
    pub fn load(name_or_path: &str) -> Result<TaskSpec, TaskError> {
        let text = match name_or_path {
            "take-off" => TAKE_OFF.to_owned(),
            "find-suspect" => FIND_SUSPECT.to_owned(),
            path => std::fs::read_to_string(Path::new(path)).map_err(|e| TaskError::Read {
                path: path.to_owned(),
                reason: format!("{e} (built-in tasks: {})", BUILTIN.join(", ")),
            })?,
        };
        TaskSpec::from_toml(&text)
    }

    /// Parses a task; [`validate`](Self::validate) checks it against its scenario.
    pub fn from_toml(text: &str) -> Result<TaskSpec, TaskError> {
        let task: TaskSpec = toml::from_str(text).map_err(|e| TaskError::Read {
            path: "(text)".into(),
            reason: e.to_string(),
        })?;
        let invalid = |reason: &str| TaskError::Invalid {
            task: task.name.clone(),
            reason: reason.to_owned(),
        };
        if task.pilot.iter().all(|l| l.trim().is_empty()) {
            return Err(invalid("no pilot line"));
        }
        if !(task.time_limit_s.is_finite() && task.time_limit_s > 0.0) {
            return Err(invalid("time_limit_s must be finite and positive"));
        }
        if task
            .fault
            .as_ref()
            .is_some_and(|f| !(f.delay_s.is_finite() && f.delay_s >= 0.0))
        {
            return Err(invalid("fault.delay_s must be finite and not negative"));
        }
        if task.success.detected.is_none() && !task.success.all_airborne {
            return Err(invalid(
                "[success] names nothing to achieve (detected or all_airborne)",
            ));
        }
        Ok(task)
    }

    /// Checks the task against its scenario and the swarm size; returns the landmark where the
    /// target to detect hides, when there is one.
    pub fn validate(
        &self,
        scenario: &Scenario,
        drones: usize,
    ) -> Result<Option<String>, TaskError> {
        let invalid = |reason: String| TaskError::Invalid {
            task: self.name.clone(),
            reason,
        };
        scenario.first_drones(drones).map_err(invalid)?;
        if drones == 0 {
            return Err(invalid("a run needs at least one drone".into()));
        }
        match &self.success.detected {
            None => Ok(None),
            Some(target) => scenario
                .targets
                .iter()
                .find(|t| &t.name == target)
                .and_then(|t| t.hidden_at.clone())
                .map(Some)
                .ok_or_else(|| {
                    invalid(format!(
                        "scenario {} hides no target named {target:?}",
                        scenario.name
                    ))
                }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_tasks_load_and_fit_the_city() {
        let city = Scenario::builtin("city").expect("city");
        let t0 = TaskSpec::load("take-off").expect("take-off");
        assert!(t0.success.all_airborne && t0.fault.is_none() && !t0.setup.take_off);
        let t1 = TaskSpec::load("find-suspect").expect("find-suspect");
        assert_eq!(t1.drones, vec![6, 12, 20]);
        assert!(t1.setup.take_off);
        assert_eq!(
            t1.fault.as_ref().map(|f| (f.trigger, f.kind)),
            Some((FaultTrigger::FirstGoto, FaultKind::PowerLoss))
        );
        for n in [6, 12, 20] {
            assert_eq!(
                t1.validate(&city, n).expect("valid"),
                Some("car_7".to_owned())
            );
            assert_eq!(t0.validate(&city, n).expect("valid"), None);
        }
        assert!(t1.validate(&city, 21).is_err(), "the city has 20 slots");
    }

    #[test]
    fn bad_task_files_are_refused() {
        let good = FIND_SUSPECT;
        let broken = |from: &str, to: &str| {
            let text = good.replacen(from, to, 1);
            assert_ne!(text, good, "{from:?} not found");
            TaskSpec::from_toml(&text).expect_err("should be refused")
        };
        broken("time_limit_s = 600.0", "time_limit_s = 0.0");
        broken("detected = \"suspect\"", "");
        broken("delay_s = 3.0", "delay_s = -1.0");
        broken(
            "time_limit_s = 600.0",
            "time_limit_s = 600.0\ncolour = \"red\"",
        );
        let ghost =
            TaskSpec::from_toml(&good.replacen("\"suspect\"", "\"ghost\"", 1)).expect("parses");
        let city = Scenario::builtin("city").expect("city");
        assert!(ghost.validate(&city, 6).is_err());
    }
}

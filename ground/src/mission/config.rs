//! How a mission runs: the ablation mode, the small-model aids and the engine's bounds.

use super::aids::ModelAids;
use super::resume::MissionMemory;
use std::path::PathBuf;
use std::time::Duration;

/// The ablation modes of the paper.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// Coordinator + Supervisor, the Supervisor sees the Coordinator's reasoning.
    Tacos,
    /// The Supervisor does not get the Coordinator's reasoning.
    Wor,
    /// One model plans and executes; its history keeps executed actions only.
    Mnl,
}

impl Mode {
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Tacos => "tacos",
            Mode::Wor => "wor",
            Mode::Mnl => "mnl",
        }
    }
}

impl std::str::FromStr for Mode {
    type Err = String;
    fn from_str(s: &str) -> Result<Mode, String> {
        match s {
            "tacos" => Ok(Mode::Tacos),
            "wor" => Ok(Mode::Wor),
            "mnl" => Ok(Mode::Mnl),
            other => Err(format!("unknown mode {other:?} (tacos, wor, mnl)")),
        }
    }
}

#[derive(Debug, Clone)]
pub struct MissionConfig {
    pub mode: Mode,
    /// The small-model aids that are on (`mission::aids`).
    pub aids: ModelAids,
    /// How many times a rejected or unparsable reply goes back to its model.
    pub max_repairs: u32,
    /// A Supervisor cycle runs at the latest this long after the previous one while a plan runs.
    pub cycle_timeout: Duration,
    /// A plan is abandoned after this many Supervisor cycles.
    pub max_cycles_per_plan: u32,
    /// A plan is abandoned when one of its tasks has failed this many times: a goal that cannot
    /// be reached is reported to the pilot, not retried until the cycle limit.
    pub max_task_failures: u32,
    pub coordinator_max_tokens: u32,
    pub supervisor_max_tokens: u32,
    pub temperature: f32,
    pub seed: Option<u64>,
    /// Every Coordinator plan is held for the pilot's approval (`mission::approval`); the
    /// pilot turns it on and off with `confirm on` / `confirm off`.
    pub confirm: bool,
    /// A mission to go on with, read from its log after the ground station restarted.
    pub resume: Option<ResumeFrom>,
    /// Every step of the core is written to the mission log with its input and snapshot
    /// (`core::trace`), so `tacos-ground replay --check` can feed the mission to a fresh core.
    pub trace_steps: bool,
}

/// Where a resumed mission comes from and what it remembered (`mission::resume`).
#[derive(Debug, Clone)]
pub struct ResumeFrom {
    pub path: PathBuf,
    pub memory: MissionMemory,
}

impl Default for MissionConfig {
    fn default() -> Self {
        MissionConfig {
            mode: Mode::Tacos,
            aids: ModelAids::small(),
            max_repairs: 2,
            cycle_timeout: Duration::from_secs(10),
            max_cycles_per_plan: 30,
            max_task_failures: 3,
            coordinator_max_tokens: 600,
            supervisor_max_tokens: 400,
            temperature: 0.0,
            seed: Some(7),
            confirm: false,
            resume: None,
            trace_steps: false,
        }
    }
}

//! The evaluation harness: the paper's ablation (its section IV) as one command.
//!
//! A task file (`task`) says what the pilot asks, what is set up first, which failure is
//! injected and what success is. Each run (`run`) brings up its own simulated swarm, flies the
//! task with a model in one mode, and stops as soon as the outcome is decided; `criteria` judges
//! it from the simulator's truth and events and from the mission log. `results` keeps one JSON
//! line per finished run (the evaluation resumes from them) and computes the table; `chart`
//! draws it; `harness` runs every combination with a progress display.

pub mod chart;
pub mod criteria;
pub mod harness;
pub mod results;
pub mod run;
pub mod task;

pub use harness::{EvalOptions, EvalSummary, evaluate};
pub use task::TaskSpec;

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    Task(#[from] task::TaskError),
    #[error(transparent)]
    Results(#[from] results::ResultsError),
    #[error("writing {path}: {reason}")]
    Write { path: String, reason: String },
    #[error("a run stopped abnormally: {0}")]
    Run(String),
}

//! The language-model layers of the paper (its section III): the Coordinator turns the pilot's
//! words into a plan, the Supervisor runs that plan cycle by cycle on live telemetry, and the
//! swarm replans by itself when a drone is lost or joins. `mnl` collapses both into one model.
//!
//! The rules are a pure core (`core`: fed inputs with one snapshot of the swarm per step, it
//! hands back effects); the async driver (`driver`) takes the snapshots, runs the model calls
//! beside the mission, feeds their replies back and carries the effects out. Every call a model
//! proposes is resolved (`resolve`), checked at the safety gate, and only then sent; rejected
//! replies go back to their model with the reasons (`core::repair`). Direct commands
//! (`directives`) never wait for a model: `input` has `commands` carry them out beside the
//! driver; `undo` remembers the last instruction for `cancel` and `undo`.
//! Everything is written to the mission `log`.

pub mod addressed;
pub mod aids;
pub mod approval;
pub mod commands;
pub mod config;
pub(crate) mod core;
pub mod directives;
pub mod driver;
pub mod grounding;
pub mod handle;
pub mod input;
pub mod log;
pub mod replay;
pub mod report;
pub mod resolve;
pub mod resume;
pub mod undo;
pub mod untrusted;
pub mod whole_swarm;

pub use aids::{Aid, ModelAids};
pub use config::{MissionConfig, Mode, ResumeFrom};
pub use core::{coordinator_fixed_messages, supervisor_fixed_messages};
pub use driver::{Mission, coordinator_messages, supervisor_messages};
pub use handle::{MissionHandle, MissionTask};
pub use input::{InputClosed, MissionInputs, PilotInput};
pub use report::{EventTopic, MissionError, MissionStats, MissionUpdate, Overtaken};

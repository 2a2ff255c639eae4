//! The language-model side of TACOS as text and data: the prompt files in `prompts/text/`, the
//! JSON schemas of every model output in `prompts/schemas/`, the rendering of the swarm, the world,
//! the pending plan and the history into prompts, and the parsing of replies into typed calls.
//!
//! Nothing here talks to a network or decides anything; `tacos-ground` does.

pub mod offer;
pub mod partial;
pub mod render;
pub mod reply;
pub mod schema;
pub mod texts;

pub use reply::{ActionName, Call, CoordinatorReply, MonolithicReply, ReplyError, SupervisorReply};

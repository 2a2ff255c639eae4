//! `tacos-ground`: the ground station.
//!
//! It follows the swarm (`swarm`, `link`), checks every action before it leaves (`safety`),
//! and runs the simulated demo (`launch`, `demo`). The LLM layers and the terminal build on
//! these pieces.

pub mod cli;
pub mod demo;
pub mod direct;
pub mod eval;
pub mod jsonl;
pub mod launch;
pub mod link;
pub mod mission;
pub mod patterns;
pub mod pilot;
pub mod plot;
pub mod safety;
pub mod script;
pub mod send;
pub mod status_marks;
pub mod swarm;
pub mod table;
pub mod task_guard;
pub mod tui;

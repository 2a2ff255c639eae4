//! `tacos-onboard`: one drone's autonomy on its companion computer.
//!
//! A zenoh peer that takes actions from the ground and reports status; an action executor that
//! turns them into autopilot commands and a setpoint reference, sent over iceoryx2 to
//! `tacos-px4`; and the ground-silence failsafe.

pub mod executor;
pub mod failsafe;
pub mod ground_follow;
pub mod motion;
pub mod planner;
pub mod runtime;
pub mod stall;
pub mod tracker;

pub use runtime::{OnboardConfig, OnboardError, run};

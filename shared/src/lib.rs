//! TACOS vocabulary: what every process agrees on.
//!
//! This crate holds data and pure functions only: no I/O, no async, no clocks. The one wire codec
//! ([`codec`]), the one place that names zenoh keys and iceoryx2 services ([`keys`]), the
//! shared-memory payloads ([`ipc`]) and the scenario files ([`scenario`]) all live here so that a
//! change to any of them is made once.

pub mod action;
pub mod codec;
pub mod frames;
pub mod geometry;
pub mod ids;
pub mod ipc;
pub mod keys;
pub mod messages;
pub mod mode;
pub mod px4_mode;
pub mod scenario;
pub mod world;

pub use action::{Action, ActionCommand};
pub use geometry::Vec3;
pub use ids::{DroneId, IdError, SwarmId};
pub use mode::DroneMode;

//! `tacos-sitl`: a MAVLink-speaking stand-in for PX4 SITL, plus the world around the vehicles.
//!
//! Vehicle i behaves like PX4 SITL instance i: it binds UDP `127.0.0.1:(sitl_base + i)`, sends
//! MAVLink v2 as system i + 1 / component 1 to `127.0.0.1:(mavlink_base + i)` and answers
//! whoever last talked to it. It flies in its own NED frame with the origin at its home.
//! The world moves the scenario's targets (`world/targets`), plays the perception stand-in
//! (`world/events` detections), injects scripted and requested faults (`sim/faults`) and
//! publishes ground truth (`sim/truth`).
//!
//! Layers, innermost first: [`motion`] (bounded point mass), [`vehicle`] (PX4's modes and
//! rules), [`link`] (MAVLink ↔ vehicle), [`targets`], [`detection`], [`faults`], [`truth`],
//! [`sim`] (the world, no I/O), and [`runtime`] (sockets, zenoh, clock). Everything but
//! `runtime` is pure and unit-tested.

pub mod config;
pub mod detection;
pub mod error;
pub mod faults;
pub mod link;
pub mod motion;
pub mod runtime;
pub mod sim;
pub mod targets;
pub mod truth;
pub mod vehicle;

pub use config::SitlConfig;
pub use error::SitlError;
pub use runtime::run;

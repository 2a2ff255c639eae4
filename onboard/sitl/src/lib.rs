//! `tacos-sitl`: a MAVLink-speaking stand-in for PX4 SITL, plus the world around the vehicles.
//!
//! Vehicle i behaves like PX4 SITL instance i: it binds UDP `127.0.0.1:(sitl_base + i)`, sends
//! MAVLink v2 as system i + 1 / component 1 to `127.0.0.1:(mavlink_base + i)` until a client
//! talks to it, and from then on to that first client only, as PX4 does. It flies in its own
//! NED frame with the origin at its spawn point, reports altitudes above mean sea level (SIH's
//! origin, 489.4 m, by default), needs a few seconds after start before it can arm, and answers
//! commands with PX4's results, acks and STATUSTEXTs (see [`vehicle`] and [`link`]).
//! The world moves the scenario's targets (`world/targets`), plays the perception stand-in
//! (`world/events` detections), injects scripted and requested faults (`sim/faults`) and
//! publishes ground truth (`sim/truth`).
//!
//! Layers, innermost first: [`motion`] (bounded point mass), [`params`] and [`fence`] (PX4's
//! parameters and geofence), [`vehicle`] (PX4's modes and rules), [`geo`] (the world on the
//! Earth), [`streams`] (which messages go out how often, and the protocol replies),
//! [`telemetry`] (vehicle → MAVLink), [`link`] (MAVLink → vehicle), [`targets`], [`detection`],
//! [`faults`], [`truth`], [`sim`] (the world, no I/O), and [`runtime`] (sockets, zenoh, clock).
//! Everything but `runtime` is pure and unit-tested.

pub mod config;
pub mod detection;
pub mod error;
pub mod faults;
pub mod fence;
pub mod geo;
pub mod link;
pub mod motion;
pub mod observed;
pub mod params;
pub mod runtime;
pub mod sim;
pub mod streams;
pub mod targets;
pub mod telemetry;
pub mod truth;
pub mod vehicle;

pub use config::SitlConfig;
pub use error::SitlError;
pub use runtime::run;

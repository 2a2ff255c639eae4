//! `tacos-px4`: the MAVLink writer, one per drone.
//!
//! It is its own process so that PX4's offboard setpoint stream survives a crash or restart of
//! the planner (`tacos-onboard`): PX4 leaves offboard when setpoints stop for `COM_OF_LOSS_T`.
//! It takes setpoints and commands from iceoryx2 (world ENU), streams SET_POSITION_TARGET_LOCAL_NED
//! in the vehicle's NED frame, runs commands with acks, timeouts and retries, and publishes the
//! vehicle state back.
//!
//! Pure parts, each unit-tested: [`convert`] (ENU → NED), [`reference`] (what to stream, holds),
//! [`commands`] (the MAVLink command protocol), [`procedure`] (PX4's sequences around it:
//! readiness and mode before arming, AMSL take-off, mode switches confirmed), [`vehicle`] (link loss, state), [`mav`] (framing),
//! [`orphan`] (when a vehicle whose planner stays silent is landed).
//! The shell in [`writer`] wires them to a UDP socket and the iceoryx2 ports.

pub mod commands;
pub mod config;
pub mod convert;
pub mod fence;
pub mod mav;
pub mod orphan;
pub mod params;
pub mod procedure;
pub mod ratelimit;
pub mod reference;
pub mod setup;
pub mod transport;
pub mod vehicle;
pub mod writer;

pub use config::{ConfigError, MavlinkIds, MavlinkLink, WriterConfig, parse_home};
pub use writer::{RunSummary, run};

use std::net::SocketAddr;

#[derive(Debug, thiserror::Error)]
pub enum Px4Error {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(
        "cannot bind UDP {addr}: {source} (is another tacos-px4, MAVSDK or QGroundControl using this port?)"
    )]
    Bind {
        addr: SocketAddr,
        source: std::io::Error,
    },
    #[error("serial line {path}: {source}")]
    Serial {
        path: String,
        source: std::io::Error,
    },
    #[error("MAVLink link: {0}")]
    Socket(std::io::Error),
    #[error(transparent)]
    Ipc(#[from] tacos_ipc::IpcError),
    #[error("the MAVLink receive thread panicked")]
    ThreadPanicked,
}

//! The library's error type.

use tacos_bus::BusError;

#[derive(Debug, thiserror::Error)]
pub enum SitlError {
    #[error("{0}")]
    Config(String),
    #[error("cannot bind UDP {addr} for vehicle {drone} (port in use?): {error}")]
    Bind {
        drone: String,
        addr: std::net::SocketAddr,
        error: std::io::Error,
    },
    #[error(transparent)]
    Bus(#[from] BusError),
}

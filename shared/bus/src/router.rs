//! The swarm's zenoh router for a field deployment (`deploy/zenoh/router.json5`): zenoh's own
//! router, from the same zenoh library as every other TACOS process, run on its own host so the
//! ground station can restart without the swarm losing its network. Every process joins it as a
//! client over mutual TLS, and its access control decides, by certificate name, who may put and
//! hear what. Chosen over `zenohd` because that is a second, larger zenoh build (plugins, REST)
//! of which TACOS needs nothing.

pub mod refusals;

use crate::BusError;
use std::path::Path;
use zenoh::Session;

/// Reads a router's configuration; a file that is not for a router (`mode: "router"`) is refused,
/// since a peer or client opened from it would route nothing.
pub fn load(path: &Path) -> Result<zenoh::Config, BusError> {
    let config = zenoh::Config::from_file(path).map_err(|e| BusError::Config {
        key: path.display().to_string(),
        reason: e.to_string(),
    })?;
    let mode = config.get_json("mode").unwrap_or_default();
    if mode != "\"router\"" {
        return Err(BusError::Config {
            key: path.display().to_string(),
            reason: format!("mode is {mode}, not \"router\""),
        });
    }
    Ok(config)
}

/// Opens the router: listening on the file's endpoints until the session is dropped.
pub async fn open(config: zenoh::Config) -> Result<Session, BusError> {
    zenoh::open(config)
        .await
        .map_err(|e| BusError::Open(e.to_string()))
}

//! The per-drone operational mode of the paper: unavailable / idle / flying / tracking.

use serde::{Deserialize, Serialize};
use std::fmt;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum DroneMode {
    /// Not usable: no autopilot link, failed, or failsafe engaged.
    Unavailable,
    /// On the ground, ready to take off.
    Idle,
    /// Airborne, flying or holding.
    Flying,
    /// Airborne and following a target.
    Tracking,
}

impl DroneMode {
    pub fn as_str(self) -> &'static str {
        match self {
            DroneMode::Unavailable => "unavailable",
            DroneMode::Idle => "idle",
            DroneMode::Flying => "flying",
            DroneMode::Tracking => "tracking",
        }
    }

    pub fn is_airborne(self) -> bool {
        matches!(self, DroneMode::Flying | DroneMode::Tracking)
    }
}

impl fmt::Display for DroneMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

//! What the executor is given and gives back: its view of the vehicle, its configuration, and
//! what one tick asks the shell to send.

use crate::motion::Steering;
use tacos_shared::Vec3;
use tacos_shared::ipc::{CommandSample, VehicleStateSample};
use tacos_shared::px4_mode::Px4Mode;
use tacos_shared::scenario::FlightLimits;
use tacos_shared::world::World;

/// A position older than this means the autopilot's estimate is gone: the drone is unavailable
/// even while heartbeats still arrive (PX4 streams LOCAL_POSITION_NED at 30 Hz or more).
pub const POSITION_STALE_MS: u64 = 1_000;

/// What the executor knows of the vehicle, from `tacos-px4`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VehicleView {
    pub link_ok: bool,
    pub armed: bool,
    pub px4: Px4Mode,
    pub landed: bool,
    pub position: Vec3,
    pub velocity: Vec3,
}

impl From<&VehicleStateSample> for VehicleView {
    fn from(s: &VehicleStateSample) -> Self {
        VehicleView {
            link_ok: s.link_ok != 0 && s.position_age_ms <= POSITION_STALE_MS,
            armed: s.armed != 0,
            px4: s.mode(),
            landed: s.landed != 0,
            position: s.position(),
            velocity: s.velocity(),
        }
    }
}

/// What one tick asks the shell to send.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TickOutput {
    /// How to fly (world ENU), or `None` while the vehicle is unknown.
    pub steering: Option<Steering>,
    pub commands: Vec<CommandSample>,
}

#[derive(Debug, Clone)]
pub struct ExecutorConfig {
    pub limits: FlightLimits,
    pub world: World,
    /// A goto is done when the vehicle is this close to its goal (and slow).
    pub arrive_tolerance: f64,
    /// start_tracking is done once the vehicle is this close to its station.
    pub acquire_tolerance: f64,
    /// start_tracking fails if the target has not been seen this long after it started.
    pub unseen_timeout_s: f64,
    /// start_tracking fails if the station has not been reached this long after it started.
    pub acquire_timeout_s: f64,
}

impl ExecutorConfig {
    pub fn new(limits: FlightLimits, world: World) -> Self {
        let arrive_tolerance = (2.0 * limits.drone_radius).max(0.2);
        ExecutorConfig {
            limits,
            world,
            arrive_tolerance,
            acquire_tolerance: 2.5,
            unseen_timeout_s: 3.0,
            acquire_timeout_s: 120.0,
        }
    }
}

//! The one place that builds zenoh key expressions and iceoryx2 service names.
//!
//! Every zenoh key starts with `tacos/<swarm>/`; several swarms, or several test runs, share one
//! network without seeing each other as long as their swarm ids differ.

use crate::ids::{DroneId, SwarmId};

pub const ROOT: &str = "tacos";

/// Key builder for one swarm.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Keys {
    prefix: String,
}

impl Keys {
    pub fn new(swarm: &SwarmId) -> Self {
        Keys {
            prefix: format!("{ROOT}/{swarm}"),
        }
    }

    /// `tacos/<swarm>`: what every key of this swarm starts with.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    fn drone_key(&self, drone: &DroneId, leaf: &str) -> String {
        format!("{}/drone/{drone}/{leaf}", self.prefix)
    }

    /// ground → drone: `ActionCommand`.
    pub fn action(&self, drone: &DroneId) -> String {
        self.drone_key(drone, "action")
    }

    /// drone → ground: `DroneStatus`.
    pub fn status(&self, drone: &DroneId) -> String {
        self.drone_key(drone, "status")
    }

    /// drone → neighbours: `PathMessage`.
    pub fn path(&self, drone: &DroneId) -> String {
        self.drone_key(drone, "path")
    }

    /// The drone's liveliness token.
    pub fn alive(&self, drone: &DroneId) -> String {
        self.drone_key(drone, "alive")
    }

    pub fn all_actions(&self) -> String {
        format!("{}/drone/*/action", self.prefix)
    }

    pub fn all_status(&self) -> String {
        format!("{}/drone/*/status", self.prefix)
    }

    pub fn all_paths(&self) -> String {
        format!("{}/drone/*/path", self.prefix)
    }

    pub fn all_alive(&self) -> String {
        format!("{}/drone/*/alive", self.prefix)
    }

    /// perception (or sitl) → all: `TargetsMessage`.
    pub fn targets(&self) -> String {
        format!("{}/world/targets", self.prefix)
    }

    /// perception (or sitl) → ground: `WorldEvent`.
    pub fn events(&self) -> String {
        format!("{}/world/events", self.prefix)
    }

    /// anyone → sitl: `FaultRequest` (run-time fault injection in simulation).
    pub fn sim_faults(&self) -> String {
        format!("{}/sim/faults", self.prefix)
    }

    /// ground → drones: `GroundHeartbeat`, a few times a second; its silence drives the failsafe.
    pub fn ground_heartbeat(&self) -> String {
        format!("{}/ground/heartbeat", self.prefix)
    }

    /// sitl → tests, demo checks, evaluation: `SimTruth`.
    pub fn sim_truth(&self) -> String {
        format!("{}/sim/truth", self.prefix)
    }

    /// sitl → every process of a simulated run: `SimClock`, the simulator's time and rate.
    pub fn sim_clock(&self) -> String {
        format!("{}/sim/clock", self.prefix)
    }

    /// ground → sitl: `SimPace`, whether a model call is in flight (the simulation then runs at
    /// real time).
    pub fn sim_pace(&self) -> String {
        format!("{}/sim/pace", self.prefix)
    }

    /// The drone a `drone/<id>/...` key belongs to, if it is one of this swarm's.
    pub fn drone_of(&self, key: &str) -> Option<DroneId> {
        let rest = key.strip_prefix(&self.prefix)?.strip_prefix("/drone/")?;
        let (id, _leaf) = rest.split_once('/')?;
        DroneId::new(id).ok()
    }
}

/// The iceoryx2 channels between `tacos-onboard` and `tacos-px4` on one companion computer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IpcChannel {
    /// onboard → px4: `ipc::SetpointSample`.
    Setpoint,
    /// onboard → px4: event that wakes the writer when a setpoint or command was published.
    Wakeup,
    /// onboard → px4: `ipc::CommandSample`.
    Command,
    /// px4 → onboard: `ipc::CommandResultSample`.
    CommandResult,
    /// px4 → onboard: `ipc::VehicleStateSample`.
    VehicleState,
}

impl IpcChannel {
    fn leaf(self) -> &'static str {
        match self {
            IpcChannel::Setpoint => "setpoint",
            IpcChannel::Wakeup => "wakeup",
            IpcChannel::Command => "command",
            IpcChannel::CommandResult => "command_result",
            IpcChannel::VehicleState => "vehicle_state",
        }
    }
}

/// The iceoryx2 service name of one channel of one drone.
pub fn ipc_service(swarm: &SwarmId, drone: &DroneId, channel: IpcChannel) -> String {
    format!("{ROOT}/{swarm}/{drone}/{}", channel.leaf())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_have_the_documented_shape() {
        let keys = Keys::new(&SwarmId::new("demo").expect("valid"));
        let alfa = DroneId::new("alfa").expect("valid");
        assert_eq!(keys.action(&alfa), "tacos/demo/drone/alfa/action");
        assert_eq!(keys.status(&alfa), "tacos/demo/drone/alfa/status");
        assert_eq!(keys.alive(&alfa), "tacos/demo/drone/alfa/alive");
        assert_eq!(keys.targets(), "tacos/demo/world/targets");
        assert_eq!(
            keys.drone_of("tacos/demo/drone/alfa/status"),
            Some(alfa.clone())
        );
        assert_eq!(keys.drone_of("tacos/other/drone/alfa/status"), None);
        assert_eq!(keys.drone_of("tacos/demo/world/targets"), None);
        assert_eq!(
            ipc_service(
                &SwarmId::new("demo").expect("valid"),
                &alfa,
                IpcChannel::Setpoint
            ),
            "tacos/demo/alfa/setpoint"
        );
    }
}

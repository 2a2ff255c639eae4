//! Messages that travel over zenoh (see `keys` for where). All are encoded with [`crate::codec`].

use crate::action::{Action, ActionCommand};
use crate::geometry::Vec3;
use crate::ids::DroneId;
use crate::mode::DroneMode;
use serde::{Deserialize, Serialize};
use std::fmt;

/// Why an action failed, as the drone reports it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum FailureReason {
    /// The drone's mode does not allow the action (e.g. goto before take-off).
    InvalidForMode(String),
    /// The autopilot refused a command (with PX4's result).
    Rejected(String),
    /// The goal cannot be reached (outside the workspace, inside an obstacle, no progress).
    Unreachable(String),
    /// The action did not finish in its allotted time.
    TimedOut,
    /// A newer action replaced this one before it finished.
    Preempted,
    /// The MAVLink link to the autopilot is gone.
    AutopilotLinkLost,
    /// A tracked target was not observed for longer than the coast time.
    TargetLost(String),
    /// The failsafe took over (ground silent).
    Failsafe(String),
}

impl fmt::Display for FailureReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FailureReason::InvalidForMode(why) => write!(f, "not allowed now: {why}"),
            FailureReason::Rejected(why) => write!(f, "rejected by the autopilot: {why}"),
            FailureReason::Unreachable(why) => write!(f, "unreachable: {why}"),
            FailureReason::TimedOut => f.write_str("timed out"),
            FailureReason::Preempted => f.write_str("preempted by a newer action"),
            FailureReason::AutopilotLinkLost => f.write_str("autopilot link lost"),
            FailureReason::TargetLost(name) => write!(f, "target {name} lost"),
            FailureReason::Failsafe(why) => write!(f, "failsafe: {why}"),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum ActionState {
    /// Under way; `progress` in [0, 1] where it can be measured.
    Running {
        progress: f32,
    },
    Done,
    Failed(FailureReason),
}

impl ActionState {
    pub fn is_finished(&self) -> bool {
        !matches!(self, ActionState::Running { .. })
    }
}

/// The action a drone is on (or last finished) and how it is going.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionProgress {
    pub seq: u64,
    pub task_id: Option<String>,
    pub action: Action,
    pub state: ActionState,
}

impl ActionProgress {
    pub fn started(command: &ActionCommand) -> Self {
        ActionProgress {
            seq: command.seq,
            task_id: command.task_id.clone(),
            action: command.action.clone(),
            state: ActionState::Running { progress: 0.0 },
        }
    }
}

/// The drone's failsafe stage, when one is engaged.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum FailsafeStage {
    /// Ground silent for the hold time: holding position.
    Holding,
    /// Ground silent for the land time: landing.
    Landing,
}

/// What a drone publishes on `drone/<id>/status`, at 10 Hz or more.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DroneStatus {
    pub drone: DroneId,
    /// Counts up by one per message from this drone process (detects drops and restarts).
    pub counter: u64,
    pub mode: DroneMode,
    pub armed: bool,
    /// World frame (ENU), metres.
    pub position: Vec3,
    /// World frame (ENU), m/s.
    pub velocity: Vec3,
    /// True while MAVLink heartbeats from the autopilot arrive.
    pub autopilot_link: bool,
    /// The current (or last finished) action.
    pub action: Option<ActionProgress>,
    pub failsafe: Option<FailsafeStage>,
    /// Airborne and hearing none of the neighbours it knows: holding where it is, taking only
    /// land and hold until one is heard (the onboard's peer-silence hold).
    pub peers_silent: bool,
    /// Actions that arrived malformed on this drone's key since it started.
    pub malformed_actions: u64,
    /// The ground station this drone follows (its epoch), once one is heard: a drone takes
    /// actions from one ground station at a time (see `GroundHeartbeat::ground`).
    pub ground: Option<u64>,
    /// The latest action of the followed ground station that this drone refused on arrival
    /// (it came too late): the ground's wait for that action ends with the reason.
    pub refused: Option<ActionRefused>,
    /// PX4 flies the drone in this mode, not TACOS: it left offboard control in flight without
    /// TACOS asking (its own failsafe, a geofence, an RC pilot or another ground station
    /// switched it). The drone is out of missions until PX4 is back in offboard or the drone
    /// is on the ground; a hold or land sent to it takes it back into offboard. (Absent from
    /// mission traces written before it: read as none.)
    #[serde(default)]
    pub autopilot_took_over: Option<crate::px4_mode::Px4Mode>,
}

impl DroneStatus {
    /// TACOS flies the drone, not PX4 on its own (see `autopilot_took_over`): only then can a
    /// mission count on it.
    pub fn flown_by_tacos(&self) -> bool {
        self.autopilot_took_over.is_none()
    }
}

/// An action of the followed ground station refused on arrival, and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionRefused {
    pub seq: u64,
    pub why: RefusedBecause,
}

/// Why a drone refused an action of the ground station it follows.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum RefusedBecause {
    /// It arrived `late_s` seconds later than the ground's heartbeats take, more than the
    /// drone's bound: the network held it (a link that stalled, then delivered), and what it
    /// asked for may no longer be what the ground wants.
    Late { late_s: f64, bound_s: f64 },
}

impl std::fmt::Display for RefusedBecause {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RefusedBecause::Late { late_s, bound_s } => write!(
                f,
                "it arrived {late_s:.1} s later than this ground station's heartbeats take \
                 (bound {bound_s:.1} s): the network held it; send it again if it is still wanted"
            ),
        }
    }
}

/// One observed target (perception, or the simulator standing in for it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TargetObservation {
    pub name: String,
    pub position: Vec3,
    pub velocity: Vec3,
}

/// Published on `world/targets`: every currently observed target, stamped in seconds of the
/// publisher's clock.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TargetsMessage {
    pub stamp: f64,
    pub targets: Vec<TargetObservation>,
}

/// Published on `world/events`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum WorldEvent {
    /// A hidden target was seen by a drone ("suspect seen at car_7").
    Detection {
        drone: DroneId,
        target: String,
        /// The landmark the target was found at, when it hides at one.
        landmark: Option<String>,
        position: Vec3,
    },
    /// The simulator injected a fault (reported so tests and logs can see it).
    FaultInjected { drone: DroneId, fault: String },
}

impl fmt::Display for WorldEvent {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            WorldEvent::Detection {
                drone,
                target,
                landmark: Some(at),
                ..
            } => {
                write!(f, "{target} seen at {at} by {drone}")
            }
            WorldEvent::Detection {
                drone,
                target,
                landmark: None,
                position,
            } => write!(
                f,
                "{target} seen by {drone} at ({:.1}, {:.1}, {:.1})",
                position.x, position.y, position.z
            ),
            WorldEvent::FaultInjected { drone, fault } => {
                write!(f, "fault injected on {drone}: {fault}")
            }
        }
    }
}

/// A drone's predicted trajectory for the planner (`drone/<id>/path`): K+1 states spaced `dt`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PathMessage {
    pub drone: DroneId,
    /// Publisher's wall clock, seconds since the Unix epoch (for the age of the path).
    pub stamp: f64,
    pub dt: f64,
    pub positions: Vec<Vec3>,
    /// The target this drone is tracking, so trackers of one target spread around it.
    pub tracking: Option<String>,
    /// True while the publisher's planner flies it, so it keeps its own half of every
    /// separation. False while the autopilot flies it (take-off, landing) or it stands on the
    /// ground: it cannot give way, and neighbours keep the whole distance from it.
    pub avoids: bool,
    /// The vehicle is armed and off the ground. A neighbour whose paths stop (its onboard
    /// crashed, the network lost it) stays an obstacle for as long as its last path said this;
    /// one last seen on the ground is forgotten after a while.
    pub airborne: bool,
}

/// A run-time fault injection request to the simulator (`sim/faults`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FaultRequest {
    pub drone: DroneId,
    pub fault: crate::scenario::FaultKind,
}

/// One simulated vehicle as the simulator knows it (ground truth, world frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VehicleTruth {
    pub drone: DroneId,
    pub position: Vec3,
    pub velocity: Vec3,
    pub armed: bool,
    /// PX4 custom mode (see `px4_mode`).
    pub custom_mode: u32,
    /// False once the vehicle has died (fault injection).
    pub alive: bool,
    /// True while its MAVLink link is dropped (fault injection).
    pub link_down: bool,
    pub landed: bool,
}

/// Published by the simulator on `sim/truth` at 10 Hz: what really happened, for tests, the demo's
/// checks and the evaluation harness. Nothing in the flight path reads it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimTruth {
    /// Seconds since the simulation started.
    pub sim_time: f64,
    pub vehicles: Vec<VehicleTruth>,
    /// Smallest centre-to-centre distance seen between two airborne vehicles since the start
    /// (infinity while fewer than two have flown).
    pub min_pair_distance: f64,
    /// Smallest clearance to an obstacle surface seen for an airborne vehicle since the start.
    pub min_obstacle_clearance: f64,
    /// Count of ticks on which two airborne vehicles were closer than the safety distance.
    pub separation_breaches: u64,
    /// Count of ticks on which a vehicle was inside an obstacle inflated by the drone radius, or
    /// flew into the ground under power (a touchdown faster than a landing).
    pub obstacle_breaches: u64,
}

/// Published by the simulator on `sim/clock` at 20 Hz and whenever its rate changes: the
/// simulated time as an anchor that every process of a simulated run extrapolates from, so
/// that timers, deadlines and stamps follow the simulation when it runs faster than real time.
/// The processes share a machine (loopback), so they share the wall clock the anchor names.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SimClock {
    /// Simulated time on the Unix scale (seconds): the wall clock when the simulator started,
    /// plus the simulated seconds since.
    pub sim_unix_s: f64,
    /// The wall clock (seconds since the Unix epoch) at which the simulation was at `sim_unix_s`.
    pub wall_unix_s: f64,
    /// Simulated seconds per wall second from then on.
    pub rate: f64,
}

/// Sent by the ground on `sim/pace` when a model call starts or ends, and once a second: while
/// a call is in flight the simulation runs at real time, so the models meet the same world they
/// would in a real flight; between calls it may run at the simulator's `--speed`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SimPace {
    pub model_call_in_flight: bool,
}

/// Sent by every ground station process on `ground/heartbeat` several times a second. A drone
/// that hears none for its configured time holds, then lands.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroundHeartbeat {
    pub counter: u64,
    /// Which ground station beats: its epoch, chosen when it starts and carried by its actions
    /// too (`ActionCommand::ground`). A drone follows one at a time.
    pub ground: u64,
    /// The ground station's clock when it beat (seconds, as `ActionCommand::sent_at`).
    pub stamp: f64,
}

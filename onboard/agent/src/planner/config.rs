//! The planner's configuration: horizon, limits, margins and weights, from a scenario's flight
//! limits and world, checked before a planner is built.

use super::PlannerError;
use super::qp::CostWeights;
use tacos_shared::Vec3;
use tacos_shared::scenario::FlightLimits;
use tacos_shared::world::{Bounds, Ellipsoid, World};

/// See [`PlannerConfig::screen_distance`]; measured with the planner bench (see the README).
const SCREEN_DISTANCE: f64 = 0.3;

#[derive(Debug, Clone, PartialEq)]
pub struct PlannerConfig {
    pub horizon_steps: usize,
    /// Seconds per step.
    pub dt: f64,
    pub max_speed: f64,
    /// Vertical speed limits (m/s, both positive): the autopilot's, which are tighter than
    /// `max_speed` in most maps (PX4 climbs at 3 m/s and descends at 1.5 m/s at most).
    pub max_climb_rate: f64,
    pub max_descent_rate: f64,
    pub max_accel: f64,
    pub workspace: Bounds,
    /// The obstacles as they are (not inflated).
    pub obstacles: Vec<Ellipsoid>,
    pub drone_radius: f64,
    /// Kept between the inflated obstacles and the drone's centre on top of the radius: covers
    /// the looseness of `Ellipsoid::inflated` and `clearance_lower_bound`, and solver tolerance.
    pub obstacle_margin: f64,
    /// Minimum centre-to-centre distance between two drones (in the downwash-scaled metric,
    /// which is never more than the Euclidean one).
    pub safety_distance: f64,
    /// Added to each drone's half of the safety distance.
    pub separation_margin: f64,
    /// Required vertical separation / required horizontal separation (≥ 1).
    pub downwash_factor: f64,
    /// Neighbours closer than this are planned against (see [`neighbours_in_range`]).
    pub neighbour_range: f64,
    /// Extra margin per second of a neighbour path's age, metres per second...
    pub stale_margin_rate: f64,
    /// ...up to this many metres: a neighbour silent for good (its onboard died while its
    /// writer holds it in the air) stays an obstacle of bounded size instead of growing over
    /// the whole map.
    pub max_stale_margin: f64,
    /// L1 penalty per metre of violated obstacle or neighbour constraint, per segment. The
    /// workspace's walls and ceiling share one slack over the whole horizon, so they cost
    /// `horizon_steps` times this; the floor costs `floor_weight_factor` times that again.
    pub slack_weight: f64,
    /// How many times the walls' price a metre into the floor costs. A crowd presses on a
    /// drone from many sides at once; with the floor priced like one neighbour, the drones at
    /// the bottom of a 20-drone swap were pushed into the ground.
    pub floor_weight_factor: f64,
    /// Height above the workspace floor that a drone's centre is kept at, unless its goal or
    /// the drone itself is lower (a low goal is flown to on purpose).
    pub floor_clearance: f64,
    /// Rotation (radians, counter-clockwise about z) of separating half-spaces: both drones of a
    /// head-on pair veer to their right.
    pub right_hand_angle: f64,
    /// Clearance beyond the inflated obstacle that detour waypoints aim for.
    pub detour_margin: f64,
    /// A half-space goes into the first QP of a solve only when the previous plan comes this
    /// close to it (metres); the rest are checked on the solution (see `screen`). Zero keeps
    /// only the ones the previous plan already touches; the answer is the same at any value.
    pub screen_distance: f64,
    pub weights: CostWeights,
}

impl PlannerConfig {
    /// The default tuning for a scenario's limits and world.
    pub fn from_scenario(limits: &FlightLimits, world: &World) -> Self {
        let horizon_steps = 20;
        let dt = 0.1;
        let horizon = horizon_steps as f64 * dt;
        PlannerConfig {
            horizon_steps,
            dt,
            max_speed: limits.max_speed,
            max_climb_rate: limits.max_climb_rate,
            max_descent_rate: limits.max_descent_rate,
            max_accel: limits.max_accel,
            workspace: world.bounds,
            obstacles: world.obstacles.clone(),
            drone_radius: limits.drone_radius,
            obstacle_margin: 0.3,
            safety_distance: limits.safety_distance,
            // Covers how far the vehicle strays from its plan between solves (the autopilot's
            // tracking error), for each of the two drones. It scales with the vehicle: a sixth
            // of the safety distance, 0.5 m in the city. A fixed 0.5 m asked the lab's drones
            // (0.6 m safety distance) for 1.6 m between them; they stand 1 m apart, so they
            // pushed each other about for as long as they flew.
            separation_margin: limits.safety_distance / 6.0,
            downwash_factor: tacos_shared::scenario::DOWNWASH_FACTOR,
            // Two drones closing at full speed over one horizon, plus the safety distance,
            // plus room for stale paths.
            neighbour_range: 2.0 * limits.max_speed * horizon + 2.0 * limits.safety_distance,
            stale_margin_rate: 1.0,
            max_stale_margin: limits.safety_distance,
            slack_weight: 2e4,
            floor_weight_factor: 10.0,
            // The ground is kept a safety distance away, like another drone.
            floor_clearance: limits.safety_distance,
            right_hand_angle: 0.25,
            detour_margin: 2.0,
            screen_distance: SCREEN_DISTANCE,
            weights: CostWeights {
                position: 1.0,
                terminal_position: 10.0,
                velocity: 0.1,
                terminal_velocity: 1.0,
                acceleration: 0.05,
                jerk: 0.5,
            },
        }
    }

    pub(super) fn validate(&self) -> Result<(), PlannerError> {
        let positive = [
            ("dt", self.dt),
            ("max_speed", self.max_speed),
            ("max_climb_rate", self.max_climb_rate),
            ("max_descent_rate", self.max_descent_rate),
            ("max_accel", self.max_accel),
            ("slack_weight", self.slack_weight),
            ("floor_weight_factor", self.floor_weight_factor),
            ("downwash_factor", self.downwash_factor),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(PlannerError::InvalidConfig(format!(
                    "{name} must be finite and positive"
                )));
            }
        }
        let non_negative = [
            ("drone_radius", self.drone_radius),
            ("obstacle_margin", self.obstacle_margin),
            ("safety_distance", self.safety_distance),
            ("separation_margin", self.separation_margin),
            ("neighbour_range", self.neighbour_range),
            ("stale_margin_rate", self.stale_margin_rate),
            ("max_stale_margin", self.max_stale_margin),
            ("detour_margin", self.detour_margin),
            ("screen_distance", self.screen_distance),
            ("floor_clearance", self.floor_clearance),
            ("weights.position", self.weights.position),
            ("weights.terminal_position", self.weights.terminal_position),
            ("weights.velocity", self.weights.velocity),
            ("weights.terminal_velocity", self.weights.terminal_velocity),
            ("weights.acceleration", self.weights.acceleration),
            ("weights.jerk", self.weights.jerk),
        ];
        for (name, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return Err(PlannerError::InvalidConfig(format!(
                    "{name} must be finite and not negative"
                )));
            }
        }
        if !self.right_hand_angle.is_finite() {
            return Err(PlannerError::InvalidConfig(
                "right_hand_angle must be finite".into(),
            ));
        }
        if self.horizon_steps == 0 || self.horizon_steps > 1000 {
            return Err(PlannerError::InvalidConfig(
                "horizon_steps must be between 1 and 1000".into(),
            ));
        }
        let r = self.drone_radius;
        if !(0..3).all(|i| self.workspace.min[i] + r < self.workspace.max[i] - r) {
            return Err(PlannerError::InvalidConfig(
                "the workspace shrunk by the drone radius is empty".into(),
            ));
        }
        Ok(())
    }

    pub fn horizon(&self) -> f64 {
        self.horizon_steps as f64 * self.dt
    }

    /// How far apart two plans that obey one separating plane are: the safety distance plus
    /// each drone's margin. A finished plan is rechecked against it (`recheck::may_replace`).
    pub fn planes_distance(&self) -> f64 {
        self.safety_distance + 2.0 * self.separation_margin
    }

    /// The workspace every control point must stay in: the bounds shrunk by the drone radius.
    pub fn shrunk_workspace(&self) -> Bounds {
        let r = Vec3::repeat(self.drone_radius);
        Bounds {
            min: self.workspace.min + r,
            max: self.workspace.max - r,
        }
    }

    /// The obstacles as the planner keeps them out: inflated by radius + margin.
    pub fn keep_out(&self) -> Vec<Ellipsoid> {
        self.obstacles
            .iter()
            .map(|o| o.inflated(self.drone_radius + self.obstacle_margin))
            .collect()
    }
}

//! The distributed collision-free planner: each drone solves its own small QP (clarabel) at
//! 20 Hz or more. Pure: no I/O, no clocks, no threads; the caller passes the time.
//!
//! - Model: double integrator, state (p, v), piecewise-constant acceleration over
//!   `horizon_steps` steps of `dt` (default 20 × 0.1 s = 2 s).
//! - Cost: track the goal's position (and its velocity, for moving goals) with a heavier last
//!   step, penalise acceleration and jerk (change of acceleration between steps, including from
//!   the previous plan's acceleration now).
//! - Limits: speed and acceleration as exact second-order cones (`‖v_k‖ ≤ v̄`, `‖a_k‖ ≤ ā`;
//!   no polyhedral approximation is needed, clarabel takes the cones natively), the vertical
//!   speed within the autopilot's climb and descent rates (`−v̄_dn ≤ v_z ≤ v̄_up`), the workspace
//!   box shrunk by the drone radius on every control point, its floor raised by
//!   `floor_clearance` (unless the goal or the drone is lower) and priced far above any other
//!   constraint, so that a crowd cannot press a drone into the ground.
//! - Obstacles: each ellipsoid inflated by the drone radius (plus `obstacle_margin`) is kept out
//!   by, per segment, its tangent half-space at the point where the ray from its centre through
//!   the previous plan (or the current position, on the first solve) meets its surface. All
//!   Bézier control points of the segment must lie in it, so the whole curve does.
//! - Neighbours: per segment, a separating half-space between my previous plan and the
//!   neighbour's published path (time-aligned by its age, held at its end) in a downwash-scaled
//!   metric (vertical distances count `1 / downwash_factor`), each side keeping half the safety
//!   distance plus margins (one of them growing with the path's age), rotated by
//!   `right_hand_angle` so head-on pairs both veer right.
//! - Every obstacle and neighbour constraint group has its own slack with a heavy L1 penalty, so
//!   the QP stays feasible; if the solver still fails, the result is a braking plan.
//! - A detour waypoint (see `route`) steers the reference around the first obstacle blocking the
//!   straight line to the goal, to avoid the local minimum in front of it.
//!
//! Constraints that cannot be active are dropped before solving (see `reachable`). Neighbour
//! sets are range-based (so symmetric): see [`neighbours_in_range`].

mod config;
pub mod constraints;
pub mod plan;
pub mod qp;
mod reachable;
pub mod recheck;
mod route;
mod screen;

#[cfg(test)]
mod tests;

pub use config::PlannerConfig;
pub use constraints::{Downwash, HalfSpace, path_point, separating_half_space, tangent_half_space};
pub use plan::{Plan, ReferenceState};
pub use qp::{ConstraintKind, CostWeights, QpError, SegmentConstraint};

use qp::{QpInput, QpWorkspace};
use reachable::Reachable;
use screen::Screen;
use tacos_shared::geometry::is_finite;
use tacos_shared::messages::PathMessage;
use tacos_shared::world::Ellipsoid;
use tacos_shared::{DroneId, Vec3};

/// A neighbour's path older than this no longer shows it giving way (see `PathMessage::avoids`).
const STILL_AVOIDS_S: f64 = 1.0;

/// Where to go. `velocity` is the goal's own velocity (zero for a fixed point); the planner
/// predicts a moving goal at constant velocity over the horizon.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Goal {
    pub position: Vec3,
    pub velocity: Vec3,
}

impl Goal {
    pub fn fixed(position: Vec3) -> Goal {
        Goal {
            position,
            velocity: Vec3::zeros(),
        }
    }
}

/// Another drone's predicted path: positions `dt` apart starting at its stamp, which was
/// `age_s` seconds ago. (`dt` travels with the path, as in `PathMessage`.)
#[derive(Debug, Clone, PartialEq)]
pub struct NeighbourPath {
    pub id: DroneId,
    pub positions: Vec<Vec3>,
    pub dt: f64,
    pub age_s: f64,
    /// The neighbour plans around me too (see `PathMessage::avoids`); when false, I keep the
    /// whole safety distance from it instead of half.
    pub avoids: bool,
}

impl NeighbourPath {
    /// From a received message; `now` is the receiver's wall clock (seconds since the Unix
    /// epoch, like the stamp). Negative ages (clock skew) count as zero.
    pub fn from_message(message: &PathMessage, now: f64) -> NeighbourPath {
        NeighbourPath {
            id: message.drone.clone(),
            positions: message.positions.clone(),
            dt: message.dt,
            age_s: (now - message.stamp).max(0.0),
            avoids: message.avoids,
        }
    }

    /// True when the path can be used: points, finite values, a positive step.
    pub fn is_valid(&self) -> bool {
        !self.positions.is_empty()
            && self.positions.iter().all(is_finite)
            && self.dt.is_finite()
            && self.dt > 0.0
            && self.age_s.is_finite()
    }

    /// Where the neighbour is predicted `t` seconds from now (its age accounted for).
    pub fn position_at(&self, t: f64) -> Option<Vec3> {
        path_point(&self.positions, self.dt, self.age_s.max(0.0) + t)
    }
}

/// The neighbours whose predicted position now is within `range` of `me`. Range-based, so the
/// relation is symmetric: if I see you, you see me (up to the paths' ages). Invalid paths are
/// left out (see [`NeighbourPath::is_valid`]).
pub fn neighbours_in_range(
    me: Vec3,
    others: impl Iterator<Item = NeighbourPath>,
    range: f64,
) -> Vec<NeighbourPath> {
    others
        .filter(|n| n.is_valid())
        .filter(|n| n.position_at(0.0).is_some_and(|p| (p - me).norm() <= range))
        .collect()
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlannerError {
    #[error("planner configuration: {0}")]
    InvalidConfig(String),
    #[error("the drone's position or velocity is not finite")]
    NonFiniteState,
}

/// Why the planner fell back to braking.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BrakeReason {
    #[error("goal is not finite")]
    BadGoal,
    #[error(transparent)]
    Solver(#[from] QpError),
    #[error("the solved plan is not finite")]
    NonFinitePlan,
}

#[derive(Debug, Clone, PartialEq)]
pub enum PlanStatus {
    /// Every constraint holds (slacks below a millimetre).
    Solved,
    /// Solved, but some obstacle, neighbour or workspace constraint is violated by up to
    /// `max_slack` metres (an infeasible start, or a neighbour that did not keep its side).
    Relaxed { max_slack: f64 },
    /// The solver failed: the plan brakes at max acceleration along the current velocity,
    /// then holds.
    Braking(BrakeReason),
}

#[derive(Debug, Clone, PartialEq)]
pub struct PlanResult {
    pub plan: Plan,
    pub status: PlanStatus,
    /// Interior-point iterations over every QP of the solve (0 when braking).
    pub iterations: u32,
    /// QPs solved: 1, or more when a half-space left out by the screen was violated.
    pub qp_solves: u32,
    /// Half-spaces the last QP held (of `Planner::last_constraints`).
    pub qp_constraints: usize,
    /// Neighbour paths left out as invalid.
    pub ignored_neighbours: usize,
}

/// Slack (metres) below which a constraint counts as satisfied.
const SLACK_TOLERANCE: f64 = 1e-3;
/// The previous plan is used to linearise around only while the drone is this close to it.
const PREVIOUS_PLAN_DRIFT: f64 = 2.0;

/// One drone's planner. Keeps the previous plan (to linearise around) and its buffers.
#[derive(Debug)]
pub struct Planner {
    cfg: PlannerConfig,
    keep_out: Vec<Ellipsoid>,
    detour_zone: Vec<Ellipsoid>,
    metric: Downwash,
    previous: Option<Plan>,
    constraints: Vec<SegmentConstraint>,
    /// The half-spaces the QP holds (see `screen`).
    screen: Screen,
    in_qp: Vec<SegmentConstraint>,
    detour_sides: Vec<i8>,
    reference: Vec<Vec3>,
    qp: QpWorkspace,
    /// This drone's margin for straying from its plan: the configured one unless
    /// [`Planner::set_separation_margin`] widened it.
    separation_margin: f64,
}

impl Planner {
    pub fn new(cfg: PlannerConfig) -> Result<Planner, PlannerError> {
        cfg.validate()?;
        let keep_out = cfg.keep_out();
        let detour_zone = cfg
            .obstacles
            .iter()
            .map(|o| o.inflated(cfg.drone_radius + cfg.obstacle_margin + cfg.detour_margin))
            .collect();
        Ok(Planner {
            metric: Downwash::new(cfg.downwash_factor),
            detour_sides: vec![0; cfg.obstacles.len()],
            keep_out,
            detour_zone,
            previous: None,
            constraints: Vec::new(),
            screen: Screen::default(),
            in_qp: Vec::new(),
            reference: Vec::new(),
            qp: QpWorkspace::default(),
            separation_margin: cfg.separation_margin,
            cfg,
        })
    }

    pub fn config(&self) -> &PlannerConfig {
        &self.cfg
    }

    /// The last plan returned (solved or braking).
    pub fn previous(&self) -> Option<&Plan> {
        self.previous.as_ref()
    }

    /// Takes back `plan` as the previous plan, after the one just solved was not flown (see
    /// [`recheck`]): the next solve linearises around what the drone flies and its neighbours
    /// read.
    pub fn restore_previous(&mut self, plan: Option<Plan>) {
        self.previous = plan;
    }

    /// The margin kept for straying from the plan in the next solves: `margin`, never less than
    /// the configured one (a non-finite value keeps the configured one). Returns the one kept.
    pub fn set_separation_margin(&mut self, margin: f64) -> f64 {
        self.separation_margin = if margin.is_finite() {
            margin.max(self.cfg.separation_margin)
        } else {
            self.cfg.separation_margin
        };
        self.separation_margin
    }

    /// Forgets the previous plan (the next solve linearises around the current position).
    pub fn reset(&mut self) {
        self.previous = None;
        self.detour_sides.iter_mut().for_each(|s| *s = 0);
    }

    /// QPs solved by updating the last solver's data rather than setting one up (a problem of
    /// the same shape), since the planner was made.
    pub fn solver_reuses(&self) -> u64 {
        self.qp.reuses()
    }

    /// The half-spaces of the last solve (after dropping the redundant ones), for checks.
    pub fn last_constraints(&self) -> &[SegmentConstraint] {
        &self.constraints
    }

    /// Plans from the drone's state at time `now` (seconds, any clock shared with the plans'
    /// `start`) towards `goal`, apart from `neighbours` (already range-filtered, see
    /// [`neighbours_in_range`]). Only a non-finite state is an error; everything else yields a
    /// plan (solved, relaxed or braking).
    pub fn plan(
        &mut self,
        now: f64,
        position: Vec3,
        velocity: Vec3,
        goal: &Goal,
        neighbours: &[NeighbourPath],
    ) -> Result<PlanResult, PlannerError> {
        if !(now.is_finite() && is_finite(&position) && is_finite(&velocity)) {
            return Err(PlannerError::NonFiniteState);
        }
        let cfg = &self.cfg;
        let k = cfg.horizon_steps;
        let dt = cfg.dt;
        self.constraints.clear();

        // The previous plan, if it is current and the drone is on it.
        let previous = self.previous.as_ref().filter(|p| {
            now >= p.start - 1e-9
                && now <= p.end_time()
                && (p.sample(now).position - position).norm() <= PREVIOUS_PLAN_DRIFT
        });
        let a_prev = previous.map_or(Vec3::zeros(), |p| p.sample(now).acceleration);
        let lin = |t: f64| -> Vec3 {
            previous
                .and_then(|p| path_point(&p.positions, p.dt, now - p.start + t))
                .unwrap_or(position)
        };

        if !(is_finite(&goal.position) && is_finite(&goal.velocity)) {
            return Ok(self.brake(now, position, velocity, BrakeReason::BadGoal, 0));
        }

        // A half-space no plan the QP can return leaves cannot be active.
        let reachable = Reachable::new(position, velocity, cfg.max_speed, cfg.max_accel, dt, k);
        let redundant = |half: &HalfSpace, seg: usize| reachable.keeps_inside(half, seg);
        let speed_bounds: Vec<f64> = (1..=k)
            .map(|step| {
                cfg.max_speed
                    .max(velocity.norm() - cfg.max_accel * step as f64 * dt)
            })
            .collect();

        // Reference: the goal predicted to the end of the horizon, reached around the first
        // blocking obstacle, clipped to one horizon's travel along that route.
        let horizon = cfg.horizon();
        let goal_end = goal.position + goal.velocity * horizon;
        let route = route::plan_route(
            &position,
            &goal_end,
            &self.keep_out,
            &self.detour_zone,
            &mut self.detour_sides,
        );
        let (carrot, clipped) =
            route::carrot(&position, &route, &goal_end, cfg.max_speed * horizon);
        self.reference.clear();
        // Far away (or detouring): every step aims at the carrot, cruising towards it. Close to
        // the goal: the goal's predicted positions and its velocity.
        let velocity_reference = if clipped || route.waypoint.is_some() {
            self.reference.extend(std::iter::repeat_n(carrot, k));
            let dir = carrot - position;
            if dir.norm() > 1e-9 {
                dir / dir.norm() * cfg.max_speed
            } else {
                Vec3::zeros()
            }
        } else {
            self.reference
                .extend((1..=k).map(|step| goal.position + goal.velocity * (step as f64 * dt)));
            goal.velocity
        };

        // Obstacles: tangent half-spaces at the previous plan, per segment.
        for (oi, obstacle) in self.keep_out.iter().enumerate() {
            let away = position - obstacle.center;
            for seg in 0..k {
                let q = lin((seg as f64 + 0.5) * dt);
                let half = tangent_half_space(obstacle, &q, &away);
                if redundant(&half, seg) {
                    continue;
                }
                self.constraints.push(SegmentConstraint {
                    segment: seg,
                    half,
                    kind: ConstraintKind::Obstacle(oi),
                });
            }
        }

        // Neighbours: separating half-spaces, per segment, from the same pair of points the
        // neighbour uses (my published path and theirs, read at the same instants).
        let mut ignored = 0;
        for (ni, n) in neighbours.iter().enumerate() {
            if !n.is_valid() {
                ignored += 1;
                continue;
            }
            // A neighbour that gives way keeps half the distance; from one that cannot, I keep
            // all of it, measured from its own path rather than from the midpoint. One whose
            // path is older than a second is not giving way any more, whatever it said.
            let share = if n.avoids && n.age_s <= STILL_AVOIDS_S {
                0.5
            } else {
                1.0
            };
            let stale = (cfg.stale_margin_rate * n.age_s.max(0.0)).min(cfg.max_stale_margin);
            let keep = cfg.safety_distance * share + self.separation_margin + stale;
            let fallback = n.position_at(0.0).unwrap_or(position) - position;
            for seg in 0..k {
                let t = (seg as f64 + 0.5) * dt;
                let mine = lin(t);
                let Some(theirs) = n.position_at(t) else {
                    continue;
                };
                let half = separating_half_space(
                    &mine,
                    &theirs,
                    keep,
                    share,
                    &self.metric,
                    cfg.right_hand_angle,
                    &fallback,
                );
                if redundant(&half, seg) {
                    continue;
                }
                self.constraints.push(SegmentConstraint {
                    segment: seg,
                    half,
                    kind: ConstraintKind::Neighbour(ni),
                });
            }
        }

        let mut shrunk = cfg.shrunk_workspace();
        let ground = cfg.workspace.min.z;
        let lowest_wanted = goal.position.z.min(goal_end.z).min(position.z) - ground;
        shrunk.min.z = shrunk
            .min
            .z
            .max(ground + cfg.floor_clearance.min(lowest_wanted));
        let workspace_slack_weight = cfg.slack_weight * k as f64;
        let warm = previous.map(|_| &lin as &dyn Fn(f64) -> Vec3);
        self.screen
            .start(&self.constraints, warm, dt, cfg.screen_distance);
        let mut iterations = 0;
        let (plan, out) = loop {
            self.screen.chosen(&self.constraints, &mut self.in_qp);
            let input = QpInput {
                dt,
                p0: position,
                v0: velocity,
                a_prev,
                reference: &self.reference,
                velocity_reference,
                speed_bounds: &speed_bounds,
                // A drone already climbing or descending faster than allowed (a take-over in
                // flight) is let keep that rate rather than made infeasible; the cost slows it.
                climb_bound: cfg.max_climb_rate.max(velocity.z),
                descent_bound: cfg.max_descent_rate.max(-velocity.z),
                max_accel: cfg.max_accel,
                box_lo: shrunk.min,
                box_hi: shrunk.max,
                reachable: &reachable,
                constraints: &self.in_qp,
                weights: cfg.weights,
                slack_weight: cfg.slack_weight,
                workspace_slack_weight,
                floor_slack_weight: workspace_slack_weight * cfg.floor_weight_factor,
            };
            let mut out = match self.qp.solve(&input) {
                Ok(out) => out,
                Err(e) => return Ok(self.brake(now, position, velocity, e.into(), ignored)),
            };
            iterations += out.iterations;
            let plan = Plan::integrate(
                now,
                dt,
                position,
                velocity,
                std::mem::take(&mut out.accelerations),
            );
            if !plan.is_finite() {
                return Ok(self.brake(
                    now,
                    position,
                    velocity,
                    BrakeReason::NonFinitePlan,
                    ignored,
                ));
            }
            if !self
                .screen
                .missed(&self.constraints, &plan, cfg.screen_distance)
            {
                break (plan, out);
            }
        };
        let max_slack = out
            .slacks
            .iter()
            .copied()
            .fold(out.workspace_slack.max(out.floor_slack), f64::max);
        let status = if max_slack <= SLACK_TOLERANCE {
            PlanStatus::Solved
        } else {
            PlanStatus::Relaxed { max_slack }
        };
        self.previous = Some(plan.clone());
        Ok(PlanResult {
            plan,
            status,
            iterations,
            qp_solves: self.screen.solves(),
            qp_constraints: self.in_qp.len(),
            ignored_neighbours: ignored,
        })
    }

    fn brake(
        &mut self,
        now: f64,
        position: Vec3,
        velocity: Vec3,
        reason: BrakeReason,
        ignored: usize,
    ) -> PlanResult {
        let plan = Plan::braking(
            now,
            self.cfg.dt,
            self.cfg.horizon_steps,
            position,
            velocity,
            self.cfg.max_accel,
        );
        self.previous = Some(plan.clone());
        PlanResult {
            plan,
            status: PlanStatus::Braking(reason),
            iterations: 0,
            qp_solves: self.screen.solves(),
            qp_constraints: self.in_qp.len(),
            ignored_neighbours: ignored,
        }
    }
}

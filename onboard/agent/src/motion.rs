//! Between the executor and the planner: the neighbours' latest paths, the tracks of the observed
//! targets, and the planner stepped at its own rate, sampled into a reference at every control
//! tick. No I/O: the shell passes in the messages and the time (the one clock read here times
//! the solves, for the log).
//!
//! Time is the wall clock in seconds since the Unix epoch, the clock of `PathMessage::stamp`, so
//! a neighbour's path can be aged on arrival.

use crate::planner::{
    Goal, NeighbourPath, Plan, PlanStatus, Planner, PlannerConfig, PlannerError, ReferenceState,
    neighbours_in_range,
};
use crate::tracker::{Track, TrackerConfig, tracking_offset};
use std::collections::HashMap;
use tacos_shared::messages::{PathMessage, TargetsMessage};
use tacos_shared::{DroneId, Vec3};

#[derive(Debug, Clone, PartialEq)]
pub struct MotionConfig {
    /// Seconds between solves (the planner's rate is its inverse: 20 Hz or more).
    pub plan_period: f64,
    /// A neighbour path older than this is forgotten: its drone has been silent that long.
    /// Until then it is kept with a margin that grows with its age (see the planner).
    pub forget_path_after: f64,
    pub tracker: TrackerConfig,
    /// Trackers of one target stand on a circle of at least this radius around it.
    pub tracking_radius: f64,
}

impl Default for MotionConfig {
    fn default() -> Self {
        MotionConfig {
            plan_period: 0.04,
            forget_path_after: 10.0,
            tracker: TrackerConfig::default(),
            tracking_radius: 6.0,
        }
    }
}

/// How the executor wants the drone flown this tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Steering {
    /// The autopilot flies (take-off, landing) or the drone stands: stream this point as a
    /// still reference; the drone cannot give way, and its path says so.
    Still(Vec3),
    /// The planner flies towards this goal, apart from the neighbours and the obstacles.
    Toward(Goal),
}

/// Where a tracker should be, or why it cannot say.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Station {
    /// The target's predicted state plus this drone's offset: a moving goal.
    At(Goal),
    /// The target has not been observed yet.
    Unseen,
    /// Observed once, silent for longer than the coast time.
    Lost,
}

/// Counters for the log (nothing is logged per tick).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SolveStats {
    pub solves: u64,
    pub relaxed: u64,
    pub braking: u64,
    /// Longest solve so far, seconds.
    pub slowest_s: f64,
}

/// One tick's result: the setpoint to stream and, at the planner's rate, the path to publish.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionOutput {
    pub reference: ReferenceState,
    pub path: Option<PathMessage>,
}

#[derive(Debug)]
pub struct Motion {
    me: DroneId,
    cfg: MotionConfig,
    planner: Planner,
    paths: HashMap<DroneId, PathMessage>,
    tracks: HashMap<String, Track>,
    /// The plan being sampled, while the planner flies.
    plan: Option<Plan>,
    last_solve: Option<f64>,
    last_path: Option<f64>,
    stats: SolveStats,
}

impl Motion {
    pub fn new(
        me: DroneId,
        planner: PlannerConfig,
        cfg: MotionConfig,
    ) -> Result<Self, PlannerError> {
        Ok(Motion {
            me,
            planner: Planner::new(planner)?,
            cfg,
            paths: HashMap::new(),
            tracks: HashMap::new(),
            plan: None,
            last_solve: None,
            last_path: None,
            stats: SolveStats::default(),
        })
    }

    pub fn stats(&self) -> SolveStats {
        self.stats
    }

    pub fn planner_config(&self) -> &PlannerConfig {
        self.planner.config()
    }

    /// A neighbour's path. My own (echoed back by zenoh) and older ones than the latest held
    /// are ignored; an unusable one (no points, non-finite) is dropped by the planner's filter.
    pub fn on_path(&mut self, path: PathMessage) {
        if path.drone == self.me || !path.stamp.is_finite() {
            return;
        }
        match self.paths.get(&path.drone) {
            Some(held) if held.stamp >= path.stamp => {}
            _ => {
                self.paths.insert(path.drone.clone(), path);
            }
        }
    }

    /// Observed targets; `now` is when they arrived (the publisher's stamp is on its own clock).
    pub fn on_targets(&mut self, message: &TargetsMessage, now: f64) {
        for target in &message.targets {
            match self.tracks.get_mut(&target.name) {
                Some(track) => track.observe(target.position, target.velocity, now),
                None => {
                    let finite = tacos_shared::geometry::is_finite(&target.position)
                        && tacos_shared::geometry::is_finite(&target.velocity);
                    if finite {
                        let track =
                            Track::new(self.cfg.tracker, target.position, target.velocity, now);
                        self.tracks.insert(target.name.clone(), track);
                    }
                }
            }
        }
    }

    /// The neighbours whose path is recent enough to plan against, aged to `now`.
    fn neighbours(&self, now: f64) -> impl Iterator<Item = NeighbourPath> + '_ {
        self.paths
            .values()
            .filter(move |p| now - p.stamp <= self.cfg.forget_path_after)
            .map(move |p| NeighbourPath::from_message(p, now))
    }

    /// The drones (me included) tracking `target` now, by their recent paths.
    fn trackers_of(&self, target: &str, now: f64) -> Vec<DroneId> {
        let fresh = 1.0;
        let mut all: Vec<DroneId> = self
            .paths
            .values()
            .filter(|p| now - p.stamp <= fresh && p.tracking.as_deref() == Some(target))
            .map(|p| p.drone.clone())
            .collect();
        all.push(self.me.clone());
        all
    }

    /// Where this drone should be to follow `target` at `altitude`: the target predicted to
    /// `now` plus this drone's place on a circle shared evenly with every other tracker of it.
    pub fn station(&self, target: &str, altitude: f64, now: f64) -> Station {
        let Some(track) = self.tracks.get(target) else {
            return Station::Unseen;
        };
        if track.lost(now) {
            return Station::Lost;
        }
        let (position, velocity) = track.predict(now);
        let trackers = self.trackers_of(target, now);
        // Neighbours on the circle must stand the safety distance apart (plus a margin).
        let n = trackers.len().max(1) as f64;
        let chord = self.planner.config().safety_distance + 1.0;
        let radius = if n >= 2.0 {
            self.cfg
                .tracking_radius
                .max(chord / (2.0 * (std::f64::consts::PI / n).sin()))
        } else {
            self.cfg.tracking_radius
        };
        let others: Vec<DroneId> = trackers.into_iter().filter(|d| *d != self.me).collect();
        let offset = tracking_offset(&self.me, &others, radius, 0.0);
        let goal = Vec3::new(position.x + offset.x, position.y + offset.y, altitude);
        let velocity = Vec3::new(velocity.x, velocity.y, 0.0);
        Station::At(Goal {
            position: goal,
            velocity,
        })
    }

    /// One control tick: the setpoint to stream now, and the path to publish when one is due.
    /// `position` and `velocity` are the vehicle's, `tracking` the target followed (if any).
    pub fn step(
        &mut self,
        now: f64,
        position: Vec3,
        velocity: Vec3,
        steering: Steering,
        tracking: Option<&str>,
    ) -> MotionOutput {
        let period = self.cfg.plan_period;
        let due = |last: Option<f64>| last.is_none_or(|t| now - t >= period - 1e-3);
        match steering {
            Steering::Still(point) => {
                self.plan = None;
                self.planner.reset();
                let path = due(self.last_path).then(|| {
                    self.last_path = Some(now);
                    // Where it is heading on its own (climbing, descending, standing).
                    let cfg = self.planner.config();
                    let positions = (0..=cfg.horizon_steps)
                        .map(|k| position + velocity * (k as f64 * cfg.dt))
                        .collect();
                    self.path_message(now, cfg.dt, positions, false, None)
                });
                MotionOutput {
                    reference: ReferenceState::still(point),
                    path,
                }
            }
            Steering::Toward(goal) => {
                let mut path = None;
                if self.plan.is_none() || due(self.last_solve) {
                    self.solve(now, position, velocity, &goal);
                    if let Some(plan) = &self.plan {
                        self.last_path = Some(now);
                        let positions = plan.positions.clone();
                        path = Some(self.path_message(
                            now,
                            plan.dt,
                            positions,
                            true,
                            tracking.map(str::to_owned),
                        ));
                    }
                }
                let reference = match &self.plan {
                    Some(plan) => plan.sample(now),
                    None => ReferenceState::still(position),
                };
                MotionOutput { reference, path }
            }
        }
    }

    fn solve(&mut self, now: f64, position: Vec3, velocity: Vec3, goal: &Goal) {
        self.last_solve = Some(now);
        let range = self.planner.config().neighbour_range;
        let neighbours = neighbours_in_range(position, self.neighbours(now), range);
        let started = std::time::Instant::now();
        let result = self
            .planner
            .plan(now, position, velocity, goal, &neighbours);
        let took = started.elapsed().as_secs_f64();
        self.stats.slowest_s = self.stats.slowest_s.max(took);
        match result {
            Ok(r) => {
                self.stats.solves += 1;
                match r.status {
                    PlanStatus::Solved => {}
                    PlanStatus::Relaxed { .. } => self.stats.relaxed += 1,
                    PlanStatus::Braking(_) => self.stats.braking += 1,
                }
                self.plan = Some(r.plan);
            }
            // A non-finite vehicle state: keep sampling the last plan (or hold, without one).
            Err(_) => {}
        }
    }

    fn path_message(
        &self,
        now: f64,
        dt: f64,
        positions: Vec<Vec3>,
        avoids: bool,
        tracking: Option<String>,
    ) -> PathMessage {
        PathMessage {
            drone: self.me.clone(),
            stamp: now,
            dt,
            positions,
            tracking,
            avoids,
        }
    }
}

#[cfg(test)]
mod tests;

//! Between the executor and the planner: the neighbours' latest paths, the tracks of the observed
//! targets, and the planner stepped at its own rate, sampled into a reference at every control
//! tick. No I/O: the shell passes in the messages and the time (the one clock read here times
//! the solves, for the log).
//!
//! Time is the swarm's clock in seconds on the Unix scale (the wall clock, or the simulator's in
//! a simulated run: `tacos_bus::clock`), the clock of `PathMessage::stamp`, so a neighbour's path
//! can be aged on arrival.

use crate::planner::{
    Downwash, Goal, NeighbourPath, Plan, PlanStatus, Planner, PlannerConfig, PlannerError,
    ReferenceState, neighbours_in_range, recheck,
};
use crate::tracker::{Track, TrackerConfig, tracking_offset};
use std::collections::HashMap;
use tacos_shared::messages::{PathMessage, TargetsMessage};
use tacos_shared::{DroneId, Vec3};

mod tracking_error;
pub use tracking_error::TrackingError;

#[derive(Debug, Clone, PartialEq)]
pub struct MotionConfig {
    /// Seconds between solves (the planner's rate is its inverse: 20 Hz or more).
    pub plan_period: f64,
    /// The path of a neighbour last seen on the ground is forgotten when it is older than
    /// this. One last seen airborne never is: a drone whose onboard died goes on hovering (its
    /// writer holds it), so it stays an obstacle at its path's end, with a margin that grows
    /// with the path's age up to a bound (see the planner), until a newer path says it landed.
    pub forget_path_after: f64,
    pub tracker: TrackerConfig,
    /// Trackers of one target stand on a circle of at least this radius around it.
    pub tracking_radius: f64,
    /// A solve starts from the current plan's own state at that instant while the vehicle is
    /// within this distance of it, and from the vehicle's measured state otherwise (see
    /// [`Motion::solve_job`]).
    pub replan_from_plan_within: f64,
    /// The measured tracking error (see [`TrackingError`]) halves every this many seconds.
    pub tracking_error_half_life: f64,
}

impl Default for MotionConfig {
    fn default() -> Self {
        MotionConfig {
            plan_period: 0.05,
            forget_path_after: 10.0,
            tracker: TrackerConfig::default(),
            tracking_radius: 6.0,
            replan_from_plan_within: 0.25,
            tracking_error_half_life: 5.0,
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
    /// The last centimetres of a landing under offboard control: stream `point` with a descent
    /// of `speed` m/s as the velocity feed-forward. PX4's land detector counts ground contact
    /// only while the setpoint asks for a descent (`MulticopterLandDetector`'s `_in_descend`), so
    /// a still point on the floor would never be detected as landed.
    Sink { point: Vec3, speed: f64 },
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
    /// Finished plans not flown: they came closer to a neighbour's latest path than the plan
    /// being flown (see [`crate::planner::recheck`]).
    pub rejected: u64,
    /// Longest solve so far, seconds.
    pub slowest_s: f64,
    /// Longest the planner's drone was flown past its plan's end, seconds: the reference then
    /// stands at the plan's last point, and a vehicle that reaches it at speed overshoots
    /// where no neighbour expects it.
    pub overran_s: f64,
    /// Widest separation margin a solve used (metres): the configured one, or the measured
    /// tracking error when larger (see [`TrackingError`]).
    pub widest_margin_m: f64,
}

/// One tick's result: the setpoint to stream and, at the planner's rate, the path to publish.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionOutput {
    pub reference: ReferenceState,
    pub path: Option<PathMessage>,
}

/// One solve, taken out of `Motion` to run off the control loop (a blocking thread): the
/// planner itself and everything it reads. `run` is pure computation.
#[derive(Debug)]
pub struct SolveJob {
    planner: Planner,
    now: f64,
    position: Vec3,
    velocity: Vec3,
    goal: Goal,
    neighbours: Vec<NeighbourPath>,
    tracking: Option<String>,
    generation: u64,
}

/// A finished solve, to hand back with [`Motion::solve_done`].
#[derive(Debug)]
pub struct SolveDone {
    planner: Planner,
    result: Result<crate::planner::PlanResult, PlannerError>,
    took_s: f64,
    now: f64,
    tracking: Option<String>,
    generation: u64,
}

impl SolveJob {
    pub fn run(mut self) -> SolveDone {
        let started = std::time::Instant::now();
        let result = self.planner.plan(
            self.now,
            self.position,
            self.velocity,
            &self.goal,
            &self.neighbours,
        );
        SolveDone {
            took_s: started.elapsed().as_secs_f64(),
            planner: self.planner,
            result,
            now: self.now,
            tracking: self.tracking,
            generation: self.generation,
        }
    }
}

#[derive(Debug)]
pub struct Motion {
    me: DroneId,
    cfg: MotionConfig,
    planner_cfg: PlannerConfig,
    /// `None` while a solve is out (see [`SolveJob`]).
    planner: Option<Planner>,
    paths: HashMap<DroneId, PathMessage>,
    tracks: HashMap<String, Track>,
    /// The plan being sampled, while the planner flies.
    plan: Option<Plan>,
    /// Bumped whenever the planner stops flying, so a solve started before is not used after.
    generation: u64,
    last_solve: Option<f64>,
    last_path: Option<f64>,
    stats: SolveStats,
    /// Whether this drone's vehicle is airborne, as the executor says (`set_airborne`): told
    /// to neighbours in every path.
    airborne: bool,
    /// The spans (from, to) this process was stalled and could not listen (`crate::stall`): the
    /// part of the peers' silence inside them is not silence. A path stamped inside a span
    /// (published while this process was stopped, taken in after it) leaves the rest of the
    /// span excused: resetting the excuse on any newer path made such a path, 1 s into a 5 s
    /// stall, count the 4 s after it as silence, and the drone held.
    deaf: Vec<(f64, f64)>,
    /// How far the vehicle has strayed from the plans it flew, lately.
    tracking_error: TrackingError,
}

impl Motion {
    pub fn new(
        me: DroneId,
        planner: PlannerConfig,
        cfg: MotionConfig,
    ) -> Result<Self, PlannerError> {
        Ok(Motion {
            me,
            planner: Some(Planner::new(planner.clone())?),
            planner_cfg: planner,
            paths: HashMap::new(),
            tracks: HashMap::new(),
            plan: None,
            generation: 0,
            last_solve: None,
            last_path: None,
            stats: SolveStats::default(),
            deaf: Vec::new(),
            airborne: false,
            tracking_error: TrackingError::new(cfg.tracking_error_half_life),
            cfg,
        })
    }

    /// Whether the vehicle is armed and off the ground (the executor's view), for the paths.
    pub fn set_airborne(&mut self, airborne: bool) {
        self.airborne = airborne;
    }

    /// True while a plan is being sampled (the planner flies and has solved at least once).
    pub fn has_plan(&self) -> bool {
        self.plan.is_some()
    }

    pub fn stats(&self) -> SolveStats {
        self.stats
    }

    pub fn planner_config(&self) -> &PlannerConfig {
        &self.planner_cfg
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
                // A span that ended before this stamp cannot overlap a silence counted from it.
                let stamp = path.stamp;
                self.deaf.retain(|&(_, to)| to > stamp);
                self.paths.insert(path.drone.clone(), path);
            }
        }
    }

    /// The `deaf_s` seconds up to `now` this process could not listen (a stall:
    /// `crate::stall`) are left out of the peers' silence.
    pub fn excuse_peers(&mut self, deaf_s: f64, now: f64) {
        if deaf_s.is_finite() && deaf_s > 0.0 && now.is_finite() {
            self.deaf.push((now - deaf_s, now));
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

    /// A neighbour is known while it was last seen airborne, or for `forget_path_after`.
    fn known(&self, path: &PathMessage, now: f64) -> bool {
        path.airborne || now - path.stamp <= self.cfg.forget_path_after
    }

    /// The neighbours whose path is recent enough to plan against, aged to `now`.
    fn neighbours(&self, now: f64) -> impl Iterator<Item = NeighbourPath> + '_ {
        self.paths
            .values()
            .filter(move |p| self.known(p, now))
            .map(move |p| NeighbourPath::from_message(p, now))
    }

    /// How long since any neighbour this drone knows (one it plans against: see `neighbours`)
    /// was last heard, by the newest of their paths' stamps; `None` while it knows fewer than
    /// two. Every onboard publishes a path at the planner's rate whether it flies or stands, so
    /// two or more falling silent together means this drone is cut off from its peers. The
    /// silence of a single neighbour cannot tell this drone's link from that neighbour's
    /// failure, which the ground sees and answers (it replans without it) while the planner
    /// keeps it where it was last heard. A neighbour last seen on the ground is forgotten after
    /// `forget_path_after`, and its silence with it; one last seen airborne never is.
    pub fn peers_silence(&self, now: f64) -> Option<f64> {
        let stamps = self
            .paths
            .values()
            .filter(|p| self.known(p, now))
            .map(|p| p.stamp);
        let (count, newest) = stamps.fold((0, f64::NEG_INFINITY), |(n, m), t| (n + 1, m.max(t)));
        (count >= 2).then(|| {
            let deaf: f64 = (self.deaf.iter())
                .map(|&(from, to)| (to.min(now) - from.max(newest)).max(0.0))
                .sum();
            (now - newest - deaf).max(0.0)
        })
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
        let chord = self.planner_cfg.safety_distance + 1.0;
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

    /// One control tick: the setpoint to stream now (the current plan sampled, or the still
    /// point), and for a drone the planner does not fly, its path when one is due. Solves are
    /// separate: see [`Motion::solve_job`].
    pub fn tick(
        &mut self,
        now: f64,
        position: Vec3,
        velocity: Vec3,
        steering: Steering,
    ) -> MotionOutput {
        let reference = match steering {
            Steering::Still(point) => ReferenceState::still(point),
            Steering::Sink { point, speed } => ReferenceState {
                position: point,
                velocity: Vec3::new(0.0, 0.0, -speed),
                acceleration: Vec3::zeros(),
            },
            Steering::Toward(_) => {
                let reference = match &self.plan {
                    Some(plan) => {
                        let overran = now - plan.end_time();
                        self.stats.overran_s = self.stats.overran_s.max(overran);
                        let planned = plan.sample(now);
                        // In the separation's own metric (vertical distances count less).
                        let metric = Downwash::new(self.planner_cfg.downwash_factor);
                        let error = metric.distance(&planned.position, &position);
                        self.tracking_error.observe(now, error);
                        planned
                    }
                    // Until the first solve lands (a few milliseconds), stay where it is.
                    None => ReferenceState::still(position),
                };
                return MotionOutput {
                    reference,
                    path: None,
                };
            }
        };
        // Not flown by the planner: drop its plan, and publish where the drone heads on its own.
        if self.plan.take().is_some() {
            self.generation += 1;
        }
        if let Some(planner) = self.planner.as_mut() {
            planner.reset();
        }
        let path = self.due(self.last_path, now).then(|| {
            self.last_path = Some(now);
            // Where it is heading on its own (climbing, descending, standing).
            let cfg = &self.planner_cfg;
            let positions = (0..=cfg.horizon_steps)
                .map(|k| position + velocity * (k as f64 * cfg.dt))
                .collect();
            self.path_message(now, cfg.dt, positions, false, None)
        });
        MotionOutput { reference, path }
    }

    fn due(&self, last: Option<f64>, now: f64) -> bool {
        last.is_none_or(|t| now - t >= self.cfg.plan_period - 1e-3)
    }

    /// The solve to run now, unless one is out: the planner is lent to the job until
    /// [`Motion::solve_done`] returns it. The caller paces solves (the shell's planner timer).
    pub fn solve_job(
        &mut self,
        now: f64,
        position: Vec3,
        velocity: Vec3,
        goal: Goal,
        tracking: Option<&str>,
    ) -> Option<SolveJob> {
        let range = self.planner_cfg.neighbour_range;
        let neighbours = neighbours_in_range(position, self.neighbours(now), range);
        let mut planner = self.planner.take()?;
        self.last_solve = Some(now);
        // The margin for straying covers what this vehicle has been seen to stray, up to a
        // third of the safety distance: two drones' margins then ask for 1.67 safety distances
        // between them, which the lab's pads (1 m apart, 0.6 m safety distance) still give;
        // half of it asked for 1.2 m there, and the drones squeezed between their neighbours
        // were pushed into PX4's geofence or away from their goals.
        let strayed = (self.tracking_error.value(now)).min(self.planner_cfg.safety_distance / 3.0);
        let margin = planner.set_separation_margin(strayed);
        self.stats.widest_margin_m = self.stats.widest_margin_m.max(margin);
        // Replanning from the measured state every 50 ms feeds the autopilot's lag and its
        // estimate's noise back into the plan: each new plan starts where the vehicle lags, at
        // the speed it has reached, and a climb at the lab's 1 m/s² stalled 0.3 m up on PX4 SIH
        // while every plan still ended at the goal. So a solve starts from the plan being
        // flown, as long as the vehicle follows it.
        let (start, start_velocity) = match &self.plan {
            Some(plan) => {
                let planned = plan.sample(now);
                if (planned.position - position).norm() <= self.cfg.replan_from_plan_within {
                    (planned.position, planned.velocity)
                } else {
                    (position, velocity)
                }
            }
            None => (position, velocity),
        };
        Some(SolveJob {
            planner,
            now,
            position: start,
            velocity: start_velocity,
            goal,
            neighbours,
            tracking: tracking.map(str::to_owned),
            generation: self.generation,
        })
    }

    /// Takes a finished solve back at `now`: its plan is sampled from now on, and its path is
    /// returned for publishing. A solve overtaken by a still reference (take-off, landing) is
    /// dropped, and so is a plan that comes closer to a neighbour's latest path than the planes
    /// ask and than the plan being flown (see [`crate::planner::recheck`]).
    pub fn solve_done(&mut self, done: SolveDone, now: f64) -> Option<PathMessage> {
        let mut planner = done.planner;
        self.stats.slowest_s = self.stats.slowest_s.max(done.took_s);
        if done.generation != self.generation {
            planner.reset();
            self.planner = Some(planner);
            return None;
        }
        self.planner = Some(planner);
        // A non-finite vehicle state is the only error: keep sampling the last plan.
        let result = done.result.ok()?;
        self.stats.solves += 1;
        if !self.recheck(&result.plan, now) {
            self.stats.rejected += 1;
            if let Some(planner) = self.planner.as_mut() {
                planner.restore_previous(self.plan.clone());
            }
            return None;
        }
        match result.status {
            PlanStatus::Solved => {}
            PlanStatus::Relaxed { .. } => self.stats.relaxed += 1,
            PlanStatus::Braking(_) => self.stats.braking += 1,
        }
        self.last_path = Some(done.now);
        let path = self.path_message(
            done.now,
            result.plan.dt,
            result.plan.positions.clone(),
            true,
            done.tracking,
        );
        self.plan = Some(result.plan);
        Some(path)
    }

    /// Whether `plan` may replace the plan being flown (see [`crate::planner::recheck`]).
    fn recheck(&self, plan: &Plan, now: f64) -> bool {
        let cfg = &self.planner_cfg;
        let here = plan.sample(now).position;
        let neighbours = neighbours_in_range(here, self.neighbours(now), cfg.neighbour_range);
        recheck::may_replace(
            plan,
            self.plan.as_ref(),
            now,
            &neighbours,
            &Downwash::new(cfg.downwash_factor),
            cfg.planes_distance(),
            cfg.horizon() / 2.0,
        )
    }

    /// `tick` with any due solve run at once, on this thread: for tests and benchmarks.
    pub fn step(
        &mut self,
        now: f64,
        position: Vec3,
        velocity: Vec3,
        steering: Steering,
        tracking: Option<&str>,
    ) -> MotionOutput {
        let mut path = None;
        let due = self.plan.is_none() || self.due(self.last_solve, now);
        if let Steering::Toward(goal) = steering
            && due
            && let Some(job) = self.solve_job(now, position, velocity, goal, tracking)
        {
            path = self.solve_done(job.run(), now);
        }
        let out = self.tick(now, position, velocity, steering);
        MotionOutput {
            reference: out.reference,
            path: path.or(out.path),
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
            airborne: self.airborne,
        }
    }
}

#[cfg(test)]
mod tests;

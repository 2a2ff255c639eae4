//! Closed-loop tests of the planner: plan, follow the plan perfectly for one replanning period,
//! replan. Every check is on densely sampled positions, not only the knots.

use super::*;
use tacos_shared::scenario::Scenario;

mod neighbours;
mod screening;
mod stale_reads;

const REPLAN: f64 = 0.05;
const DENSE: usize = 10;

fn city() -> Scenario {
    match Scenario::builtin("city") {
        Ok(s) => s,
        Err(e) => panic!("the built-in city is valid: {e}"),
    }
}

fn city_config() -> PlannerConfig {
    let s = city();
    PlannerConfig::from_scenario(&s.limits, &s.world)
}

fn planner(cfg: &PlannerConfig) -> Planner {
    match Planner::new(cfg.clone()) {
        Ok(p) => p,
        Err(e) => panic!("valid config: {e}"),
    }
}

fn id(name: &str) -> DroneId {
    match DroneId::new(name) {
        Ok(id) => id,
        Err(e) => panic!("{name}: {e}"),
    }
}

fn solve(
    p: &mut Planner,
    now: f64,
    pos: Vec3,
    vel: Vec3,
    goal: &Goal,
    neighbours: &[NeighbourPath],
) -> PlanResult {
    match p.plan(now, pos, vel, goal, neighbours) {
        Ok(r) => r,
        Err(e) => panic!("finite state: {e}"),
    }
}

/// Checks the last solve's constraints on the plan's control points.
fn assert_constraints_hold(p: &Planner, plan: &Plan, tolerance: f64) {
    assert!(!p.last_constraints().is_empty() || plan.steps() > 0);
    for c in p.last_constraints() {
        for (i, cp) in plan.free_control_points(c.segment).iter().enumerate() {
            let d = c.half.signed_distance(cp);
            assert!(
                d >= -tolerance,
                "free control point {i} of segment {} violates {:?} ({:?}) by {d}",
                c.segment,
                c.half,
                c.kind
            );
        }
    }
}

fn assert_within_limits(cfg: &PlannerConfig, plan: &Plan) {
    let tol = 1e-4;
    for v in &plan.velocities[1..] {
        assert!(
            v.norm() <= cfg.max_speed * (1.0 + tol),
            "speed {}",
            v.norm()
        );
    }
    for v in &plan.velocities[1..] {
        assert!(v.z <= cfg.max_climb_rate * (1.0 + tol), "climb {}", v.z);
        assert!(
            -v.z <= cfg.max_descent_rate * (1.0 + tol),
            "descent {}",
            -v.z
        );
    }
    for a in &plan.accelerations {
        assert!(
            a.norm() <= cfg.max_accel * (1.0 + tol),
            "accel {}",
            a.norm()
        );
    }
    let ws = cfg.shrunk_workspace();
    for k in 0..plan.steps() {
        for cp in plan.free_control_points(k) {
            assert!(
                ws.contains_with_margin(&cp, -1e-4),
                "{cp:?} leaves the workspace"
            );
        }
    }
}

#[test]
fn solved_plans_respect_their_half_spaces_and_limits() {
    // The neighbour here does not react; with the default margin the start would already need
    // relaxing. This test is about the construction, so it uses a slimmer margin.
    let cfg = PlannerConfig {
        separation_margin: 0.15,
        ..city_config()
    };
    let mut p = planner(&cfg);
    // Beside a tower, moving fast towards it, with a neighbour ahead.
    let pos = Vec3::new(-18.0, -40.0, 15.0);
    let vel = Vec3::new(0.0, 7.0, 0.0);
    let other = NeighbourPath {
        id: id("bravo"),
        positions: (0..=20)
            .map(|i| Vec3::new(-12.0, -30.0 + 0.3 * i as f64, 15.0))
            .collect(),
        dt: 0.1,
        age_s: 0.05,
        avoids: true,
    };
    let goal = Goal::fixed(Vec3::new(-18.0, 5.0, 15.0));
    let mut now = 0.0;
    let (mut pos, mut vel) = (pos, vel);
    let mut checked = 0;
    let mut solved = 0;
    for _ in 0..20 {
        let r = solve(&mut p, now, pos, vel, &goal, std::slice::from_ref(&other));
        // The neighbour does not react, so it may leave less room than it should: any relaxation
        // is small and shows up as slack, which bounds the violation.
        let tolerance = match r.status {
            PlanStatus::Solved => {
                solved += 1;
                SLACK_TOLERANCE + 1e-4
            }
            PlanStatus::Relaxed { max_slack } => {
                assert!(max_slack < 0.05, "{max_slack}");
                max_slack + 1e-4
            }
            PlanStatus::Braking(reason) => panic!("braking: {reason}"),
        };
        assert_constraints_hold(&p, &r.plan, tolerance);
        assert_within_limits(&cfg, &r.plan);
        checked += p.last_constraints().len();
        now += REPLAN;
        let s = r.plan.sample(now);
        (pos, vel) = (s.position, s.velocity);
    }
    let kinds = p
        .last_constraints()
        .iter()
        .map(|c| c.kind)
        .collect::<Vec<_>>();
    assert!(checked > 100, "{checked} constraints checked");
    assert!(
        solved >= 15,
        "only {solved} of 20 solves kept every constraint"
    );
    assert!(
        kinds
            .iter()
            .any(|k| matches!(k, ConstraintKind::Obstacle(_)))
    );
}

#[test]
fn plans_stop_at_the_workspace_walls() {
    let cfg = city_config();
    let mut p = planner(&cfg);
    let (mut pos, mut vel) = (Vec3::new(140.0, 0.0, 90.0), Vec3::new(6.0, 0.0, 3.0));
    let goal = Goal::fixed(Vec3::new(300.0, 0.0, 200.0)); // outside the bounds
    let ws = cfg.shrunk_workspace();
    let mut now = 0.0;
    for _ in 0..200 {
        let r = solve(&mut p, now, pos, vel, &goal, &[]);
        assert_eq!(r.status, PlanStatus::Solved);
        assert_within_limits(&cfg, &r.plan);
        for i in 0..=DENSE {
            let q = r
                .plan
                .sample(now + REPLAN * i as f64 / DENSE as f64)
                .position;
            assert!(ws.contains_with_margin(&q, -1e-4), "{q:?}");
        }
        now += REPLAN;
        let s = r.plan.sample(now);
        (pos, vel) = (s.position, s.velocity);
    }
    // It ended up in the corner nearest the goal, stopped.
    assert!((pos - Vec3::new(159.5, 0.0, 99.5)).norm() < 1.0, "{pos:?}");
    assert!(vel.norm() < 0.1);
}

#[test]
fn climbs_and_descents_keep_to_the_autopilots_vertical_rates() {
    // The city allows 8 m/s; PX4 climbs at 3 and descends at 1.5 m/s at most, whatever its
    // setpoints ask, so a plan faster than that is one the vehicle falls behind.
    let cfg = city_config();
    assert!(cfg.max_speed > cfg.max_climb_rate && cfg.max_climb_rate > cfg.max_descent_rate);
    for (start, goal) in [
        (Vec3::new(100.0, 100.0, 60.0), Vec3::new(100.0, 100.0, 5.0)),
        (Vec3::new(100.0, 100.0, 5.0), Vec3::new(100.0, 100.0, 60.0)),
    ] {
        let mut p = planner(&cfg);
        let (mut pos, mut vel) = (start, Vec3::zeros());
        let (mut fastest_up, mut fastest_down) = (0.0_f64, 0.0_f64);
        let mut now = 0.0;
        while now < 60.0 && (pos - goal).norm() > 0.5 {
            let r = solve(&mut p, now, pos, vel, &Goal::fixed(goal), &[]);
            assert_within_limits(&cfg, &r.plan);
            for i in 0..=DENSE {
                let v = r
                    .plan
                    .sample(now + REPLAN * i as f64 / DENSE as f64)
                    .velocity;
                fastest_up = fastest_up.max(v.z);
                fastest_down = fastest_down.max(-v.z);
            }
            now += REPLAN;
            let s = r.plan.sample(now);
            (pos, vel) = (s.position, s.velocity);
        }
        assert!(
            (pos - goal).norm() <= 0.5,
            "from {start:?}: stopped at {pos:?}"
        );
        assert!(
            fastest_up <= cfg.max_climb_rate + 1e-3,
            "climbed at {fastest_up}"
        );
        assert!(
            fastest_down <= cfg.max_descent_rate + 1e-3,
            "descended at {fastest_down}"
        );
        // And the rates are used, not a slower crawl.
        assert!(fastest_up.max(fastest_down) >= 0.9 * cfg.max_descent_rate);
    }
}

struct Flight {
    /// Per drone: dense positions.
    tracks: Vec<Vec<Vec3>>,
    arrived_at: Vec<Option<f64>>,
    relaxed: usize,
    braking: usize,
}

/// Flies `starts` to `goals` with perfect tracking and 20 Hz replanning; each drone sees every
/// other's previous path (range-filtered, age one period).
fn fly(cfg: &PlannerConfig, starts: &[Vec3], goals: &[Vec3], seconds: f64) -> Flight {
    let n = starts.len();
    let mut planners: Vec<Planner> = (0..n).map(|_| planner(cfg)).collect();
    let ids: Vec<DroneId> = (0..n).map(|i| id(&format!("d{i}"))).collect();
    let mut state: Vec<(Vec3, Vec3)> = starts.iter().map(|p| (*p, Vec3::zeros())).collect();
    let mut published: Vec<(f64, Vec<Vec3>)> = starts
        .iter()
        .map(|p| (0.0, vec![*p; cfg.horizon_steps + 1]))
        .collect();
    let mut flight = Flight {
        tracks: vec![Vec::new(); n],
        arrived_at: vec![None; n],
        relaxed: 0,
        braking: 0,
    };
    let mut now = 0.0;
    while now < seconds && flight.arrived_at.iter().any(Option::is_none) {
        let mut plans = Vec::with_capacity(n);
        for i in 0..n {
            let others = (0..n).filter(|&j| j != i).map(|j| NeighbourPath {
                id: ids[j].clone(),
                positions: published[j].1.clone(),
                dt: cfg.dt,
                age_s: now - published[j].0,
                avoids: true,
            });
            let near = neighbours_in_range(state[i].0, others, cfg.neighbour_range);
            let r = solve(
                &mut planners[i],
                now,
                state[i].0,
                state[i].1,
                &Goal::fixed(goals[i]),
                &near,
            );
            match r.status {
                PlanStatus::Solved => {}
                PlanStatus::Relaxed { .. } => flight.relaxed += 1,
                PlanStatus::Braking(_) => flight.braking += 1,
            }
            plans.push(r.plan);
        }
        for (i, plan) in plans.iter().enumerate() {
            for s in 0..DENSE {
                let t = now + REPLAN * s as f64 / DENSE as f64;
                flight.tracks[i].push(plan.sample(t).position);
            }
            published[i] = (now, plan.path().to_vec());
        }
        now += REPLAN;
        for (i, plan) in plans.iter().enumerate() {
            let s = plan.sample(now);
            state[i] = (s.position, s.velocity);
            if flight.arrived_at[i].is_none() && (s.position - goals[i]).norm() < 1.0 {
                flight.arrived_at[i] = Some(now);
            }
        }
    }
    flight
}

#[test]
fn flies_around_a_skyscraper() {
    let cfg = city_config();
    let world = city().world;
    // Straight through the centre of skyscraper_1 (at (-18, -18)).
    let start = Vec3::new(-18.0, -50.0, 15.0);
    let goal = Vec3::new(-18.0, 5.0, 15.0);
    assert!(
        world
            .segment_blocked_by(&start, &goal, cfg.drone_radius)
            .is_some()
    );
    let f = fly(&cfg, &[start], &[goal], 60.0);
    let arrived = f.arrived_at[0];
    assert!(
        arrived.is_some(),
        "did not arrive; ended at {:?}",
        f.tracks[0].last()
    );
    for p in &f.tracks[0] {
        for o in &world.obstacles {
            assert!(
                !o.inflated(cfg.drone_radius).contains(p),
                "{p:?} inside {}",
                o.name
            );
        }
    }
    assert_eq!(f.braking, 0);
    // Around the tower at up to 8 m/s: about 60 m, so well under 20 s.
    assert!(arrived.is_some_and(|t| t < 20.0), "{arrived:?}");
}

#[test]
fn two_drones_swap_head_on() {
    let cfg = city_config();
    // In the park (no obstacles), exactly head-on at the same altitude.
    let a = Vec3::new(40.0, 80.0, 15.0);
    let b = Vec3::new(90.0, 80.0, 15.0);
    let f = fly(&cfg, &[a, b], &[b, a], 60.0);
    assert!(
        f.arrived_at.iter().all(Option::is_some),
        "{:?}",
        f.arrived_at
    );
    let min = f.tracks[0]
        .iter()
        .zip(&f.tracks[1])
        .map(|(p, q)| (p - q).norm())
        .fold(f64::INFINITY, f64::min);
    assert!(min >= cfg.safety_distance, "closest approach {min}");
    assert_eq!(f.braking, 0);
}

#[test]
fn an_infeasible_start_neither_panics_nor_stays() {
    let cfg = city_config();
    let mut p = planner(&cfg);
    // Inside skyscraper_1's inflated zone (centre (-18, -18), semi-axis 8 + 0.5).
    let pos = Vec3::new(-18.0, -10.2, 15.0);
    let goal = Goal::fixed(Vec3::new(-18.0, 30.0, 15.0));
    let r = solve(&mut p, 0.0, pos, Vec3::zeros(), &goal, &[]);
    match r.status {
        PlanStatus::Relaxed { max_slack } => assert!(max_slack > 0.0),
        PlanStatus::Braking(_) => {}
        PlanStatus::Solved => panic!("a start inside an obstacle cannot satisfy every constraint"),
    }
    assert!(r.plan.is_finite());
    assert_eq!(r.plan.positions.len(), cfg.horizon_steps + 1);
    // The plan heads out of the obstacle, not deeper in.
    let tower = &city().world.obstacles[0];
    let level0 = tower.level(&pos);
    let level_end = tower.level(&r.plan.positions[cfg.horizon_steps]);
    assert!(level_end > level0, "{level0} → {level_end}");

    // Between two drones on the same spot: also a plan.
    let twin = NeighbourPath {
        id: id("twin"),
        positions: vec![Vec3::new(60.0, 60.0, 15.0); 21],
        dt: 0.1,
        age_s: 0.0,
        avoids: true,
    };
    let r = solve(
        &mut planner(&cfg),
        0.0,
        Vec3::new(60.0, 60.0, 15.0),
        Vec3::zeros(),
        &Goal::fixed(Vec3::new(70.0, 60.0, 15.0)),
        &[twin],
    );
    assert!(r.plan.is_finite());
    assert!(!matches!(r.status, PlanStatus::Solved));
}

#[test]
fn bad_inputs_are_reported_not_panicked_on() {
    let cfg = city_config();
    let mut p = planner(&cfg);
    let nan = Vec3::new(f64::NAN, 0.0, 0.0);
    assert_eq!(
        p.plan(0.0, nan, Vec3::zeros(), &Goal::fixed(Vec3::zeros()), &[]),
        Err(PlannerError::NonFiniteState)
    );
    let pos = Vec3::new(50.0, 50.0, 10.0);
    let r = solve(
        &mut p,
        0.0,
        pos,
        Vec3::new(2.0, 0.0, 0.0),
        &Goal::fixed(nan),
        &[],
    );
    assert_eq!(r.status, PlanStatus::Braking(BrakeReason::BadGoal));
    assert!(r.plan.velocities.last().is_some_and(|v| v.norm() < 1e-9));
    // A garbage neighbour path is ignored and counted.
    let garbage = NeighbourPath {
        id: id("junk"),
        positions: vec![nan],
        dt: 0.1,
        age_s: 0.0,
        avoids: true,
    };
    let r = solve(
        &mut p,
        0.1,
        pos,
        Vec3::zeros(),
        &Goal::fixed(pos),
        &[garbage],
    );
    assert_eq!(r.ignored_neighbours, 1);
    assert_eq!(r.status, PlanStatus::Solved);

    let mut bad = cfg.clone();
    bad.dt = 0.0;
    assert!(matches!(
        Planner::new(bad),
        Err(PlannerError::InvalidConfig(_))
    ));
    let mut bad = cfg;
    bad.horizon_steps = 0;
    assert!(matches!(
        Planner::new(bad),
        Err(PlannerError::InvalidConfig(_))
    ));
}

#[test]
fn catches_up_with_a_moving_goal() {
    let cfg = city_config();
    let mut p = planner(&cfg);
    let goal_velocity = Vec3::new(3.0, 0.0, 0.0);
    let goal_at = |t: f64| Goal {
        position: Vec3::new(-60.0, 60.0, 15.0) + goal_velocity * t,
        velocity: goal_velocity,
    };
    let (mut pos, mut vel) = (Vec3::new(-60.0, 30.0, 20.0), Vec3::zeros());
    let mut now = 0.0;
    while now < 25.0 {
        let r = solve(&mut p, now, pos, vel, &goal_at(now), &[]);
        assert_eq!(r.status, PlanStatus::Solved);
        now += REPLAN;
        let s = r.plan.sample(now);
        (pos, vel) = (s.position, s.velocity);
    }
    let goal = goal_at(now);
    assert!(
        (pos - goal.position).norm() < 0.5,
        "{pos:?} vs {:?}",
        goal.position
    );
    assert!((vel - goal_velocity).norm() < 0.2, "{vel:?}");
}

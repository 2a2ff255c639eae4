//! The planner's shortcuts change how fast a plan is found, not which plan: the constraint
//! screen (`planner/screen.rs`) — a drone crossing a crowd of hovering neighbours is planned
//! with and without it, from the same states — and the reuse of the last solver for a problem
//! of the same shape (`qp.rs`).

use super::*;
use crate::planner::qp::{QpInput, QpWorkspace};
use crate::planner::reachable::Reachable;

fn hovering(name: &str, at: Vec3) -> NeighbourPath {
    NeighbourPath {
        id: id(name),
        positions: vec![at; 21],
        dt: 0.1,
        age_s: 0.0,
        avoids: true,
    }
}

#[test]
fn a_screened_solve_finds_the_plan_of_the_full_one() {
    let screened_cfg = PlannerConfig {
        screen_distance: 0.3,
        ..city_config()
    };
    let full_cfg = PlannerConfig {
        screen_distance: 1e9,
        ..city_config()
    };
    let (mut screened, mut full) = (planner(&screened_cfg), planner(&full_cfg));
    // Nine neighbours hovering on a grid across the way, at the drone's height and above it.
    let crowd: Vec<NeighbourPath> = [-8.0, 0.0, 8.0]
        .iter()
        .flat_map(|&x| [-7.0, 0.0, 7.0].map(|y| (x, y)))
        .enumerate()
        .map(|(i, (x, y))| {
            let z = if i % 2 == 0 { 15.0 } else { 18.0 };
            hovering(&format!("n{i}"), Vec3::new(x, y, z))
        })
        .collect();
    let goal = Goal::fixed(Vec3::new(30.0, 1.0, 15.0));
    let (mut now, mut pos, mut vel) = (0.0, Vec3::new(-30.0, 0.0, 15.0), Vec3::zeros());
    let (mut left_out, mut largest_gap) = (0, 0.0_f64);
    for _ in 0..120 {
        let a = solve(&mut screened, now, pos, vel, &goal, &crowd);
        let b = solve(&mut full, now, pos, vel, &goal, &crowd);
        assert!(
            !matches!(a.status, PlanStatus::Braking(_)),
            "{:?}",
            a.status
        );
        assert_eq!(b.qp_constraints, full.last_constraints().len());
        left_out += screened.last_constraints().len() - a.qp_constraints;
        // Every half-space holds on the screened plan, the left-out ones included.
        let tolerance = match a.status {
            PlanStatus::Relaxed { max_slack } => max_slack + 1e-4,
            _ => SLACK_TOLERANCE + 1e-4,
        };
        assert_constraints_hold(&screened, &a.plan, tolerance);
        for (p, q) in a.plan.positions.iter().zip(&b.plan.positions) {
            largest_gap = largest_gap.max((p - q).norm());
        }
        now += REPLAN;
        let s = b.plan.sample(now);
        (pos, vel) = (s.position, s.velocity);
    }
    // Into the crowd: past its first column (x = −8 m) and the second.
    assert!(pos.x > 0.0, "the crossing ended at {pos:?}");
    eprintln!("left out {left_out}, plans differ by up to {largest_gap:.2e} m, ended at {pos:?}");
    assert!(
        left_out > 1000,
        "only {left_out} half-spaces were screened out"
    );
    assert!(largest_gap < 0.05, "the plans differ by {largest_gap} m");
}

#[test]
fn a_reused_solver_finds_the_solution_of_a_fresh_one() {
    let cfg = city_config();
    let k = cfg.horizon_steps;
    let speed_bounds = vec![cfg.max_speed; k];
    let mut reusing = QpWorkspace::default();
    let mut largest_gap = 0.0_f64;
    // A drone flying east past the map's middle: every step's problem has the same shape and
    // different data (start, velocity, reference).
    for step in 0..30 {
        let p0 = Vec3::new(-20.0 + 0.5 * step as f64, 3.0, 12.0);
        let v0 = Vec3::new(8.0, 0.0, 0.1 * (step % 3) as f64);
        let reference = vec![Vec3::new(25.0, 3.0 + 0.1 * step as f64, 14.0); k];
        let input = QpInput {
            dt: cfg.dt,
            p0,
            v0,
            a_prev: Vec3::zeros(),
            reference: &reference,
            velocity_reference: Vec3::new(cfg.max_speed, 0.0, 0.0),
            speed_bounds: &speed_bounds,
            climb_bound: cfg.max_climb_rate,
            descent_bound: cfg.max_descent_rate,
            max_accel: cfg.max_accel,
            box_lo: cfg.shrunk_workspace().min,
            box_hi: cfg.shrunk_workspace().max,
            reachable: &Reachable::new(p0, v0, cfg.max_speed, cfg.max_accel, cfg.dt, k),
            constraints: &[],
            weights: cfg.weights,
            slack_weight: cfg.slack_weight,
            workspace_slack_weight: cfg.slack_weight * k as f64,
            floor_slack_weight: cfg.slack_weight * k as f64 * cfg.floor_weight_factor,
        };
        let (reused, fresh) = match (reusing.solve(&input), QpWorkspace::default().solve(&input)) {
            (Ok(a), Ok(b)) => (a, b),
            (a, b) => panic!("step {step}: {a:?} / {b:?}"),
        };
        for (a, b) in reused.accelerations.iter().zip(&fresh.accelerations) {
            largest_gap = largest_gap.max((a - b).norm());
        }
    }
    assert_eq!(
        reusing.reuses(),
        29,
        "every solve after the first reuses the solver"
    );
    assert!(
        largest_gap < 1e-4,
        "accelerations differ by {largest_gap} m/s²"
    );
    eprintln!("accelerations differ by up to {largest_gap:.2e} m/s²");
}

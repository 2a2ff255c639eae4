//! The cause of the 20-drone swap's separation breaches (issue 18 item 7), reproduced with two
//! planners: each solve reads the neighbour's path as last heard, and a neighbour that has
//! replaced that path since plans against a different pair of paths. The two separating planes
//! then differ, each plan keeps to its own, and nothing keeps the plans apart. The same solves
//! reading the same pair keep their distance; [`crate::planner::recheck`] refuses the plans
//! that do not.

use super::super::recheck::{closest_approach, may_replace};
use super::*;

/// `who`'s path as a neighbour hears it: `plan`, published `age_s` ago.
fn heard(who: &str, plan: &Plan, age_s: f64) -> NeighbourPath {
    NeighbourPath {
        id: id(who),
        positions: plan.positions.clone(),
        dt: plan.dt,
        age_s,
        avoids: true,
    }
}

/// A plan from rest at `from`, accelerating along `direction` as hard as `cfg` allows.
fn leaving(cfg: &PlannerConfig, start: f64, from: Vec3, direction: Vec3) -> Plan {
    let steps = cfg.horizon_steps;
    let accelerations = (0..steps)
        .map(|k| {
            let speed = cfg.max_accel * k as f64 * cfg.dt;
            if speed < cfg.max_speed {
                direction * cfg.max_accel
            } else {
                Vec3::zeros()
            }
        })
        .collect();
    Plan::integrate(start, cfg.dt, from, Vec3::zeros(), accelerations)
}

/// alfa's and bravo's next plans, from rest at [`positions`] and bound for each other's side,
/// each solved against the path of the other it holds.
fn solve_pair(
    cfg: &PlannerConfig,
    alfa_reads: NeighbourPath,
    bravo_reads: NeighbourPath,
) -> (Plan, Plan) {
    let (alfa_at, bravo_at) = positions();
    let solve = |own: Vec3, goal: Vec3, reads: NeighbourPath| {
        let mut planner = planner(cfg);
        planner.restore_previous(Some(Plan::hold(0.0, cfg.dt, cfg.horizon_steps, own)));
        planner
            .plan(0.0, own, Vec3::zeros(), &Goal::fixed(goal), &[reads])
            .unwrap_or_else(|e| panic!("finite state: {e}"))
            .plan
    };
    let east = Vec3::new(30.0, 0.0, 0.0);
    (
        solve(alfa_at, bravo_at + east, alfa_reads),
        solve(bravo_at, alfa_at - east, bravo_reads),
    )
}

/// alfa and bravo, 10 m apart west to east at 15 m over the park.
fn positions() -> (Vec3, Vec3) {
    (Vec3::new(55.0, 80.0, 15.0), Vec3::new(65.0, 80.0, 15.0))
}

#[test]
fn plans_solved_against_replaced_paths_come_too_close_and_the_recheck_refuses_them() {
    let cfg = city_config();
    let metric = Downwash::new(cfg.downwash_factor);
    let (alfa_at, bravo_at) = positions();
    let hold = |at: Vec3| Plan::hold(0.0, cfg.dt, cfg.horizon_steps, at);
    let east = Vec3::new(1.0, 0.0, 0.0);
    let closest = |a: &Plan, b: &Plan| {
        closest_approach(a, 0.0, cfg.horizon(), &[heard("bravo", b, 0.0)], &metric)
    };

    // Both read the other hovering, as it is: the same pair of paths, the same plane.
    let (alfa, bravo) = solve_pair(
        &cfg,
        heard("bravo", &hold(bravo_at), 0.0),
        heard("alfa", &hold(alfa_at), 0.0),
    );
    let consistent = closest(&alfa, &bravo);
    assert!(consistent >= cfg.safety_distance, "{consistent}");

    // Each last heard the other leaving, away from it (a path replaced by the hover since,
    // 50 ms ago): each plane lies beyond where the other will be.
    let (alfa, bravo) = solve_pair(
        &cfg,
        heard("bravo", &leaving(&cfg, -0.05, bravo_at, east), 0.05),
        heard("alfa", &leaving(&cfg, -0.05, alfa_at, -east), 0.05),
    );
    let inconsistent = closest(&alfa, &bravo);
    assert!(inconsistent < cfg.safety_distance, "{inconsistent}");
    println!(
        "closest planned approach: {consistent:.2} m from the same pair of paths, {inconsistent:.2} m from replaced ones (safety distance {} m)",
        cfg.safety_distance
    );

    // The recheck, with the plan each would now hear from the other: neither is flown.
    let flown = |new: &Plan, current: &Plan, other: &str, theirs: &Plan| {
        may_replace(
            new,
            Some(current),
            0.0,
            &[heard(other, theirs, 0.0)],
            &metric,
            cfg.planes_distance(),
            cfg.horizon() / 2.0,
        )
    };
    assert!(!flown(&alfa, &hold(alfa_at), "bravo", &bravo));
    assert!(!flown(&bravo, &hold(bravo_at), "alfa", &alfa));
}

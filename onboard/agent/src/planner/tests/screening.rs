//! The constraint screen (`planner/screen.rs`) changes how fast a plan is found, not which plan:
//! a drone crossing a crowd of hovering neighbours is planned with and without it, from the
//! same states, and the plans agree to within the solver's tolerance.

use super::*;

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

//! The planner and its neighbours: who counts as one, a neighbour that cannot give way, a crowd
//! overhead, a neighbour fallen silent.

use super::*;

#[test]
fn neighbour_sets_are_range_based_and_symmetric() {
    let path = |x: f64, name: &str| NeighbourPath {
        id: id(name),
        positions: vec![Vec3::new(x, 0.0, 10.0); 21],
        dt: 0.1,
        age_s: 0.0,
        avoids: true,
    };
    let all = [
        path(0.0, "a"),
        path(30.0, "b"),
        path(45.0, "c"),
        path(200.0, "d"),
    ];
    let seen_by = |i: usize| -> Vec<String> {
        let me = all[i].positions[0];
        neighbours_in_range(
            me,
            all.iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, n)| n.clone()),
            40.0,
        )
        .into_iter()
        .map(|n| n.id.as_str().to_owned())
        .collect()
    };
    assert_eq!(seen_by(0), ["b"]);
    assert_eq!(seen_by(1), ["a", "c"]);
    assert_eq!(seen_by(2), ["b"]);
    assert!(seen_by(3).is_empty());
    // Symmetric: i sees j iff j sees i.
    for i in 0..4 {
        for j in 0..4 {
            let name = |k: usize| all[k].id.as_str().to_owned();
            assert_eq!(seen_by(i).contains(&name(j)), seen_by(j).contains(&name(i)));
        }
    }
    // Time alignment: a path 1 s old is read one second further along.
    let mut moving = path(0.0, "m");
    moving.positions = (0..=20).map(|i| Vec3::new(i as f64, 0.0, 10.0)).collect();
    moving.age_s = 1.0;
    assert_eq!(moving.position_at(0.0), Some(Vec3::new(10.0, 0.0, 10.0)));
    assert_eq!(moving.position_at(5.0), Some(Vec3::new(20.0, 0.0, 10.0)));
}

/// A neighbour the autopilot flies (it cannot give way) is kept at the whole safety distance:
/// one flies straight through the point where this drone holds, and this drone steps aside.
fn closest_to_a_neighbour_crossing_my_hold_point(avoids: bool) -> f64 {
    let cfg = city_config();
    let mut p = planner(&cfg);
    let hold = Vec3::new(60.0, 60.0, 15.0);
    let goal = Goal::fixed(hold);
    let (mut pos, mut vel) = (hold, Vec3::zeros());
    // It flies north at 3 m/s along x = 60.3, passing my point at t = 5 s.
    let theirs = |t: f64| Vec3::new(60.3, 45.0 + 3.0 * t, 15.0);
    let mut now = 0.0;
    let mut closest = f64::INFINITY;
    for _ in 0..200 {
        let other = NeighbourPath {
            id: id("crossing"),
            positions: (0..=cfg.horizon_steps)
                .map(|k| theirs(now + k as f64 * cfg.dt))
                .collect(),
            dt: cfg.dt,
            age_s: 0.0,
            avoids,
        };
        let r = solve(&mut p, now, pos, vel, &goal, std::slice::from_ref(&other));
        for i in 1..=DENSE {
            let t = now + REPLAN * i as f64 / DENSE as f64;
            closest = closest.min((r.plan.sample(t).position - theirs(t)).norm());
        }
        let s = r.plan.sample(now + REPLAN);
        (pos, vel) = (s.position, s.velocity);
        now += REPLAN;
    }
    closest
}

#[test]
fn a_neighbour_that_cannot_give_way_is_kept_at_the_whole_distance() {
    let closest = closest_to_a_neighbour_crossing_my_hold_point(false);
    let d = city_config().safety_distance;
    assert!(
        closest >= d,
        "came within {closest:.2} m of a drone that cannot give way (safety {d} m)"
    );
}

/// Flies `goal` in closed loop for `seconds` beside neighbours that hold still (and do not give
/// way); returns the lowest altitude of the flown path, densely sampled.
fn lowest_flown(cfg: &PlannerConfig, start: Vec3, goal: Vec3, still: &[Vec3], seconds: f64) -> f64 {
    let mut p = planner(cfg);
    let neighbours: Vec<NeighbourPath> = still
        .iter()
        .enumerate()
        .map(|(i, at)| NeighbourPath {
            id: id(&format!("n{i}")),
            positions: vec![*at; 21],
            dt: 0.1,
            age_s: 0.0,
            avoids: false,
        })
        .collect();
    let (mut pos, mut vel, mut now) = (start, Vec3::zeros(), 0.0);
    let mut lowest = f64::INFINITY;
    let goal = Goal::fixed(goal);
    while now < seconds {
        let r = solve(&mut p, now, pos, vel, &goal, &neighbours);
        for i in 0..=DENSE {
            let t = now + REPLAN * i as f64 / DENSE as f64;
            lowest = lowest.min(r.plan.sample(t).position.z);
        }
        now += REPLAN;
        let s = r.plan.sample(now);
        (pos, vel) = (s.position, s.velocity);
    }
    assert!(pos.z.is_finite());
    lowest
}

#[test]
fn a_crowd_overhead_does_not_press_a_drone_into_the_ground() {
    let cfg = city_config();
    // Four drones just above, all around: the separating planes point straight down. In a
    // 20-drone swap the drones at the bottom of the crowd were pushed to the ground this way.
    let here = Vec3::new(60.0, 60.0, 5.0);
    let crowd: Vec<Vec3> = [(0.5, 0.0), (-0.5, 0.0), (0.0, 0.5), (0.0, -0.5)]
        .iter()
        .map(|(dx, dy)| here + Vec3::new(*dx, *dy, 1.5))
        .collect();
    let lowest = lowest_flown(&cfg, here, here, &crowd, 4.0);
    assert!(
        lowest >= cfg.floor_clearance - 0.01,
        "pressed down to {lowest:.2} m (floor clearance {} m)",
        cfg.floor_clearance
    );
    // A goal below the clearance is flown to on purpose: the floor gives way to it.
    let low = Vec3::new(60.0, 60.0, 1.5);
    let lowest = lowest_flown(&cfg, here, low, &[], 8.0);
    assert!((lowest - low.z).abs() < 0.2, "went down to {lowest:.2} m");
}

/// A neighbour silent for minutes (its onboard died; its writer holds it in the air) is an
/// obstacle of bounded size: a drone passing it keeps the whole safety distance plus margins
/// and the capped stale margin, no more, and is not told that the silent one gives way.
#[test]
fn a_long_silent_neighbour_is_kept_with_a_bounded_margin_and_without_giving_way() {
    let cfg = city_config();
    let hover = Vec3::new(60.0, 60.0, 15.0);
    let silent = NeighbourPath {
        id: id("silent"),
        positions: vec![hover; 21],
        dt: 0.1,
        age_s: 600.0,
        avoids: true,
    };
    // The room this drone must keep: all of the safety distance (the silent one cannot give
    // way), the margin, and the stale margin at its cap.
    let keep = cfg.safety_distance + cfg.separation_margin + cfg.max_stale_margin;
    let mut p = planner(&cfg);
    // The straight line passes 2 m from it: the drone must go round.
    let mut pos = Vec3::new(58.0, 45.0, 15.0);
    let mut vel = Vec3::zeros();
    let goal = Goal::fixed(Vec3::new(58.0, 75.0, 15.0));
    let mut closest = f64::INFINITY;
    let mut now = 0.0;
    for _ in 0..400 {
        let r = solve(&mut p, now, pos, vel, &goal, std::slice::from_ref(&silent));
        let next = r.plan.sample(now + REPLAN);
        pos = next.position;
        vel = next.velocity;
        now += REPLAN;
        let d = pos - hover;
        closest = closest.min((d.x * d.x + d.y * d.y).sqrt());
    }
    assert!(
        (pos - goal.position).norm() < 1.0,
        "passed by to its goal: {pos:?}"
    );
    assert!(
        closest > keep - 0.3,
        "kept {closest:.2} m from the silent neighbour, less than {keep:.2}"
    );
    assert!(
        closest < keep + 1.5,
        "kept {closest:.2} m: the stale margin is not bounded at {}",
        cfg.max_stale_margin
    );
}

#[test]
fn a_wider_margin_keeps_the_plan_further_from_a_neighbour() {
    // A drone heading for a point beside a neighbour that stands (cannot give way): the plan
    // stops where the half-spaces allow, the margin further away when it is wider. A margin
    // below the configured one, or not finite, is the configured one.
    let cfg = city_config();
    let here = Vec3::new(60.0, 60.0, 10.0);
    let neighbour = NeighbourPath {
        id: id("n"),
        positions: vec![here + Vec3::new(6.0, 0.0, 0.0); 21],
        dt: 0.1,
        age_s: 0.0,
        avoids: false,
    };
    let closest = |margin: f64| {
        let mut p = planner(&cfg);
        p.set_separation_margin(margin);
        let goal = Goal::fixed(neighbour.positions[0]);
        let (mut pos, mut vel, mut now) = (here, Vec3::zeros(), 0.0);
        for _ in 0..100 {
            let r = solve(
                &mut p,
                now,
                pos,
                vel,
                &goal,
                std::slice::from_ref(&neighbour),
            );
            now += 0.05;
            let s = r.plan.sample(now);
            (pos, vel) = (s.position, s.velocity);
        }
        (pos - neighbour.positions[0]).norm()
    };
    let configured = closest(cfg.separation_margin);
    let wider = closest(cfg.separation_margin + 0.5);
    assert!(
        (wider - configured - 0.5).abs() < 0.1,
        "stopped {configured:.2} m away, {wider:.2} m with a margin 0.5 m wider"
    );
    assert!((closest(0.0) - configured).abs() < 1e-9);
    assert!((closest(f64::NAN) - configured).abs() < 1e-9);
}

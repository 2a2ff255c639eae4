use super::*;
use tacos_shared::messages::TargetObservation;
use tacos_shared::scenario::Scenario;

fn id(name: &str) -> DroneId {
    match DroneId::new(name) {
        Ok(id) => id,
        Err(e) => panic!("{name}: {e}"),
    }
}

fn motion(me: &str) -> Motion {
    let city = match Scenario::builtin("city") {
        Ok(s) => s,
        Err(e) => panic!("built-in city: {e}"),
    };
    let planner = PlannerConfig::from_scenario(&city.limits, &city.world);
    match Motion::new(id(me), planner, MotionConfig::default()) {
        Ok(m) => m,
        Err(e) => panic!("valid planner config: {e}"),
    }
}

fn path(drone: &str, stamp: f64, at: Vec3, tracking: Option<&str>) -> PathMessage {
    PathMessage {
        drone: id(drone),
        stamp,
        dt: 0.1,
        positions: vec![at; 21],
        tracking: tracking.map(str::to_owned),
        avoids: true,
        airborne: true,
    }
}

fn targets(name: &str, position: Vec3, velocity: Vec3) -> TargetsMessage {
    TargetsMessage {
        stamp: 0.0,
        targets: vec![TargetObservation {
            name: name.into(),
            position,
            velocity,
        }],
    }
}

#[test]
fn keeps_the_newest_path_per_neighbour_ignores_its_own_and_forgets_the_silent() {
    let mut m = motion("alfa");
    let p = Vec3::new(10.0, 0.0, 10.0);
    m.on_path(path("alfa", 100.0, p, None));
    m.on_path(path("bravo", 100.0, p, None));
    m.on_path(path("bravo", 99.0, Vec3::new(50.0, 0.0, 10.0), None));
    m.on_path(path("charlie", f64::NAN, p, None));
    let seen: Vec<NeighbourPath> = m.neighbours(100.5).collect();
    assert_eq!(seen.len(), 1, "{seen:?}");
    assert_eq!(seen[0].id, id("bravo"));
    assert_eq!(
        seen[0].positions[0], p,
        "the older path did not replace the newer"
    );
    assert!((seen[0].age_s - 0.5).abs() < 1e-9);
    // Silent for 11 s: one last seen on the ground is forgotten, one last seen airborne (its
    // onboard died, its writer holds it in the air) is not, until a path says it landed.
    assert_eq!(m.neighbours(111.0).count(), 1, "bravo was airborne");
    let mut landed = path("bravo", 101.0, Vec3::new(10.0, 0.0, 0.0), None);
    landed.airborne = false;
    landed.avoids = false;
    m.on_path(landed);
    assert_eq!(
        m.neighbours(105.0).count(),
        1,
        "a landed drone is still there a while"
    );
    assert_eq!(
        m.neighbours(112.0).count(),
        0,
        "landed and silent for 11 s: forgotten"
    );
    let mut dead = motion("alfa");
    dead.on_path(path("delta", 100.0, p, None));
    let kept: Vec<NeighbourPath> = dead.neighbours(1000.0).collect();
    assert_eq!(
        kept.len(),
        1,
        "an airborne neighbour silent for 15 min is kept"
    );
    assert_eq!(
        kept[0].position_at(0.0),
        Some(p),
        "at the end of its last path"
    );
}

/// The silence of the peers is counted from the newest path of the neighbours still known,
/// once there are two or more of them.
#[test]
fn peers_silence_runs_from_the_newest_known_path() {
    let mut m = motion("alfa");
    let p = Vec3::new(10.0, 0.0, 10.0);
    assert_eq!(m.peers_silence(100.0), None, "no neighbour known");
    m.on_path(path("alfa", 100.0, p, None));
    m.on_path(path("bravo", 100.0, p, None));
    assert_eq!(
        m.peers_silence(105.0),
        None,
        "one neighbour's silence is its own failure as much as this drone's link"
    );
    m.on_path(path("charlie", 102.0, p, None));
    assert_eq!(m.peers_silence(101.0), Some(0.0));
    assert_eq!(
        m.peers_silence(105.5),
        Some(3.5),
        "from charlie's, the newest"
    );
    // Airborne neighbours are never forgotten, and their silence keeps growing; those last
    // seen on the ground are forgotten after a while, and then there is none to be silent.
    assert_eq!(m.peers_silence(1000.0), Some(898.0));
    let mut landed = motion("alfa");
    for drone in ["delta", "echo"] {
        let mut on_the_ground = path(drone, 100.0, p, None);
        on_the_ground.airborne = false;
        landed.on_path(on_the_ground);
    }
    assert_eq!(landed.peers_silence(105.0), Some(5.0));
    assert_eq!(landed.peers_silence(111.0), None, "forgotten: none known");
}

/// Time this process spent stalled is not the peers' silence.
#[test]
fn a_stall_is_left_out_of_the_peers_silence() {
    let mut m = motion("alfa");
    let p = Vec3::new(10.0, 0.0, 10.0);
    m.on_path(path("bravo", 100.0, p, None));
    m.on_path(path("charlie", 101.0, p, None));
    m.excuse_peers(12.0, 113.0);
    assert_eq!(
        m.peers_silence(114.0),
        Some(1.0),
        "13 s since charlie, 12 of them deaf"
    );
    m.excuse_peers(f64::NAN, 114.0);
    m.excuse_peers(-3.0, 114.0);
    assert_eq!(m.peers_silence(114.0), Some(1.0), "nothing to excuse");
    m.on_path(path("bravo", 113.5, p, None));
    assert_eq!(
        m.peers_silence(114.0),
        Some(0.5),
        "a newer path: counted from it alone"
    );
}

/// Seen in CI (`onboard_stall`): a 5 s stall, then the first path taken in was one a neighbour
/// published 1 s into the stall (queued while this process was stopped). That path is newer
/// than any held, but the stall after its stamp is still not silence: the drone must not hold.
#[test]
fn a_path_published_during_the_stall_leaves_the_rest_of_it_excused() {
    let mut m = motion("alfa");
    let p = Vec3::new(10.0, 0.0, 10.0);
    m.on_path(path("bravo", 100.0, p, None));
    m.on_path(path("charlie", 100.1, p, None));
    // Stopped from 100.2 to 105.2; the stall is seen at the first tick after it.
    m.excuse_peers(5.0, 105.2);
    m.on_path(path("bravo", 101.2, p, None));
    let silence = m.peers_silence(105.3).expect("two neighbours known");
    assert!(
        (silence - 0.1).abs() < 1e-9,
        "{silence}: only the 0.1 s after the stall"
    );
    // Without newer paths the silence grows from the stall's end.
    let silence = m.peers_silence(108.2).expect("two neighbours known");
    assert!((silence - 3.0).abs() < 1e-9, "{silence}");
    // A path from after the stall: counted from it, the stall forgotten.
    m.on_path(path("charlie", 105.4, p, None));
    assert_eq!(
        m.peers_silence(105.5).map(|s| (s * 1e9).round() / 1e9),
        Some(0.1)
    );
}

#[test]
fn stations_are_unseen_then_ahead_of_the_target_then_lost() {
    let mut m = motion("alfa");
    assert_eq!(m.station("van", 12.0, 0.0), Station::Unseen);
    let v = Vec3::new(2.0, 0.0, 0.0);
    m.on_targets(&targets("van", Vec3::new(0.0, 0.0, 0.0), v), 0.0);
    match m.station("van", 12.0, 1.0) {
        Station::At(goal) => {
            // Alone: on the circle of the configured radius, at the altitude, moving with it.
            let centre = Vec3::new(2.0, 0.0, 12.0);
            assert!(
                ((goal.position - centre).norm() - 6.0).abs() < 0.2,
                "{goal:?}"
            );
            assert!((goal.velocity - v).norm() < 1e-6);
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(m.station("van", 12.0, 3.5), Station::Lost);
}

#[test]
fn trackers_of_one_target_take_places_the_safety_distance_apart() {
    let names = ["alfa", "bravo", "charlie", "delta", "echo", "foxtrot"];
    let now = 50.0;
    let target = Vec3::new(10.0, 10.0, 0.0);
    let places: Vec<Vec3> = names
        .iter()
        .map(|me| {
            let mut m = motion(me);
            m.on_targets(&targets("van", target, Vec3::zeros()), now);
            for other in names.iter().filter(|o| *o != me) {
                m.on_path(path(other, now - 0.1, target, Some("van")));
            }
            // A drone tracking something else does not take a place.
            m.on_path(path("golf", now - 0.1, target, Some("suspect")));
            match m.station("van", 15.0, now) {
                Station::At(goal) => goal.position,
                other => panic!("{other:?}"),
            }
        })
        .collect();
    let safety = m_safety();
    for (i, a) in places.iter().enumerate() {
        for b in &places[i + 1..] {
            assert!((a - b).norm() >= safety, "{a:?} and {b:?}");
        }
    }
}

fn m_safety() -> f64 {
    motion("alfa").planner_config().safety_distance
}

#[test]
fn standing_drones_publish_that_they_cannot_give_way_flying_ones_their_plan() {
    let mut m = motion("alfa");
    let p = Vec3::new(-50.0, -132.5, 0.0);
    let climbing = Vec3::new(0.0, 0.0, 1.0);
    let out = m.step(100.0, p, climbing, Steering::Still(p), None);
    assert_eq!(out.reference, ReferenceState::still(p));
    let path = out.path.expect("a path on the first tick");
    assert!(!path.avoids);
    assert!(
        !path.airborne,
        "on the ground until the executor says otherwise"
    );
    assert!((path.positions[20] - (p + climbing * 2.0)).norm() < 1e-9);
    // Not due again within the period.
    assert!(
        m.step(100.01, p, climbing, Steering::Still(p), None)
            .path
            .is_none()
    );

    m.set_airborne(true);
    let air = Vec3::new(-50.0, -100.0, 10.0);
    let goal = Goal::fixed(Vec3::new(-50.0, -80.0, 10.0));
    let out = m.step(
        101.0,
        air,
        Vec3::zeros(),
        Steering::Toward(goal),
        Some("van"),
    );
    let path = out.path.expect("a fresh plan is published");
    assert!(path.avoids && path.airborne);
    assert_eq!(path.tracking.as_deref(), Some("van"));
    assert_eq!(path.positions.len(), 21);
    assert!(path.positions[20].y > air.y, "heads for the goal");
    // Between solves the same plan is sampled: the reference moves on along it.
    let later = m.step(
        101.02,
        air,
        Vec3::zeros(),
        Steering::Toward(goal),
        Some("van"),
    );
    assert!(later.path.is_none());
    assert!(later.reference.position.y >= out.reference.position.y);
    assert!(
        m.step(101.05, air, Vec3::zeros(), Steering::Toward(goal), None)
            .path
            .is_some()
    );
    assert!(m.stats().solves >= 2);
}

/// The whole chain without processes: noisy observations of a target at constant velocity, the
/// tracker, the station, the planner, and a drone that follows its reference exactly. The
/// distance to the station settles below a bound.
#[test]
fn a_target_at_constant_velocity_is_followed_with_a_settling_error() {
    let mut m = motion("alfa");
    let velocity = Vec3::new(2.5, 1.0, 0.0);
    let truth = |t: f64| Vec3::new(-60.0, -80.0, 0.0) + velocity * t;
    let noise = |k: usize| ((k as f64 * 12.9898).sin() * 43758.5453).rem_euclid(1.0) - 0.5;
    let (mut pos, mut vel) = (Vec3::new(-70.0, -100.0, 12.0), Vec3::zeros());
    let dt = 0.02;
    let mut errors = Vec::new();
    for k in 0..2000 {
        let t = k as f64 * dt;
        if k % 5 == 0 {
            let observed = truth(t) + Vec3::new(noise(k), noise(k + 1), 0.0) * 0.6;
            m.on_targets(&targets("van", observed, velocity), t);
        }
        let Station::At(goal) = m.station("van", 12.0, t) else {
            panic!("observed at 10 Hz, never lost")
        };
        m.step(t, pos, vel, Steering::Toward(goal), Some("van"));
        // The drone flies its plan exactly until the next tick.
        let Some(next) = m.plan.as_ref().map(|p| p.sample(t + dt)) else {
            panic!("a plan while steering toward a goal")
        };
        (pos, vel) = (next.position, next.velocity);
        // Where it should be: the true target plus the same offset.
        let (estimate, _) = match m.tracks.get("van") {
            Some(track) => track.predict(t),
            None => panic!("tracked"),
        };
        let offset = goal.position - Vec3::new(estimate.x, estimate.y, 12.0);
        let wanted = truth(t) + offset + Vec3::new(0.0, 0.0, 12.0);
        errors.push((pos - wanted).norm());
    }
    let early = errors[0];
    let late = errors[1500..].iter().cloned().fold(0.0, f64::max);
    assert!(early > 10.0, "starts far off: {early}");
    assert!(late < 1.0, "settled error {late:.2} m");
}

/// A vehicle that lags its plan (PX4 on a slow climb) is replanned from the plan it is flying,
/// so the lag does not eat the plan; one pushed off it is replanned from where it is.
#[test]
fn solves_start_from_the_plan_being_flown_while_the_vehicle_follows_it() {
    let mut m = motion("alfa");
    let p = Vec3::new(-50.0, -132.5, 10.0);
    let goal = Goal::fixed(p + Vec3::new(0.0, 0.0, 5.0));
    m.step(100.0, p, Vec3::zeros(), Steering::Toward(goal), None);
    let planned = m
        .tick(100.5, p, Vec3::zeros(), Steering::Toward(goal))
        .reference;
    assert!(
        planned.position.z > p.z + 0.01,
        "the plan climbs: {planned:?}"
    );
    // Lagging 0.1 m behind, still: the solve starts on the plan, at its speed.
    let lagging = planned.position - Vec3::new(0.0, 0.0, 0.1);
    let job = m
        .solve_job(100.5, lagging, Vec3::zeros(), goal, None)
        .expect("a solve");
    assert_eq!(
        (job.position, job.velocity),
        (planned.position, planned.velocity)
    );
    m.solve_done(job.run(), 100.5);
    // A metre off the plan: from the vehicle's own state.
    let off = p + Vec3::new(1.0, 0.0, 0.0);
    let v = Vec3::new(0.3, 0.0, 0.0);
    let job = m.solve_job(100.6, off, v, goal, None).expect("a solve");
    assert_eq!((job.position, job.velocity), (off, v));
}

/// A solve that finishes after a neighbour published a path it would run into is not flown:
/// the drone keeps the plan it flies (which that neighbour planned against) and solves again.
#[test]
fn a_finished_plan_that_runs_into_a_path_published_meanwhile_is_not_flown() {
    let mut m = motion("alfa");
    m.set_airborne(true);
    let p = Vec3::new(-50.0, -132.5, 10.0);
    let east = Goal::fixed(p + Vec3::new(40.0, 0.0, 0.0));
    let north = Goal::fixed(p + Vec3::new(0.0, 40.0, 0.0));
    assert!(
        m.step(100.0, p, Vec3::zeros(), Steering::Toward(east), None)
            .path
            .is_some()
    );
    let flown = m
        .tick(100.05, p, Vec3::zeros(), Steering::Toward(east))
        .reference;
    // A solve towards the north starts; while it runs, bravo publishes that it stands where
    // the new plan will be in a second.
    let job = m
        .solve_job(100.05, flown.position, flown.velocity, north, None)
        .expect("a solve");
    let done = job.run();
    let mut probe = motion("probe");
    probe.set_airborne(true);
    let ahead = {
        let job = probe
            .solve_job(100.05, flown.position, flown.velocity, north, None)
            .expect("a solve");
        let path = probe.solve_done(job.run(), 100.05).expect("a path");
        path.positions[10]
    };
    m.on_path(path("bravo", 100.06, ahead, None));
    assert_eq!(m.solve_done(done, 100.07), None, "not published");
    assert_eq!(m.stats().rejected, 1);
    // Still flying the eastward plan.
    let now = m
        .tick(100.1, p, Vec3::zeros(), Steering::Toward(north))
        .reference;
    let east_plan = m
        .tick(100.1, p, Vec3::zeros(), Steering::Toward(east))
        .reference;
    assert_eq!(now, east_plan);
    assert!(
        now.velocity.x > 0.0 && now.velocity.y.abs() < 1e-6,
        "{now:?}"
    );
    // The next solve knows bravo's path and keeps away from it (the refused plan went through
    // it): flown.
    let job = m
        .solve_job(100.1, now.position, now.velocity, north, None)
        .expect("a solve");
    let path = m
        .solve_done(job.run(), 100.12)
        .expect("flown and published");
    let closest = path
        .positions
        .iter()
        .map(|q| (q - ahead).norm())
        .fold(f64::INFINITY, f64::min);
    assert!(closest >= m_safety() / 2.0, "{closest}");
    assert_eq!(m.stats().rejected, 1);
}

/// A vehicle seen straying from its plan widens the separation margin of the next solves, up to
/// a third of the safety distance, and the widening fades as it follows again.
#[test]
fn straying_from_the_plan_widens_the_margin_of_the_next_solves() {
    let mut m = motion("alfa");
    let cfg = m.planner_config().clone();
    let p = Vec3::new(-50.0, -132.5, 10.0);
    let goal = Goal::fixed(p + Vec3::new(5.0, 0.0, 0.0));
    m.step(100.0, p, Vec3::zeros(), Steering::Toward(goal), None);
    assert_eq!(m.stats().widest_margin_m, cfg.separation_margin);
    // 0.9 m beside the plan (the configured margin is 0.5 m in the city), then 5 m: the
    // margin follows, then stops at a third of the safety distance (1 m).
    for (off, widest) in [(0.9, 0.9), (5.0, cfg.safety_distance / 3.0)] {
        let planned = m
            .tick(100.1, p, Vec3::zeros(), Steering::Toward(goal))
            .reference;
        let beside = planned.position + Vec3::new(0.0, off, 0.0);
        m.tick(100.1, beside, Vec3::zeros(), Steering::Toward(goal));
        let job = m
            .solve_job(100.1, beside, Vec3::zeros(), goal, None)
            .expect("a solve");
        m.solve_done(job.run(), 100.1);
        assert!(
            (m.stats().widest_margin_m - widest).abs() < 1e-6,
            "{off} m off: {:?}",
            m.stats()
        );
    }
    // Twenty seconds (four half-lives) of following later, the 5 m peak is a sixteenth of it,
    // below the configured margin again.
    assert!((m.tracking_error.value(120.1) - 5.0 / 16.0).abs() < 1e-9);
    assert!(5.0 / 16.0 < cfg.separation_margin);
}

//! End-to-end tests of the onboard planner and tracker: real tacos-onboard, tacos-px4 and
//! tacos-sitl processes on loopback, the drones exchanging their paths over zenoh. Every check
//! is made in the simulator's ground truth.

use std::time::Duration;
use tacos_ground::direct::run_actions;
use tacos_ground::patterns::fly_swap;
use tacos_ground::safety::SafetyGate;
use tacos_shared::action::Action;
use tacos_shared::messages::SimTruth;
use tacos_shared::{DroneId, Vec3};
use tacos_tests::{SimSwarm, all_ready, id, truth_until, vehicle, within};

const STEP: Duration = Duration::from_secs(90);

fn breaches(truth: &SimTruth) -> (u64, u64) {
    (truth.separation_breaches, truth.obstacle_breaches)
}

/// The paper's stress case for a distributed planner: 20 drones on a circle round the business
/// district swap to the antipodal points, all through the four skyscrapers at once.
///
/// The simulation runs at half speed (every process follows its clock, see `--sim-speed`):
/// each drone has a companion computer of its own, but here 20 onboards share two cores, and
/// at real time their planners starved each other where all 20 cross (4–10 solves per second
/// instead of 20, the slowest 400 ms; one CI run cut 0.24 m into a skyscraper's margin). At
/// half speed every drone makes 16–20 solves per simulated second there.
///
/// Once flaky (issue 18 item 7), so nextest still retries it once (`.config/nextest.toml`): 1 run
/// in 4 ended with a pair inside the safety distance. The cause was solves reading different
/// pairs of paths (`planner/tests/stale_reads.rs`), now refused by the onboard's recheck of a
/// finished plan (`planner/recheck.rs`), and a drone flown past the end of a plan it kept too
/// long, now bounded there too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn twenty_drones_swap_through_the_skyscrapers_without_a_breach() -> anyhow::Result<()> {
    let sim = SimSwarm::start_with("swap", "city", 20, |c| c.sim_speed = 0.5).await?;
    let ids = sim.stack.config.drone_ids();
    let truth = sim.link.watch_truth().await?;
    let gate = SafetyGate::new(sim.scenario.clone());
    let flown = within(
        "the 20-drone swap",
        Duration::from_secs(600),
        fly_swap(&sim.link, &gate, &ids, truth.clone(), true),
    )
    .await;
    let last = truth.borrow().clone();
    sim.stop().await;
    // fly_swap checks every phase in the truth, and fails on any breach; the counters are
    // checked here again so the test says what it saw.
    flown??;
    let last = last.ok_or_else(|| anyhow::anyhow!("no truth from the simulator"))?;
    assert_eq!(breaches(&last), (0, 0), "breaches in {last:?}");
    assert!(last.min_pair_distance >= sim_safety(), "{last:?}");
    assert!(last.min_obstacle_clearance > 0.0, "{last:?}");
    Ok(())
}

fn sim_safety() -> f64 {
    tacos_shared::scenario::Scenario::builtin("city")
        .map(|s| s.limits.safety_distance)
        .unwrap_or(f64::INFINITY)
}

/// Distance from `p` to the segment `a`–`b`, in the horizontal plane.
fn off_line(p: Vec3, a: Vec3, b: Vec3) -> f64 {
    let (p, a, b) = (p.xy(), a.xy(), b.xy());
    let ab = b - a;
    let t = ((p - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0);
    (p - (a + ab * t)).norm()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_goto_whose_straight_line_crosses_skyscrapers_goes_round_them() -> anyhow::Result<()> {
    let sim = SimSwarm::start("detour", "city", 1).await?;
    let alfa = id("alfa");
    let gate = SafetyGate::new(sim.scenario.clone());
    let mut truth = sim.link.watch_truth().await?;
    all_ready(&sim, std::slice::from_ref(&alfa)).await?;
    let go = |action: Action| vec![(alfa.clone(), action)];
    run_actions(&sim.link, &gate, &go(Action::ArmTakeoff), None, STEP).await?;
    let a = Vec3::new(-40.0, -40.0, 12.0);
    let b = Vec3::new(40.0, 40.0, 12.0);
    // The straight line from a to b runs through the centres of skyscraper_1 and skyscraper_4.
    let world = &sim.scenario.world;
    assert!(world.segment_blocked_by(&a, &b, 0.5).is_some());
    run_actions(
        &sim.link,
        &gate,
        &go(Action::Goto { target: a }),
        None,
        STEP,
    )
    .await?;

    // Record how far from the straight line the vehicle flies on its way to b.
    let widest = std::sync::Arc::new(std::sync::Mutex::new(0.0_f64));
    let watcher = {
        let mut truth = truth.clone();
        let widest = widest.clone();
        let alfa = alfa.clone();
        tokio::spawn(async move {
            while truth.changed().await.is_ok() {
                let p = truth
                    .borrow()
                    .as_ref()
                    .and_then(|t| vehicle(t, &alfa).map(|v| v.position));
                if let (Some(p), Ok(mut w)) = (p, widest.lock()) {
                    *w = w.max(off_line(p, a, b));
                }
            }
        })
    };
    let flown = run_actions(
        &sim.link,
        &gate,
        &go(Action::Goto { target: b }),
        None,
        STEP,
    )
    .await;
    watcher.abort();
    let arrived = truth_until(&mut truth, Duration::from_secs(10), "alfa at b", |t| {
        vehicle(t, &alfa).is_some_and(|v| (v.position - b).norm() < 1.5)
    })
    .await;
    let widest = widest.lock().map(|w| *w).unwrap_or(0.0);
    sim.stop().await;
    flown?;
    let last = arrived?;
    assert_eq!(breaches(&last), (0, 0), "{last:?}");
    // Round a skyscraper of semi-axis 8 m plus the drone's radius and margin.
    assert!(
        widest > 8.5,
        "the vehicle stayed within {widest:.1} m of the straight line"
    );
    Ok(())
}

/// City plus a rover driving at constant velocity, published on `world/targets`.
fn city_with_rover(velocity: Vec3) -> anyhow::Result<std::path::PathBuf> {
    let city = include_str!("../../shared/scenarios/city.toml");
    let rover = format!(
        "\n[[targets]]\nname = \"rover\"\nkind = \"vehicle\"\nstart = [-60.0, -90.0, 0.0]\nmotion = {{ type = \"constant_velocity\", velocity = [{}, {}, 0.0] }}\n",
        velocity.x, velocity.y
    );
    let path = std::env::temp_dir().join(format!(
        "tacos-rover-{}-{}.toml",
        std::process::id(),
        tacos_tests::unique_swarm("r")
    ));
    std::fs::write(&path, format!("{city}{rover}"))?;
    Ok(path)
}

/// Two drones follow a target moving at constant velocity: each settles at its own place on a
/// circle round it, and stays there with a small error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_target_at_constant_velocity_is_followed_with_a_settling_error() -> anyhow::Result<()> {
    let velocity = Vec3::new(1.5, 0.5, 0.0);
    let file = city_with_rover(velocity)?;
    let scenario_arg = file.display().to_string();
    let sim = SimSwarm::start("rover", &scenario_arg, 2).await?;
    let ids: Vec<DroneId> = sim.stack.config.drone_ids();
    let gate = SafetyGate::new(sim.scenario.clone());
    let truth = sim.link.watch_truth().await?;
    let targets = sim.link.watch_targets().await?;
    all_ready(&sim, &ids).await?;
    let all = |action: Action| -> Vec<(DroneId, Action)> {
        ids.iter().map(|d| (d.clone(), action.clone())).collect()
    };
    let result = async {
        run_actions(&sim.link, &gate, &all(Action::ArmTakeoff), None, STEP).await?;
        let follow = Action::StartTracking {
            target: "rover".into(),
        };
        // Done once each drone has reached its place round the rover.
        run_actions(&sim.link, &gate, &all(follow), None, STEP).await?;
        // Then watch for 15 s: distance to the rover (horizontal) against the circle's radius,
        // and the two drones apart.
        let mut samples = Vec::new();
        let end = tokio::time::Instant::now() + Duration::from_secs(15);
        let mut truth = truth.clone();
        while tokio::time::Instant::now() < end {
            within("truth", Duration::from_secs(2), truth.changed()).await??;
            let rover = targets.borrow().iter().find(|t| t.name == "rover").cloned();
            let Some(t) = truth.borrow().clone() else {
                continue;
            };
            let Some(rover) = rover else { continue };
            let places: Vec<Vec3> = ids
                .iter()
                .filter_map(|d| vehicle(&t, d).map(|v| v.position))
                .collect();
            if places.len() == 2 {
                let radii: Vec<f64> = places
                    .iter()
                    .map(|p| (p.xy() - rover.position.xy()).norm())
                    .collect();
                samples.push((radii, (places[0] - places[1]).norm(), t.clone()));
            }
        }
        anyhow::Ok(samples)
    }
    .await;
    sim.stop().await;
    let _ = std::fs::remove_file(&file);
    let samples = result?;
    assert!(samples.len() > 50, "{} samples", samples.len());
    // The circle's radius is 6 m; the error is how far each drone is off it.
    let worst = samples
        .iter()
        .flat_map(|(radii, _, _)| radii.iter().map(|r| (r - 6.0).abs()))
        .fold(0.0, f64::max);
    assert!(worst < 2.0, "tracking error up to {worst:.2} m");
    let closest = samples.iter().map(|s| s.1).fold(f64::INFINITY, f64::min);
    assert!(closest > 6.0, "the two trackers came within {closest:.1} m");
    let (_, _, last) = &samples[samples.len() - 1];
    assert_eq!(breaches(last), (0, 0), "{last:?}");
    Ok(())
}

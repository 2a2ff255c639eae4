//! End-to-end: tacos-sitl, three tacos-px4 + tacos-onboard pairs and a ground link, all real
//! processes on loopback with unique ports and keys. Every check is made in the simulator's
//! ground truth or in what the ground sees; every wait has a deadline.

use std::time::{Duration, Instant};
use tacos_ground::direct::run_actions;
use tacos_ground::launch::Role;
use tacos_ground::link::GroundLink;
use tacos_ground::safety::SafetyGate;
use tacos_ground::swarm::SwarmChange;
use tacos_shared::action::Action;
use tacos_shared::px4_mode::Px4Mode;
use tacos_shared::{DroneId, DroneMode, Vec3};
use tacos_tests::{SimSwarm, all_ready, id, truth_until, vehicle, within};

const STEP: Duration = Duration::from_secs(60);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_drones_take_off_fly_to_points_and_land() -> anyhow::Result<()> {
    let sim = SimSwarm::start("e2efly", "city", 3).await?;
    let result = fly_pattern(&sim).await;
    sim.stop().await;
    result
}

async fn fly_pattern(sim: &SimSwarm) -> anyhow::Result<()> {
    let ids = [id("alfa"), id("bravo"), id("charlie")];
    let gate = SafetyGate::new(sim.scenario.clone());
    let mut truth = sim.link.watch_truth().await?;
    all_ready(sim, &ids).await?;
    let alt = sim.scenario.limits.takeoff_altitude;

    act_all(
        &sim.link,
        &gate,
        ids.iter()
            .map(|d| (d.clone(), Action::ArmTakeoff))
            .collect(),
    )
    .await?;
    truth_until(
        &mut truth,
        Duration::from_secs(10),
        "all three airborne at take-off altitude",
        |t| {
            ids.iter()
                .all(|d| vehicle(t, d).is_some_and(|v| v.armed && v.position.z > 0.8 * alt))
        },
    )
    .await?;

    // A malformed payload on alfa's action key: counted, logged, and alfa keeps working.
    sim.link
        .session()
        .put(sim.link.keys().action(&ids[0]), vec![1u8, 0xff, 0xfe, 0x00])
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    within(
        "alfa to count the malformed action",
        Duration::from_secs(5),
        async {
            let mut changes = sim.link.changes();
            loop {
                let counted = sim
                    .link
                    .view()
                    .get(&ids[0])
                    .and_then(|e| e.status.as_ref())
                    .is_some_and(|s| s.malformed_actions == 1);
                if counted {
                    break;
                }
                let _ = changes.recv().await;
            }
        },
    )
    .await?;

    let goals: Vec<Vec3> = ids
        .iter()
        .map(|d| {
            let home = sim.scenario.drone(d).map(|s| s.home).unwrap_or_default();
            home + Vec3::new(0.0, 30.0, alt + 2.0)
        })
        .collect();
    act_all(
        &sim.link,
        &gate,
        ids.iter()
            .cloned()
            .zip(goals.iter().map(|g| Action::Goto { target: *g }))
            .collect(),
    )
    .await?;
    truth_until(
        &mut truth,
        Duration::from_secs(10),
        "each vehicle at its goto point",
        |t| {
            ids.iter()
                .zip(&goals)
                .all(|(d, g)| vehicle(t, d).is_some_and(|v| (v.position - g).norm() < 1.5))
        },
    )
    .await?;

    act_all(
        &sim.link,
        &gate,
        ids.iter().map(|d| (d.clone(), Action::Land)).collect(),
    )
    .await?;
    let last = truth_until(
        &mut truth,
        Duration::from_secs(10),
        "all landed and disarmed",
        |t| {
            ids.iter()
                .all(|d| vehicle(t, d).is_some_and(|v| v.landed && !v.armed))
        },
    )
    .await?;
    assert_eq!(last.separation_breaches, 0, "separation breach in truth");
    assert_eq!(last.obstacle_breaches, 0, "obstacle breach in truth");
    Ok(())
}

/// Sends one action per drone at once (through the gate), then waits until every one is done.
/// The vehicle in the simulator's next truth update.
async fn next_state_of(
    truth: &mut tokio::sync::watch::Receiver<Option<tacos_shared::messages::SimTruth>>,
    drone: &DroneId,
) -> anyhow::Result<tacos_shared::messages::VehicleTruth> {
    within("a truth update", Duration::from_secs(2), truth.changed()).await??;
    truth
        .borrow()
        .as_ref()
        .and_then(|t| vehicle(t, drone).cloned())
        .ok_or_else(|| anyhow::anyhow!("{drone} missing from truth"))
}

async fn act_all(
    link: &GroundLink,
    gate: &SafetyGate,
    actions: Vec<(DroneId, Action)>,
) -> anyhow::Result<()> {
    Ok(run_actions(link, gate, &actions, None, STEP).await?)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn crashed_processes_are_seen_the_vehicles_fail_safe_and_restarts_take_over()
-> anyhow::Result<()> {
    let mut sim = SimSwarm::start("e2ecrash", "city", 3).await?;
    let result = crash_onboard_and_writer(&mut sim).await;
    sim.stop().await;
    result
}

async fn crash_onboard_and_writer(sim: &mut SimSwarm) -> anyhow::Result<()> {
    let (alfa, bravo) = (id("alfa"), id("bravo"));
    let gate = SafetyGate::new(sim.scenario.clone());
    let mut truth = sim.link.watch_truth().await?;
    all_ready(sim, &[alfa.clone(), bravo.clone()]).await?;
    act_all(
        &sim.link,
        &gate,
        vec![
            (alfa.clone(), Action::ArmTakeoff),
            (bravo.clone(), Action::ArmTakeoff),
        ],
    )
    .await?;

    // Alfa mid-flight: send it on a long goto and kill its onboard process once it moves.
    let home = sim
        .scenario
        .drone(&alfa)
        .map(|s| s.home)
        .unwrap_or_default();
    let far = home + Vec3::new(0.0, 60.0, sim.scenario.limits.takeoff_altitude);
    let checked = {
        let view = sim.link.view();
        gate.check(&view, "alfa", &Action::Goto { target: far }, Instant::now())
    }
    .map_err(|r| anyhow::anyhow!("{r}"))?;
    sim.link.send(&checked, None).await?;
    truth_until(
        &mut truth,
        Duration::from_secs(15),
        "alfa moving north",
        |t| vehicle(t, &alfa).is_some_and(|v| v.velocity.y > 2.0),
    )
    .await?;

    let mut changes = sim.link.changes();
    let killed_at = Instant::now();
    let exit = sim.stack.crash(Role::Onboard, Some(&alfa)).await;
    anyhow::ensure!(exit.is_some(), "alfa's onboard process was not running");
    within(
        "the ground to see alfa gone",
        Duration::from_secs(1),
        async {
            loop {
                match changes.recv().await {
                    Ok(SwarmChange::Left(d)) if d == alfa => break,
                    Ok(_) => {}
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                    Err(e) => panic!("change stream ended: {e}"),
                }
            }
        },
    )
    .await?;
    let seen_gone_after = killed_at.elapsed();
    println!(
        "ground saw alfa gone {} ms after the kill",
        seen_gone_after.as_millis()
    );

    // The writer keeps streaming a hold at the last setpoint: alfa stays in offboard and stops.
    let after = Instant::now();
    let mut last = None;
    while after.elapsed() < Duration::from_secs(3) {
        let v = next_state_of(&mut truth, &alfa).await?;
        anyhow::ensure!(
            Px4Mode::from_custom_mode(v.custom_mode) == Px4Mode::Offboard,
            "alfa left offboard after its onboard process died: {:?}",
            Px4Mode::from_custom_mode(v.custom_mode)
        );
        last = Some(v);
    }
    let last = last.ok_or_else(|| anyhow::anyhow!("no truth"))?;
    anyhow::ensure!(
        last.velocity.norm() < 0.5,
        "alfa still moving at {:.2} m/s",
        last.velocity.norm()
    );
    anyhow::ensure!(
        last.armed && last.position.z > 5.0,
        "alfa is not holding in the air: {last:?}"
    );

    // Killing bravo's writer stops the setpoint stream: PX4 leaves offboard for hold after 1 s.
    let exit = sim.stack.crash(Role::Writer, Some(&bravo)).await;
    anyhow::ensure!(exit.is_some(), "bravo's writer was not running");
    truth_until(
        &mut truth,
        Duration::from_secs(3),
        "bravo in hold after its writer died",
        |t| {
            vehicle(t, &bravo).is_some_and(|v| {
                Px4Mode::from_custom_mode(v.custom_mode) == Px4Mode::Hold && v.armed
            })
        },
    )
    .await?;
    // And the ground learns bravo lost its autopilot link (its onboard hears no writer).
    sim.link
        .wait_for_drones(std::slice::from_ref(&bravo), Duration::from_secs(5), |s| {
            !s.autopilot_link && s.mode == DroneMode::Unavailable
        })
        .await?;

    // Both restarted in flight, as systemd's Restart= would: each drone is seen flying and
    // available again, alfa is held where it stopped (through the planner, in OFFBOARD), and
    // both take work again. Bravo is PX4's until its failsafe ends, a second into the restarted
    // writer's stream, when PX4 flies OFFBOARD again.
    sim.stack.restart(Role::Onboard, Some(&alfa))?;
    sim.stack.restart(Role::Writer, Some(&bravo))?;
    sim.link
        .wait_for_drones(
            &[alfa.clone(), bravo.clone()],
            Duration::from_secs(30),
            |s| s.autopilot_link && s.mode == DroneMode::Flying && s.autopilot_took_over.is_none(),
        )
        .await?;
    let held = truth_until(&mut truth, Duration::from_secs(5), "a truth update", |_| {
        true
    })
    .await?;
    let alfa_now = vehicle(&held, &alfa).ok_or_else(|| anyhow::anyhow!("alfa missing"))?;
    let drift = (alfa_now.position - last.position).norm();
    anyhow::ensure!(
        Px4Mode::from_custom_mode(alfa_now.custom_mode) == Px4Mode::Offboard && drift < 1.0,
        "alfa after its onboard restarted: {:?}, {drift:.2} m from where it stopped",
        Px4Mode::from_custom_mode(alfa_now.custom_mode)
    );
    let back = |d: &DroneId| {
        let home = sim.scenario.drone(d).map(|s| s.home).unwrap_or_default();
        home + Vec3::new(0.0, 10.0, sim.scenario.limits.takeoff_altitude)
    };
    act_all(
        &sim.link,
        &gate,
        vec![
            (
                alfa.clone(),
                Action::Goto {
                    target: back(&alfa),
                },
            ),
            (
                bravo.clone(),
                Action::Goto {
                    target: back(&bravo),
                },
            ),
        ],
    )
    .await?;
    Ok(())
}

/// An onboard that crashes and does not come back: the writer holds the vehicle, then lands it
/// once the planner has been silent for its bound (4 s here, 15 s by default).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_vehicle_whose_onboard_does_not_come_back_is_landed_by_its_writer() -> anyhow::Result<()>
{
    const LAND_AFTER_S: f64 = 4.0;
    let mut sim = SimSwarm::start_with("orphan", "city", 1, |c| {
        c.writer_args = vec!["--onboard-land-after-s".into(), LAND_AFTER_S.to_string()];
    })
    .await?;
    let result = orphaned(&mut sim, LAND_AFTER_S).await;
    sim.stop().await;
    result
}

async fn orphaned(sim: &mut SimSwarm, land_after_s: f64) -> anyhow::Result<()> {
    let alfa = id("alfa");
    let gate = SafetyGate::new(sim.scenario.clone());
    let mut truth = sim.link.watch_truth().await?;
    all_ready(sim, std::slice::from_ref(&alfa)).await?;
    act_all(&sim.link, &gate, vec![(alfa.clone(), Action::ArmTakeoff)]).await?;
    let exit = sim.stack.crash(Role::Onboard, Some(&alfa)).await;
    anyhow::ensure!(exit.is_some(), "alfa's onboard was not running");
    let killed = Instant::now();
    // Within the bound it holds in the air...
    while killed.elapsed().as_secs_f64() < land_after_s - 1.0 {
        let v = next_state_of(&mut truth, &alfa).await?;
        anyhow::ensure!(
            v.armed && v.position.z > 5.0,
            "alfa came down {:.1} s after its onboard died, within the bound: {v:?}",
            killed.elapsed().as_secs_f64()
        );
    }
    // ...after it, it is landed and disarmed.
    truth_until(
        &mut truth,
        Duration::from_secs(60),
        "alfa landed by its writer",
        |t| vehicle(t, &alfa).is_some_and(|v| v.landed && !v.armed),
    )
    .await?;
    let landed_after = killed.elapsed().as_secs_f64();
    anyhow::ensure!(
        landed_after >= land_after_s,
        "landed after {landed_after:.1} s"
    );
    println!("onboard dead: alfa held, then was landed by its writer {landed_after:.1} s later");
    Ok(())
}

//! Real PX4 (SITL with SIH) under the whole stack. The conformance scenario is written once and
//! flown on both autopilots, `tacos-sitl` and PX4: they must show the same sequence. Checks are
//! made on the simulator's truth, which with PX4 is what each vehicle reports on its own GCS
//! link, independently of the writer that flies it.

use std::time::Duration;
use tacos_ground::demo::{DemoOptions, DemoPlan, run_demo};
use tacos_ground::direct::{DirectError, run_actions};
use tacos_ground::launch::{AutopilotKind, Role};
use tacos_ground::safety::SafetyGate;
use tacos_shared::action::Action;
use tacos_shared::messages::{FailsafeStage, FailureReason};
use tacos_shared::px4_mode::Px4Mode;
use tacos_shared::{DroneId, DroneMode, Vec3};
use tacos_tests::{SimSwarm, all_ready, id, px4_sitl_or_skip, truth_until, vehicle};

/// Time for one action (PX4 climbs at 1.5 m/s and lands at 0.7 m/s).
const STEP: Duration = Duration::from_secs(90);

/// The onboard's ground-silence landing stage in the conformance scenario (30 s by default), so
/// that its silence step reaches it in seconds (the hold stage comes at 3 s).
const GROUND_SILENCE_LAND_S: u64 = 6;

/// What one scenario step showed: its name and what was seen, in words both autopilots share.
type Observation = (&'static str, String);

async fn act(sim: &SimSwarm, gate: &SafetyGate, drone: &DroneId, action: Action) -> String {
    match run_actions(&sim.link, gate, &[(drone.clone(), action)], None, STEP).await {
        Ok(()) => "done".into(),
        Err(DirectError::Failed { reason, .. }) => format!("failed: {}", kind_of(&reason)),
        Err(e) => format!("error: {e}"),
    }
}

fn kind_of(reason: &FailureReason) -> &'static str {
    match reason {
        FailureReason::InvalidForMode(_) => "invalid for mode",
        FailureReason::Rejected(_) => "rejected",
        FailureReason::Unreachable(_) => "unreachable",
        FailureReason::TimedOut => "timed out",
        FailureReason::Preempted => "preempted",
        FailureReason::AutopilotLinkLost => "link lost",
        FailureReason::TargetLost(_) => "target lost",
        FailureReason::Failsafe(_) => "failsafe",
    }
}

/// Take-off, offboard goto, land, the mode after landing (a second take-off must work), a
/// writer killed mid-air (the autopilot's configured failsafe: hold) and restarted (offboard
/// again), another ground station's switch to Hold (PX4 flies the drone: reported, out of
/// missions, and left to PX4 by the onboard's failsafes while the ground is silent), a hold
/// that takes it back, land.
async fn conformance(autopilot: AutopilotKind, tag: &str) -> anyhow::Result<Vec<Observation>> {
    let mut sim = SimSwarm::start_with(tag, "city", 1, |c| {
        c.autopilot = autopilot;
        c.onboard_args = vec![
            "--failsafe-land-s".into(),
            GROUND_SILENCE_LAND_S.to_string(),
        ];
    })
    .await?;
    let result = conformance_steps(&mut sim).await;
    if result.is_err() {
        tacos_tests::print_log_tails(&sim.stack.config.log_dir, 40);
    }
    sim.stop().await;
    result
}

async fn conformance_steps(sim: &mut SimSwarm) -> anyhow::Result<Vec<Observation>> {
    let alfa = id("alfa");
    let gate = SafetyGate::new(sim.scenario.clone());
    let mut truth = sim.link.watch_truth().await?;
    all_ready(sim, std::slice::from_ref(&alfa)).await?;
    let home = sim
        .scenario
        .drone(&alfa)
        .map(|s| s.home)
        .unwrap_or_default();
    let alt = sim.scenario.limits.takeoff_altitude;
    let mut seen = Vec::new();

    seen.push(("take off", act(sim, &gate, &alfa, Action::ArmTakeoff).await));
    truth_until(
        &mut truth,
        Duration::from_secs(10),
        "alfa at take-off altitude",
        |t| vehicle(t, &alfa).is_some_and(|v| v.armed && (v.position.z - home.z - alt).abs() < 1.0),
    )
    .await?;
    seen.push(("mode after take-off", settled_mode(&mut truth, &alfa).await));

    let goal = home + Vec3::new(5.0, 15.0, alt);
    seen.push((
        "goto",
        act(sim, &gate, &alfa, Action::Goto { target: goal }).await,
    ));
    truth_until(
        &mut truth,
        Duration::from_secs(10),
        "alfa at its goto point",
        |t| vehicle(t, &alfa).is_some_and(|v| (v.position - goal).norm() < 1.0),
    )
    .await?;

    seen.push(("land", act(sim, &gate, &alfa, Action::Land).await));
    truth_until(
        &mut truth,
        Duration::from_secs(15),
        "alfa landed and disarmed",
        |t| vehicle(t, &alfa).is_some_and(|v| v.landed && !v.armed),
    )
    .await?;
    seen.push(("mode after landing", settled_mode(&mut truth, &alfa).await));

    // PX4 is back in OFFBOARD after an offboard flight and refuses to arm there: the writer
    // switches to Hold first.
    all_ready(sim, std::slice::from_ref(&alfa)).await?;
    // The take-off altitude is above where the drone stands. On PX4 SIH that is not always the
    // floor: its ground holds only a vehicle pressed into it, and one that meets it in a steady
    // descent can sink through (0.76 and 1.53 m seen), where PX4's estimate then is too.
    let pad_z = truth
        .borrow()
        .as_ref()
        .and_then(|t| vehicle(t, &alfa).map(|v| v.position.z))
        .unwrap_or(home.z);
    seen.push((
        "take off again",
        act(sim, &gate, &alfa, Action::ArmTakeoff).await,
    ));

    // The writer dies mid-air, in a settled hover (a kill during the last metre of the climb
    // would measure the climb's own braking, not the hold): no setpoints, so the autopilot's
    // offboard-loss failsafe holds it.
    // (On PX4 under CI load the hover after the take-off was seen still 0.8 m above the
    // take-off altitude and drifting at 0.4 m/s after 15 s: hence these bounds.)
    truth_until(
        &mut truth,
        Duration::from_secs(20),
        "alfa hovering at take-off altitude",
        |t| {
            vehicle(t, &alfa).is_some_and(|v| {
                v.armed && (v.position.z - pad_z - alt).abs() < 1.0 && v.velocity.norm() < 0.5
            })
        },
    )
    .await
    .map_err(|e| e.context(format!("pad at z {pad_z:.2}; steps so far: {seen:?}")))?;
    let before = truth
        .borrow()
        .as_ref()
        .and_then(|t| vehicle(t, &alfa).map(|v| v.position));
    let exit = sim.stack.crash(Role::Writer, Some(&alfa)).await;
    anyhow::ensure!(exit.is_some(), "alfa's writer was not running");
    // The failsafe engages after the offboard-loss timeout (COM_OF_LOSS_T, 1 s): the vehicle
    // brakes from whatever the last setpoint asked (0.9–1.1 m in 3 s seen on PX4, still moving
    // 0.2 m/s then), then holds, its estimate wandering up to 0.17 m/s in SIH. Held = armed, in
    // Hold, within 3 m of where the writer died, and still (under 1 m, i.e. 0.5 m/s: a vehicle
    // flying on would move metres) over the 2 s after the first 4.
    let position_now = |truth: &Truth| {
        truth
            .borrow()
            .as_ref()
            .and_then(|t| vehicle(t, &alfa).map(|v| (v.position, v.armed, v.custom_mode)))
    };
    tokio::time::sleep(Duration::from_secs(4)).await;
    let settled = position_now(&truth);
    tokio::time::sleep(Duration::from_secs(2)).await;
    let after = position_now(&truth);
    let held = match (before, settled, after) {
        (Some(b), Some((s, _, _)), Some((a, armed, custom_mode))) => {
            let mode = Px4Mode::from_custom_mode(custom_mode);
            eprintln!(
                "writer killed: moved {:.2} m in 4 s, then {:.2} m in 2 s ({b:?} to {s:?} to {a:?})",
                (s - b).norm(),
                (a - s).norm(),
            );
            format!(
                "armed {armed}, mode {mode:?}, within 3 m: {}, then still: {}",
                (a - b).norm() < 3.0,
                (a - s).norm() < 1.0
            )
        }
        _ => "no truth".into(),
    };
    seen.push(("writer killed", held));
    sim.stack.restart(Role::Writer, Some(&alfa))?;
    sim.link
        .wait_for_drones(std::slice::from_ref(&alfa), Duration::from_secs(30), |s| {
            s.autopilot_link
        })
        .await?;
    // With the stream back, PX4's offboard-loss failsafe ends and it flies OFFBOARD again.
    seen.push((
        "who flies it after the writer came back",
        who_flies(sim, &alfa).await,
    ));
    // Another ground station (or an RC pilot's switch) puts it in Hold: PX4 flies it, not
    // TACOS. The drone says so, and the ground counts it out of missions; a hold takes it back.
    let (autopilot, sysid) = sim
        .stack
        .autopilot_address(0)
        .ok_or_else(|| anyhow::anyhow!("no MAVLink address for alfa's autopilot"))?;
    tacos_tests::ground_station::switch_mode(autopilot, sysid, Px4Mode::Hold)?;
    seen.push((
        "mode after another station's switch",
        settled_mode(&mut truth, &alfa).await,
    ));
    seen.push(("who flies it then", who_flies(sim, &alfa).await));
    seen.push((
        "in the ground's missions",
        format!("{:?}", sim.link.view().present_ids().contains(&alfa)),
    ));
    // The ground falls silent meanwhile: the drone goes through both of its failsafe stages
    // (hold, then land), and neither takes it from PX4, which keeps it in Hold, in the air.
    sim.link.set_heartbeat(false);
    sim.link
        .wait_for_drones(std::slice::from_ref(&alfa), STEP, |s| {
            s.failsafe == Some(FailsafeStage::Landing)
        })
        .await?;
    seen.push((
        "ground silent into the landing stage",
        format!(
            "mode {}, {}",
            settled_mode(&mut truth, &alfa).await,
            flight_state(&truth, &alfa)
        ),
    ));
    // A hold sent without a beat (a pilot acting before the drone hears the ground again) is
    // refused in the landing stage: taking the drone back from PX4, the next tick's landing
    // stage would land it.
    seen.push((
        "hold before a beat",
        act(sim, &gate, &alfa, Action::Hold).await,
    ));
    seen.push((
        "after the refused hold",
        format!(
            "mode {}, {}",
            settled_mode(&mut truth, &alfa).await,
            flight_state(&truth, &alfa)
        ),
    ));
    // The ground beats again, and the pilot acts once the drone has heard it.
    sim.link.set_heartbeat(true);
    sim.link
        .wait_for_drones(std::slice::from_ref(&alfa), STEP, |s| s.failsafe.is_none())
        .await?;
    seen.push(("hold", act(sim, &gate, &alfa, Action::Hold).await));
    seen.push(("mode after the hold", settled_mode(&mut truth, &alfa).await));
    seen.push(("who flies it after the hold", who_flies(sim, &alfa).await));
    seen.push((
        "land after the writer came back",
        act(sim, &gate, &alfa, Action::Land).await,
    ));
    truth_until(
        &mut truth,
        Duration::from_secs(15),
        "alfa landed and disarmed",
        |t| vehicle(t, &alfa).is_some_and(|v| v.landed && !v.armed),
    )
    .await?;
    Ok(seen)
}

type Truth = tokio::sync::watch::Receiver<Option<tacos_shared::messages::SimTruth>>;

/// Who the drone's status says flies it, "TACOS" or "PX4 in MODE": looked at twice, 0.5 s
/// apart, after 3 s (past the onboard's 1.6 s grace for PX4's mode reports and a heartbeat of
/// PX4's, which tells the mode at 1 Hz); "unsettled: …" when the two looks differ.
async fn who_flies(sim: &SimSwarm, drone: &DroneId) -> String {
    let says = |sim: &SimSwarm| {
        let view = sim.link.view();
        let status = view.get(drone)?.status.as_ref()?;
        Some(match status.autopilot_took_over {
            Some(mode) => format!("PX4 in {mode}"),
            None => "TACOS".to_owned(),
        })
    };
    tokio::time::sleep(Duration::from_secs(3)).await;
    let first = says(sim);
    tokio::time::sleep(Duration::from_millis(500)).await;
    match (first, says(sim)) {
        (Some(a), Some(b)) if a == b => a,
        (a, b) => format!("unsettled: {a:?} then {b:?}"),
    }
}

/// "armed …, landed …" as the vehicle reports it now.
fn flight_state(truth: &Truth, drone: &DroneId) -> String {
    match truth.borrow().as_ref().and_then(|t| vehicle(t, drone)) {
        Some(v) => format!("armed {}, landed {}", v.armed, v.landed),
        None => "not reported".into(),
    }
}

/// The mode the vehicle reports once its heartbeat (1 Hz) has caught up: unchanged for 2 s
/// (within 8 s at most).
async fn settled_mode(truth: &mut Truth, drone: &DroneId) -> String {
    let mode_now = |truth: &Truth| {
        truth
            .borrow()
            .as_ref()
            .and_then(|t| vehicle(t, drone))
            .map(|v| Px4Mode::from_custom_mode(v.custom_mode))
    };
    let mut last = mode_now(truth);
    let mut since = tokio::time::Instant::now();
    let deadline = since + Duration::from_secs(8);
    while tokio::time::Instant::now() < deadline && since.elapsed() < Duration::from_secs(2) {
        let _ = tokio::time::timeout(Duration::from_millis(200), truth.changed()).await;
        let now = mode_now(truth);
        if now != last {
            last = now;
            since = tokio::time::Instant::now();
        }
    }
    format!("{last:?}")
}

fn expected() -> Vec<Observation> {
    vec![
        ("take off", "done".into()),
        (
            "mode after take-off",
            format!("{:?}", Some(Px4Mode::Offboard)),
        ),
        ("goto", "done".into()),
        ("land", "done".into()),
        (
            "mode after landing",
            format!("{:?}", Some(Px4Mode::Offboard)),
        ),
        ("take off again", "done".into()),
        (
            "writer killed",
            format!(
                "armed true, mode {:?}, within 3 m: true, then still: true",
                Px4Mode::Hold
            ),
        ),
        ("who flies it after the writer came back", "TACOS".into()),
        (
            "mode after another station's switch",
            format!("{:?}", Some(Px4Mode::Hold)),
        ),
        ("who flies it then", "PX4 in Hold".into()),
        ("in the ground's missions", "false".into()),
        (
            "ground silent into the landing stage",
            format!("mode {:?}, armed true, landed false", Some(Px4Mode::Hold)),
        ),
        ("hold before a beat", "failed: failsafe".into()),
        (
            "after the refused hold",
            format!("mode {:?}, armed true, landed false", Some(Px4Mode::Hold)),
        ),
        ("hold", "done".into()),
        (
            "mode after the hold",
            format!("{:?}", Some(Px4Mode::Offboard)),
        ),
        ("who flies it after the hold", "TACOS".into()),
        ("land after the writer came back", "done".into()),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn conformance_on_the_stand_in() -> anyhow::Result<()> {
    let seen = conformance(AutopilotKind::Sitl, "confsitl").await?;
    assert_eq!(seen, expected());
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn conformance_on_real_px4() -> anyhow::Result<()> {
    let Some(dir) = px4_sitl_or_skip("conformance_on_real_px4") else {
        return Ok(());
    };
    let seen = conformance(AutopilotKind::Px4Sitl { dir }, "confpx4").await?;
    assert_eq!(seen, expected());
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_drones_fly_the_fixed_pattern_on_real_px4() -> anyhow::Result<()> {
    let Some(dir) = px4_sitl_or_skip("three_drones_fly_the_fixed_pattern_on_real_px4") else {
        return Ok(());
    };
    let scenario = tacos_bus::load_scenario("city")?;
    let opts = DemoOptions {
        scenario_arg: "city".into(),
        scenario,
        drones: 3,
        sim_speed: 1.0,
        autopilot: AutopilotKind::Px4Sitl { dir },
        verbose: true,
    };
    run_demo(opts, DemoPlan::Fixed, std::future::pending()).await?;
    Ok(())
}

/// The fault table on real PX4: the onboard killed (the writer holds the last setpoint and PX4
/// stays in OFFBOARD), then the ground silent (the drone holds, then lands by itself), then the
/// vehicle dead (its PX4 instance killed: unavailable).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn faults_on_real_px4() -> anyhow::Result<()> {
    let Some(dir) = px4_sitl_or_skip("faults_on_real_px4") else {
        return Ok(());
    };
    let mut sim = SimSwarm::start_with("faultpx4", "city", 1, |c| {
        c.autopilot = AutopilotKind::Px4Sitl { dir };
        c.onboard_args = vec!["--failsafe-land-s".into(), "8".into()];
    })
    .await?;
    let result = fault_steps(&mut sim).await;
    if result.is_err() {
        tacos_tests::print_log_tails(&sim.stack.config.log_dir, 40);
    }
    sim.stop().await;
    result
}

async fn fault_steps(sim: &mut SimSwarm) -> anyhow::Result<()> {
    let alfa = id("alfa");
    let gate = SafetyGate::new(sim.scenario.clone());
    let mut truth = sim.link.watch_truth().await?;
    all_ready(sim, std::slice::from_ref(&alfa)).await?;
    run_actions(
        &sim.link,
        &gate,
        &[(alfa.clone(), Action::ArmTakeoff)],
        None,
        STEP,
    )
    .await
    .map_err(|e| anyhow::anyhow!("take-off: {e:?}"))?;
    let position = |truth: &Truth| {
        truth
            .borrow()
            .as_ref()
            .and_then(|t| vehicle(t, &alfa).cloned())
    };
    tokio::time::sleep(Duration::from_secs(2)).await;
    let before = position(&truth).ok_or_else(|| anyhow::anyhow!("no truth"))?;

    let exit = sim.stack.crash(Role::Onboard, Some(&alfa)).await;
    anyhow::ensure!(exit.is_some(), "alfa's onboard was not running");
    tokio::time::sleep(Duration::from_secs(4)).await;
    let after = position(&truth).ok_or_else(|| anyhow::anyhow!("no truth"))?;
    let drift = (after.position - before.position).norm();
    let mode = Px4Mode::from_custom_mode(after.custom_mode);
    anyhow::ensure!(
        after.armed && mode == Px4Mode::Offboard && drift < 1.0,
        "with its onboard dead the drone should hold in OFFBOARD: armed {}, {mode:?}, moved {drift:.2} m",
        after.armed
    );

    sim.stack.restart(Role::Onboard, Some(&alfa))?;
    sim.link
        .wait_for_drones(std::slice::from_ref(&alfa), Duration::from_secs(30), |s| {
            s.autopilot_link
        })
        .await?;
    // The ground goes silent: hold after 3 s, land after 8 s.
    sim.link.set_heartbeat(false);
    truth_until(
        &mut truth,
        Duration::from_secs(60),
        "alfa landed by its failsafe",
        |t| vehicle(t, &alfa).is_some_and(|v| v.landed && !v.armed),
    )
    .await?;
    sim.link.set_heartbeat(true);

    // The vehicle dies, as a script's `fail alfa` makes it on PX4 SITL: its PX4 instance is
    // killed. The writer loses its autopilot (3 s without a heartbeat) and the drone is
    // unavailable to the ground.
    let exit = sim.stack.crash(Role::Px4, Some(&alfa)).await;
    anyhow::ensure!(exit.is_some(), "alfa's PX4 instance was not running");
    sim.link
        .wait_for_drones(std::slice::from_ref(&alfa), Duration::from_secs(15), |s| {
            s.mode == DroneMode::Unavailable && !s.autopilot_link
        })
        .await?;
    Ok(())
}

//! A drone cut off from its peers but not from the ground: tacos-sitl, three tacos-px4 +
//! tacos-onboard pairs and a ground link on loopback. All three take off and alfa flies a long
//! goto; the onboards of both its neighbours die (the silence alfa would hear behind a broken
//! radio between the drones). Alfa must stop and hold where it is, refuse work other than land
//! and hold while no neighbour is heard (its status saying so), and take work again once one is
//! heard. Checked in the simulator's truth and in what the ground is told.

use std::time::{Duration, Instant};
use tacos_ground::direct::{DirectError, run_actions};
use tacos_ground::launch::Role;
use tacos_ground::safety::SafetyGate;
use tacos_shared::action::Action;
use tacos_shared::messages::{FailureReason, SimTruth, VehicleTruth};
use tacos_shared::px4_mode::Px4Mode;
use tacos_shared::{DroneId, Vec3};
use tacos_tests::{SimSwarm, all_ready, id, truth_until, vehicle};

type Truth = tokio::sync::watch::Receiver<Option<SimTruth>>;

const STEP: Duration = Duration::from_secs(60);
/// The onboard's default `--peers-silent-hold-s`.
const HOLD_AFTER_S: f64 = 3.0;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drone_that_hears_none_of_its_neighbours_holds_until_one_is_heard() -> anyhow::Result<()>
{
    let mut sim = SimSwarm::start("peersilent", "city", 3).await?;
    let result = cut_off(&mut sim).await;
    sim.stop().await;
    result
}

/// The vehicle's state once it has stayed within 0.5 m of one point for 2 s.
async fn settled(
    truth: &mut Truth,
    drone: &DroneId,
    bound: Duration,
) -> anyhow::Result<VehicleTruth> {
    let deadline = Instant::now() + bound;
    let mut window: Option<(Instant, VehicleTruth)> = None;
    while Instant::now() < deadline {
        let now = truth_until(truth, Duration::from_secs(2), "a truth update", |_| true).await?;
        let v = vehicle(&now, drone)
            .cloned()
            .ok_or_else(|| anyhow::anyhow!("{drone} missing from truth"))?;
        match &window {
            Some((since, first)) if (v.position - first.position).norm() <= 0.5 => {
                if since.elapsed() >= Duration::from_secs(2) {
                    return Ok(v);
                }
            }
            _ => window = Some((Instant::now(), v)),
        }
    }
    anyhow::bail!("{drone} did not settle within {bound:?}: last {window:?}")
}

/// Whether `drone`'s last status says it holds for want of a neighbour heard.
fn peers_silent_told(sim: &SimSwarm, drone: &DroneId) -> Option<bool> {
    sim.link
        .view()
        .get(drone)
        .and_then(|e| e.status.as_ref().map(|s| s.peers_silent))
}

fn failsafe_reason(result: Result<(), DirectError>) -> anyhow::Result<String> {
    match result {
        Err(DirectError::Failed {
            reason: FailureReason::Failsafe(why),
            ..
        }) => Ok(why),
        other => anyhow::bail!("expected a failsafe failure, got {other:?}"),
    }
}

async fn cut_off(sim: &mut SimSwarm) -> anyhow::Result<()> {
    let (alfa, bravo, charlie) = (id("alfa"), id("bravo"), id("charlie"));
    let gate = SafetyGate::new(sim.scenario.clone());
    let mut truth = sim.link.watch_truth().await?;
    // All three in the air: neighbours last seen airborne are never forgotten (one last seen
    // on the ground is, after 10 s, and with it its silence).
    let all = [alfa.clone(), bravo.clone(), charlie.clone()];
    all_ready(sim, &all).await?;
    let takeoffs: Vec<_> = all
        .iter()
        .map(|d| (d.clone(), Action::ArmTakeoff))
        .collect();
    run_actions(&sim.link, &gate, &takeoffs, None, STEP).await?;

    // A long goto north, waited on in the background.
    let home = sim
        .scenario
        .drone(&alfa)
        .map(|s| s.home)
        .unwrap_or_default();
    let far = home + Vec3::new(0.0, 80.0, sim.scenario.limits.takeoff_altitude);
    let goto = sim.goto_in_background(&gate, &alfa, Vec3::new(0.0, 80.0, 0.0), STEP);
    truth_until(
        &mut truth,
        Duration::from_secs(15),
        "alfa moving north",
        |t| vehicle(t, &alfa).is_some_and(|v| v.velocity.y > 2.0),
    )
    .await?;

    // Both neighbours' onboards die: alfa hears no path from anyone.
    let cut_at = Instant::now();
    for drone in [&bravo, &charlie] {
        let exit = sim.stack.crash(Role::Onboard, Some(drone)).await;
        anyhow::ensure!(exit.is_some(), "{drone}'s onboard was not running");
    }
    let why = failsafe_reason(goto.await?)?;
    let failed_after = cut_at.elapsed().as_secs_f64();
    println!("alfa's goto failed {failed_after:.2} s after the cut: {why}");
    anyhow::ensure!(why.contains("no neighbour heard"), "{why}");
    anyhow::ensure!(
        (HOLD_AFTER_S - 0.5..HOLD_AFTER_S + 3.0).contains(&failed_after),
        "the goto failed {failed_after:.2} s after the cut (bound {HOLD_AFTER_S} s)"
    );

    // It stops and holds in the air, in OFFBOARD, far short of its goal: back at the point
    // where the silence was noticed (it brakes past it), then still for 2 s.
    let held = settled(&mut truth, &alfa, Duration::from_secs(20)).await?;
    anyhow::ensure!(
        held.armed && Px4Mode::from_custom_mode(held.custom_mode) == Px4Mode::Offboard,
        "alfa is not holding under offboard control: {held:?}"
    );
    anyhow::ensure!(
        (held.position - far).norm() > 20.0,
        "alfa got near its goal anyway: {:?}",
        held.position
    );

    // Its status says why it holds.
    let told = peers_silent_told(sim, &alfa);
    anyhow::ensure!(
        told == Some(true),
        "alfa's status does not name the hold: {told:?}"
    );

    // Work other than land and hold is refused, with the reason.
    let nearby = [(
        alfa.clone(),
        Action::Goto {
            target: held.position + Vec3::new(0.0, 5.0, 0.0),
        },
    )];
    let why = failsafe_reason(run_actions(&sim.link, &gate, &nearby, None, STEP).await)?;
    anyhow::ensure!(why.contains("only land and hold"), "{why}");

    // A neighbour is heard again: the same goto is taken and flown.
    sim.stack.restart(Role::Onboard, Some(&bravo))?;
    sim.link
        .wait_for_drones(std::slice::from_ref(&bravo), Duration::from_secs(30), |s| {
            s.autopilot_link
        })
        .await?;
    // Its paths reach alfa within a planner period or two of its start: until then the goto
    // may still meet the failsafe, and is asked again.
    let heard_by = Instant::now() + Duration::from_secs(5);
    loop {
        match run_actions(&sim.link, &gate, &nearby, None, STEP).await {
            Ok(()) => break,
            Err(DirectError::Failed {
                reason: FailureReason::Failsafe(_),
                ..
            }) if Instant::now() < heard_by => {
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(e) => anyhow::bail!("the goto after bravo came back: {e}"),
        }
    }
    let told = peers_silent_told(sim, &alfa);
    anyhow::ensure!(
        told == Some(false),
        "alfa's status still names the hold: {told:?}"
    );
    Ok(())
}

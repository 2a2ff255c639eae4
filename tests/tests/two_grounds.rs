//! One ground station at a time: while the ground in control beats, a second one that beats
//! and sends is refused, on the drone (it ignores both) and on the second ground (its send fails
//! naming the one followed); once the first falls silent, the second is in control within the
//! failsafe's hold time, and the first is then the one refused.

use std::time::{Duration, Instant};
use tacos_ground::link::{GroundLink, GroundRole, LinkError};
use tacos_ground::safety::SafetyGate;
use tacos_shared::action::Action;
use tacos_shared::messages::ActionState;
use tacos_shared::{DroneId, Vec3};
use tacos_tests::{SimSwarm, all_ready, id};

/// The onboard's default hold time, which is also when another ground may take over.
const HOLD_AFTER_S: f64 = 3.0;

async fn send(
    link: &GroundLink,
    gate: &SafetyGate,
    drone: &DroneId,
    action: Action,
) -> Result<ActionState, LinkError> {
    let checked = {
        let view = link.view();
        gate.check(&view, drone.as_str(), &action, link.clock().instant())
    };
    let checked = match checked {
        Ok(c) => c,
        Err(r) => panic!("the gate refused {action}: {r}"),
    };
    let seq = link.send(&checked, None).await?;
    link.wait_outcome(drone, seq, Duration::from_secs(60)).await
}

fn followed(link: &GroundLink, drone: &DroneId) -> Option<u64> {
    link.view()
        .get(drone)
        .and_then(|e| e.status.as_ref())
        .and_then(|s| s.ground)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_ground_is_refused_while_the_first_beats_and_takes_over_when_it_falls_silent()
-> anyhow::Result<()> {
    let sim = SimSwarm::start("grounds", "city", 1).await?;
    let result = steps(&sim).await;
    if result.is_err() {
        eprintln!("logs: {}", sim.stack.config.log_dir.display());
    }
    sim.stop().await;
    result
}

async fn steps(sim: &SimSwarm) -> anyhow::Result<()> {
    let alfa = id("alfa");
    let gate = SafetyGate::new(sim.scenario.clone());
    all_ready(sim, std::slice::from_ref(&alfa)).await?;
    let first = &sim.link;
    // The drone follows the first ground once it has heard it.
    let started = Instant::now();
    while followed(first, &alfa) != Some(first.epoch()) {
        anyhow::ensure!(
            started.elapsed() < Duration::from_secs(10),
            "alfa never named the first ground: {:?}",
            followed(first, &alfa)
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    let mut bus = sim.stack.config.ground_bus();
    bus.connect = std::mem::take(&mut bus.listen);
    let second = GroundLink::connect_as(&bus, GroundRole::InControl).await?;
    second
        .wait_for_drones(std::slice::from_ref(&alfa), Duration::from_secs(10), |_| {
            true
        })
        .await?;

    // The second one's take-off is refused, with the ground the drone follows named.
    match send(&second, &gate, &alfa, Action::ArmTakeoff).await {
        Err(LinkError::NotFollowed { followed, .. }) => assert_eq!(followed, first.epoch()),
        other => panic!("the second ground's action was not refused: {other:?}"),
    }
    // The first is undisturbed by the second one's heartbeats.
    assert_eq!(
        send(first, &gate, &alfa, Action::ArmTakeoff).await?,
        ActionState::Done
    );

    // The first falls silent: the second is followed within the hold time (plus a beat).
    first.set_heartbeat(false);
    let silent_at = Instant::now();
    while followed(&second, &alfa) != Some(second.epoch()) {
        anyhow::ensure!(
            silent_at.elapsed() < Duration::from_secs_f64(HOLD_AFTER_S + 3.0),
            "the second ground did not take over within {} s",
            HOLD_AFTER_S + 3.0
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let took = silent_at.elapsed().as_secs_f64();
    eprintln!("the second ground was followed {took:.2} s after the first fell silent");
    assert!(
        took >= HOLD_AFTER_S - 0.5,
        "taken over too early: {took:.2} s"
    );
    let goto = Action::Goto {
        target: Vec3::new(-75.0, -70.0, 12.0),
    };
    assert_eq!(send(&second, &gate, &alfa, goto).await?, ActionState::Done);
    // The first, beating again, is now the one refused.
    first.set_heartbeat(true);
    match send(first, &gate, &alfa, Action::Land).await {
        Err(LinkError::NotFollowed { followed, .. }) => assert_eq!(followed, second.epoch()),
        other => panic!("the old ground's action was not refused: {other:?}"),
    }
    assert_eq!(
        send(&second, &gate, &alfa, Action::Land).await?,
        ActionState::Done
    );
    Ok(())
}

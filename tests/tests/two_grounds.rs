//! One ground station at a time: while the ground in control beats, a second one that beats
//! and sends is refused, on the drone (it ignores both) and on the second ground (its send fails
//! naming the one followed); once the first falls silent, the second is in control within the
//! failsafe's hold time, and the first is then the one refused. And an action of the followed
//! ground that the network held on the way is refused, with the reason told to that ground.

use std::time::{Duration, Instant};
use tacos_ground::link::{GroundLink, GroundRole, LinkError};
use tacos_ground::safety::SafetyGate;
use tacos_shared::action::{Action, ActionCommand};
use tacos_shared::messages::{ActionState, RefusedBecause};
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
        tacos_tests::print_log_tails(&sim.stack.config.log_dir, 40);
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

/// An action stamped 6 s before it reaches the drone, as a network that stalled and then
/// delivered would hand it over: the drone refuses it and says why in its status, the ground's
/// wait ends with that reason, and the drone keeps doing what it did. A land held as long is
/// still taken.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_action_held_on_the_way_is_refused_and_its_ground_told_why() -> anyhow::Result<()> {
    let sim = SimSwarm::start("late", "city", 1).await?;
    let result = held_steps(&sim).await;
    if result.is_err() {
        tacos_tests::print_log_tails(&sim.stack.config.log_dir, 40);
    }
    sim.stop().await;
    result
}

async fn held_steps(sim: &SimSwarm) -> anyhow::Result<()> {
    let alfa = id("alfa");
    let gate = SafetyGate::new(sim.scenario.clone());
    all_ready(sim, std::slice::from_ref(&alfa)).await?;
    let link = &sim.link;
    assert_eq!(
        send(link, &gate, &alfa, Action::ArmTakeoff).await?,
        ActionState::Done
    );
    let hover = |link: &GroundLink| {
        link.view()
            .get(&alfa)
            .and_then(|e| e.status.clone())
            .ok_or_else(|| anyhow::anyhow!("alfa has no status"))
    };
    let before = hover(link)?;
    // The network that held the actions: a session on the ground's swarm putting what the
    // ground sent 6 s ago, in its name and with numbers newer than any it sent.
    let mut bus = sim.stack.config.ground_bus();
    bus.connect = std::mem::take(&mut bus.listen);
    let network = bus.open().await?;
    let key = bus.keys().action(&alfa);
    tacos_tests::wait_for_subscriber(&network, &key).await?;
    let held = |seq: u64, action: Action| ActionCommand {
        ground: link.epoch(),
        seq,
        sent_at: link.clock().now() - 6.0,
        task_id: None,
        action,
    };
    let seq = u64::MAX / 2;
    let goto = Action::Goto {
        target: Vec3::new(-75.0, -70.0, 12.0),
    };
    tacos_bus::put(
        &network,
        &key,
        &held(seq, goto),
        tacos_bus::Delivery::Command,
    )
    .await?;
    match link.wait_outcome(&alfa, seq, Duration::from_secs(10)).await {
        Err(LinkError::Refused {
            why: RefusedBecause::Late { late_s, bound_s },
            ..
        }) => {
            eprintln!("the held goto was refused: late by {late_s:.2} s (bound {bound_s} s)");
            assert!((5.0..7.5).contains(&late_s), "late by {late_s} s");
            assert_eq!(bound_s, 2.0);
        }
        other => panic!("the held goto was not refused as late: {other:?}"),
    }
    let after = hover(link)?;
    assert_eq!(
        after.action.as_ref().map(|a| a.seq),
        before.action.as_ref().map(|a| a.seq),
        "the held goto replaced the drone's action"
    );
    assert!(
        (after.position - before.position).norm() < 1.0,
        "alfa moved from {:?} to {:?}",
        before.position,
        after.position
    );
    // What makes the drone safer is taken however late (and last here: its number is taken).
    tacos_bus::put(
        &network,
        &key,
        &held(seq + 1, Action::Land),
        tacos_bus::Delivery::Command,
    )
    .await?;
    assert_eq!(
        link.wait_outcome(&alfa, seq + 1, Duration::from_secs(60))
            .await?,
        ActionState::Done
    );
    Ok(())
}

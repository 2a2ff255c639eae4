//! An onboard whose process stalls (SIGSTOP for longer than the failsafes' hold bound, as an
//! overloaded companion computer descheduling it would) must not take the time it could not
//! listen for silence: the ground and the neighbours went on publishing, so on resuming it flies
//! on. tacos-sitl, three tacos-px4 + tacos-onboard pairs and a ground link on loopback; all
//! three in the air (so that the peers' silence counts) and alfa on a long goto when its onboard
//! is frozen for 5 s.

use std::time::{Duration, Instant};
use tacos_ground::launch::Role;
use tacos_ground::safety::SafetyGate;
use tacos_shared::Vec3;
use tacos_tests::{SimSwarm, all_ready, id, truth_until, vehicle};

const STEP: Duration = Duration::from_secs(60);
/// Longer than the onboard's default ground and peer hold bounds (3 s each).
const FROZEN: Duration = Duration::from_secs(5);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_onboard_does_not_count_its_stall_as_silence() -> anyhow::Result<()> {
    let mut sim = SimSwarm::start("stall", "city", 3).await?;
    let result = stall_mid_goto(&mut sim).await;
    // A frozen process ignores SIGTERM: let it go before the stack stops.
    sim.stack.thaw(Role::Onboard, Some(&id("alfa")));
    if let Err(e) = &result {
        eprintln!("{e:#}; logs: {}", sim.stack.config.log_dir.display());
    }
    sim.stop().await;
    result
}

async fn stall_mid_goto(sim: &mut SimSwarm) -> anyhow::Result<()> {
    let alfa = id("alfa");
    let all = [alfa.clone(), id("bravo"), id("charlie")];
    let gate = SafetyGate::new(sim.scenario.clone());
    let mut truth = sim.link.watch_truth().await?;
    all_ready(sim, &all).await?;
    sim.take_off(&gate, &all).await?;

    let goto = sim.goto_in_background(&gate, &alfa, Vec3::new(0.0, 60.0, 0.0), STEP);
    truth_until(
        &mut truth,
        Duration::from_secs(15),
        "alfa moving north",
        |t| vehicle(t, &alfa).is_some_and(|v| v.velocity.y > 1.0),
    )
    .await?;

    anyhow::ensure!(
        sim.stack.freeze(Role::Onboard, Some(&alfa)),
        "alfa's onboard is not running"
    );
    let frozen_at = Instant::now();
    // The freeze is real: the ground stops hearing alfa's status.
    let mut longest_status_age = 0.0_f64;
    while frozen_at.elapsed() < FROZEN {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let now = sim.link.clock().instant();
        let age = sim.link.view().get(&alfa).and_then(|e| e.link_age(now));
        longest_status_age = longest_status_age.max(age.unwrap_or(0.0));
    }
    sim.stack.thaw(Role::Onboard, Some(&alfa));
    println!("alfa's onboard frozen {FROZEN:?}; its status aged to {longest_status_age:.1} s");
    anyhow::ensure!(
        longest_status_age > 3.0,
        "alfa's status never aged past the hold bound ({longest_status_age:.1} s): no stall"
    );

    // On resuming, no failsafe: its status never names one, and the goto reaches its goal.
    let watch_until = Instant::now() + Duration::from_secs(3);
    while Instant::now() < watch_until {
        if let Some(status) = sim.link.view().get(&alfa).and_then(|e| e.status.clone()) {
            anyhow::ensure!(
                status.failsafe.is_none(),
                "alfa took its stall for silence: {:?}",
                status.failsafe
            );
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    goto.await?
        .map_err(|e| anyhow::anyhow!("alfa's goto after the stall: {e}"))?;
    Ok(())
}

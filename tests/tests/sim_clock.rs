//! The simulated run's one clock, end to end: tacos-sitl runs at its speed between model calls
//! and at real time while the ground has one in flight (`sim/pace`), and the onboards and the
//! ground follow its clock (`sim/clock`), so the drones fly at speed as they do at real time.

use std::time::{Duration, Instant};
use tacos_bus::clock::Clock;
use tacos_ground::direct::run_actions;
use tacos_ground::safety::SafetyGate;
use tacos_shared::DroneId;
use tacos_shared::action::Action;
use tacos_shared::messages::SimTruth;
use tacos_tests::{SimSwarm, all_ready, within};
use tokio::sync::watch;

const SPEED: f64 = 4.0;
const STEP: Duration = Duration::from_secs(60);

/// Simulated seconds per wall second over `window`, as the simulator's truth tells them and as
/// the ground's clock reads them.
async fn rates(
    truth: &mut watch::Receiver<Option<SimTruth>>,
    clock: &Clock,
    window: Duration,
) -> anyhow::Result<(f64, f64)> {
    let mut next_truth = async || -> anyhow::Result<f64> {
        within(
            "the simulator's truth",
            Duration::from_secs(5),
            truth.changed(),
        )
        .await??;
        let t = truth.borrow_and_update().as_ref().map(|t| t.sim_time);
        t.ok_or_else(|| anyhow::anyhow!("no truth from the simulator"))
    };
    let (sim0, clock0, wall0) = (next_truth().await?, clock.now(), Instant::now());
    // A measuring window, not a wait for something to happen.
    tokio::time::sleep(window).await;
    let (sim1, clock1, wall1) = (next_truth().await?, clock.now(), Instant::now());
    let wall = wall1.duration_since(wall0).as_secs_f64();
    Ok(((sim1 - sim0) / wall, (clock1 - clock0) / wall))
}

/// Waits until the clock the ground follows runs at `rate` (the simulator heard the pace).
async fn rate_becomes(clock: &Clock, rate: f64) -> anyhow::Result<()> {
    within(
        "the simulator's change of rate",
        Duration::from_secs(5),
        async {
            while clock.rate() != rate {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        },
    )
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_simulation_runs_at_its_speed_between_model_calls_and_at_real_time_during_one()
-> anyhow::Result<()> {
    let sim = SimSwarm::start_with("clock", "lab", 3, |c| c.sim_speed = SPEED).await?;
    let ids = sim.stack.config.drone_ids();
    let gate = SafetyGate::new(sim.scenario.clone());
    let mut truth = sim.link.watch_truth().await?;
    let clock = sim.link.clock().clone();
    let all = |action: Action| -> Vec<(DroneId, Action)> {
        ids.iter().map(|d| (d.clone(), action.clone())).collect()
    };
    let result = async {
        all_ready(&sim, &ids).await?;
        assert!(clock.is_simulated());
        rate_becomes(&clock, SPEED).await?;
        run_actions(&sim.link, &gate, &all(Action::ArmTakeoff), None, STEP).await?;
        let fast = rates(&mut truth, &clock, Duration::from_secs(2)).await?;

        let call = sim.link.model_call();
        rate_becomes(&clock, 1.0).await?;
        let during_call = rates(&mut truth, &clock, Duration::from_secs(2)).await?;
        drop(call);
        rate_becomes(&clock, SPEED).await?;

        // The drones still fly on the clock at speed: no failsafe, no lost link, no breach.
        run_actions(&sim.link, &gate, &all(Action::Land), None, STEP).await?;
        let last = truth.borrow().clone();
        anyhow::Ok((fast, during_call, last))
    }
    .await;
    sim.stop().await;
    let (fast, during_call, last) = result?;
    // The machine may not keep up with 4× at every moment; it must be well above real time.
    assert!(
        fast.0 > 2.5,
        "the simulation ran at {:.2}× between calls",
        fast.0
    );
    assert!(fast.1 > 2.5, "the ground's clock ran at {:.2}×", fast.1);
    for (what, rate) in [
        ("simulation", during_call.0),
        ("ground's clock", during_call.1),
    ] {
        assert!(
            (0.7..1.3).contains(&rate),
            "the {what} ran at {rate:.2}× during a model call"
        );
    }
    let last = last.ok_or_else(|| anyhow::anyhow!("no truth from the simulator"))?;
    assert_eq!(
        (last.separation_breaches, last.obstacle_breaches),
        (0, 0),
        "{last:?}"
    );
    Ok(())
}

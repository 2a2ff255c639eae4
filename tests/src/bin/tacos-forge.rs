//! `tacos-forge`: a test peer that plays a compromised drone host. With that drone's own
//! certificate (its `--zenoh-config`) it puts, as real TACOS messages, what only others may put:
//! a `land` action for the victim drone stamped with the ground's live epoch and a sequence
//! number newer than any (were it delivered, the victim would land), a ground heartbeat, a
//! target, and the victim's status. The router must refuse all of them.
//!
//! Usage: tacos-forge --zenoh-config FILE --swarm NAME --victim DRONE --count N

use std::time::Duration;
use tacos_shared::action::{Action, ActionCommand};
use tacos_shared::messages::{GroundHeartbeat, TargetObservation, TargetsMessage};
use tacos_shared::{DroneId, SwarmId, Vec3};

struct Args {
    config: String,
    swarm: SwarmId,
    victim: DroneId,
    count: u64,
}

fn args() -> anyhow::Result<Args> {
    let mut it = std::env::args().skip(1);
    let (mut config, mut swarm, mut victim, mut count) = (None, None, None, None);
    while let Some(flag) = it.next() {
        let value = it
            .next()
            .ok_or_else(|| anyhow::anyhow!("{flag} needs a value"))?;
        match flag.as_str() {
            "--zenoh-config" => config = Some(value),
            "--swarm" => swarm = Some(SwarmId::new(value).map_err(anyhow::Error::msg)?),
            "--victim" => victim = Some(DroneId::new(value).map_err(anyhow::Error::msg)?),
            "--count" => count = Some(value.parse()?),
            other => anyhow::bail!("unknown flag {other}"),
        }
    }
    let usage = "usage: tacos-forge --zenoh-config FILE --swarm NAME --victim DRONE --count N";
    Ok(Args {
        config: config.ok_or_else(|| anyhow::anyhow!(usage))?,
        swarm: swarm.ok_or_else(|| anyhow::anyhow!(usage))?,
        victim: victim.ok_or_else(|| anyhow::anyhow!(usage))?,
        count: count.ok_or_else(|| anyhow::anyhow!(usage))?,
    })
}

#[tokio::main(flavor = "multi_thread", worker_threads = 1)]
async fn main() -> anyhow::Result<()> {
    let args = args()?;
    let config = zenoh::Config::from_file(&args.config).map_err(|e| anyhow::anyhow!("{e}"))?;
    let session = zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let keys = tacos_shared::keys::Keys::new(&args.swarm);
    // A drone may hear the heartbeat: learn the ground's epoch, so the forged action would be
    // taken were it delivered.
    let beats = tacos_bus::subscribe(&session, &keys.ground_heartbeat()).await?;
    let beat = tokio::time::timeout(Duration::from_secs(15), beats.recv_async())
        .await
        .map_err(|_| anyhow::anyhow!("no ground heartbeat heard within 15 s"))?
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let beat: GroundHeartbeat = tacos_bus::decode(&beat)?;
    println!("ground epoch {}", beat.ground);
    let status = keys.status(&args.victim);
    for i in 0..args.count {
        let land = ActionCommand {
            ground: beat.ground,
            seq: u64::MAX / 2 + i,
            sent_at: beat.stamp,
            task_id: None,
            action: Action::Land,
        };
        tacos_bus::put(
            &session,
            &keys.action(&args.victim),
            &land,
            tacos_bus::Delivery::Command,
        )
        .await?;
        let forged_beat = GroundHeartbeat {
            counter: beat.counter + 1 + i,
            ground: beat.ground,
            stamp: beat.stamp,
        };
        tacos_bus::put(
            &session,
            &keys.ground_heartbeat(),
            &forged_beat,
            tacos_bus::Delivery::Beat,
        )
        .await?;
        let target = TargetsMessage {
            stamp: 0.0,
            targets: vec![TargetObservation {
                name: "dog".into(),
                position: Vec3::new(0.0, 0.0, 0.0),
                velocity: Vec3::zeros(),
            }],
        };
        tacos_bus::put(
            &session,
            &keys.targets(),
            &target,
            tacos_bus::Delivery::Command,
        )
        .await?;
        // The victim's status: any bytes do, the router refuses it unread.
        session
            .put(status.as_str(), vec![0u8; 8])
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    println!("forged {} of each", args.count);
    session.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(())
}

//! `tacos-ground send` as a pilot runs it: started before the drone it names is heard (a ground
//! restarted in the field, a drone still reconnecting), it waits for the drone, then flies the
//! action to its end; a drone that never comes is refused with the drones it did hear.

use std::process::Stdio;
use std::time::Duration;
use tacos_ground::launch::{Stack, StackConfig};
use tacos_ground::link::{GroundLink, GroundRole};
use tacos_tests::unique_swarm;
use tokio::process::Command;

fn send_command(config: &StackConfig, args: &[&str]) -> Command {
    let mut cmd = Command::new(config.bin_dir.join("tacos-ground"));
    cmd.arg("send")
        .args(["--swarm", config.swarm.as_str()])
        .args(["--zenoh-connect", &config.hub_endpoint])
        .args(["--scenario", &config.scenario_arg])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true);
    cmd
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn send_waits_for_a_drone_that_comes_late_and_names_the_heard_ones_when_it_never_does()
-> anyhow::Result<()> {
    let scenario = tacos_bus::load_scenario("city")?;
    let config = StackConfig::on_loopback(unique_swarm("send"), "city", scenario, 1)?;
    // The hub the drones and `send` connect to.
    let _hub = GroundLink::connect_as(&config.ground_bus(), GroundRole::Monitor).await?;

    let late = send_command(&config, &["--wait-for-drone", "30", "alfa", "arm_takeoff"]).spawn()?;
    // The drone comes up well after the old 3 s `send` gave it.
    tokio::time::sleep(Duration::from_secs(6)).await;
    let stack = Stack::start(config.clone())?;
    let out = tokio::time::timeout(Duration::from_secs(90), late.wait_with_output()).await;
    let never = send_command(&config, &["--wait-for-drone", "2", "zulu", "hold"]).output();
    let never = tokio::time::timeout(Duration::from_secs(30), never).await;
    stack.shutdown(Duration::from_secs(3)).await;

    let out = out.map_err(|_| anyhow::anyhow!("send did not end within 90 s"))??;
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "send failed: {stdout}\n{stderr}");
    assert!(
        stderr.contains("waiting up to 30 s for alfa"),
        "it said it was waiting: {stderr}"
    );
    assert!(stdout.contains("alfa: arm_takeoff() done"), "{stdout}");

    let never = never.map_err(|_| anyhow::anyhow!("send to zulu did not end within 30 s"))??;
    let stderr = String::from_utf8_lossy(&never.stderr);
    assert!(
        !never.status.success(),
        "a send to a drone never heard succeeded"
    );
    assert!(
        stderr.contains("zulu was not heard within 3 s (heard: alfa)"),
        "{stderr}"
    );
    Ok(())
}

//! The writer's link to the autopilot: it sends from an ephemeral port (udpout), and only the
//! configured autopilot at its first address counts.

use super::*;

#[test]
fn udpout_sends_to_the_autopilot_from_an_ephemeral_port() {
    let swarm = unique_swarm("out");
    let node = IpcNode::new(&swarm, &drone()).expect("iceoryx2 node");
    let ports = node.onboard_ports().expect("onboard ports");
    let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
    let ap_addr = socket.local_addr().expect("addr");
    let autopilot = FakeAutopilot::listen(socket);
    // Our system id given explicitly this time.
    let writer = WriterProcess::start_with_link(
        &swarm,
        "0,0,0",
        &format!("udpout:{ap_addr}"),
        0,
        &["--sysid", "245"],
    );
    let up = poll_until(START_TIMEOUT, || {
        ports
            .state
            .drain()
            .ok()?
            .into_iter()
            .find(|s| s.link_ok == 1)
    });
    assert!(
        up.is_some(),
        "no link over udpout; log:\n{}",
        writer.log_text()
    );
    ports
        .send_setpoint(SetpointSample {
            seq: 1,
            position: [1.0, 2.0, 3.0],
            yaw: f64::NAN,
            ..Default::default()
        })
        .expect("send");
    let sp = autopilot.wait_for(Duration::from_secs(2), |s| {
        setpoints(s).first().map(|(_, sp)| sp.clone())
    });
    let sp = sp.unwrap_or_else(|| panic!("no setpoint over udpout; log:\n{}", writer.log_text()));
    assert_eq!((sp.x, sp.y, sp.z), (2.0, 1.0, -3.0));
    let ids: std::collections::BTreeSet<_> = autopilot
        .state()
        .received
        .iter()
        .map(|r| (r.header.system_id, r.header.component_id))
        .collect();
    assert_eq!(ids, [(245, 191)].into_iter().collect(), "--sysid 245");
}

#[test]
fn only_the_configured_autopilot_at_its_first_address_counts() {
    let swarm = unique_swarm("pin");
    let node = IpcNode::new(&swarm, &drone()).expect("iceoryx2 node");
    let ports = node.onboard_ports().expect("onboard ports");
    let writer = WriterProcess::start(
        &swarm,
        "0,0,0",
        free_udp_port(),
        &["--autopilot-sysid", "3"],
    );
    // System 1 talks first: not ours.
    let other = FakeAutopilot::start_as(writer.addr(), 1);
    std::thread::sleep(Duration::from_millis(600));
    let ours = FakeAutopilot::start_as(writer.addr(), 3);
    let up = poll_until(START_TIMEOUT, || {
        ports
            .state
            .drain()
            .ok()?
            .into_iter()
            .find(|s| s.link_ok == 1)
    });
    assert!(up.is_some(), "no link; log:\n{}", writer.log_text());
    // Once the link is up, system 3 from another address is ignored: it claims to be armed in
    // OFFBOARD, and the state must not follow it.
    let impostor = FakeAutopilot::start_configured(writer.addr(), 3, |ap| {
        ap.armed = true;
        ap.custom_mode = tacos_shared::px4_mode::Px4Mode::Offboard.custom_mode();
    });
    ports
        .send_command(CommandSample::new(1, CommandKind::Arm, 0.0))
        .expect("send command");
    let result = poll_until(Duration::from_secs(4), || {
        ports.results.drain().ok()?.into_iter().find(|r| r.seq == 1)
    });
    assert_eq!(
        result.and_then(|r| r.outcome()),
        Some(CommandOutcome::Accepted),
        "log:\n{}",
        writer.log_text()
    );
    let t0 = Instant::now();
    let mut modes = Vec::new();
    poll_until(Duration::from_secs(3), || {
        modes.extend(ports.state.drain().ok()?.into_iter().map(|s| s.mode()));
        (t0.elapsed() >= Duration::from_millis(1200)).then_some(())
    });
    assert!(!modes.is_empty());
    assert!(
        modes
            .iter()
            .all(|m| *m == tacos_shared::px4_mode::Px4Mode::Hold),
        "the impostor's mode got through: {modes:?}"
    );
    // Everything went to system 3 at its first address, as system 3, addressed to system 3.
    let s = ours.state();
    let arm = commands_of(&s, 400);
    assert_eq!(arm.len(), 1);
    assert_eq!((arm[0].1.target_system, arm[0].1.target_component), (3, 1));
    assert!(s.received.iter().all(|r| r.header.system_id == 3));
    assert!(s.armed);
    drop(s);
    assert!(other.state().received.is_empty(), "system 1 was talked to");
    assert!(
        impostor.state().received.is_empty(),
        "the second address was talked to"
    );
}

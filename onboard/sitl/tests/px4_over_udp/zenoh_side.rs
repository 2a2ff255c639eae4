//! The simulator's zenoh side: the ground truth it publishes and the faults it takes.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn publishes_truth_and_takes_faults_over_zenoh() {
    let swarm = unique_swarm("zenoh");
    let keys = Keys::new(&swarm);
    let endpoint = format!("tcp/127.0.0.1:{}", free_tcp_port());
    let test_bus = BusArgs::loopback(swarm.clone(), Some(endpoint.clone()), vec![]);
    let session = test_bus.open().await.expect("test session");
    let truth = tacos_bus::subscribe(&session, &keys.sim_truth())
        .await
        .expect("subscribe truth");
    let events = tacos_bus::subscribe(&session, &keys.events())
        .await
        .expect("subscribe events");
    let targets = tacos_bus::subscribe(&session, &keys.targets())
        .await
        .expect("subscribe targets");

    let mut sockets = consecutive_sockets(2).await;
    let mavlink_base = sockets[0].local_addr().expect("address").port();
    let sim_bus = BusArgs::loopback(
        swarm.clone(),
        Some("tcp/127.0.0.1:0".into()),
        vec![endpoint],
    );
    let sitl = Sitl::start(2, mavlink_base, sim_bus);
    let bravo_socket = sockets.remove(1);
    let bravo = Client::new(bravo_socket, sitl.sitl_base_port + 1, 2);
    bravo
        .wait_for(Duration::from_secs(10), "bravo's heartbeat", |h, m| {
            matches!(m, MavMessage::HEARTBEAT(_)).then_some(h.system_id)
        })
        .await;

    // Truth: both vehicles at their homes (world ENU), alive, landed.
    let lab = Scenario::builtin("lab").expect("valid");
    let deadline = Instant::now() + Duration::from_secs(10);
    let first: SimTruth = loop {
        let sample = timeout_at(deadline, truth.recv_async())
            .await
            .expect("truth in time")
            .expect("subscriber open");
        let t: SimTruth = tacos_bus::decode(&sample).expect("truth decodes");
        if !t.vehicles.is_empty() {
            break t;
        }
    };
    assert_eq!(first.vehicles.len(), 2);
    for (v, slot) in first.vehicles.iter().zip(&lab.drones) {
        assert_eq!(v.drone, slot.id);
        assert!(
            (v.position - slot.home).norm() < 1e-9,
            "{} at {:?}",
            v.drone,
            v.position
        );
        assert!(v.alive && v.landed && !v.armed && !v.link_down);
    }
    let sample = timeout(Duration::from_secs(5), targets.recv_async())
        .await
        .expect("targets in time")
        .expect("open");
    let t: TargetsMessage = tacos_bus::decode(&sample).expect("targets decode");
    assert!(t.targets.is_empty(), "the lab's dog is hidden");

    // Garbage on the fault key is ignored; a real request kills bravo.
    let faults = keys.sim_faults();
    session
        .put(&faults, vec![0xde, 0xad])
        .await
        .expect("put garbage");
    let request = FaultRequest {
        drone: DroneId::new("bravo").expect("valid"),
        fault: FaultKind::VehicleDies,
    };
    tacos_bus::put(&session, &faults, &request, tacos_bus::Delivery::Command)
        .await
        .expect("put fault");
    let sample = timeout(Duration::from_secs(5), events.recv_async())
        .await
        .expect("event in time")
        .expect("open");
    let event: WorldEvent = tacos_bus::decode(&sample).expect("event decodes");
    assert!(
        matches!(&event, WorldEvent::FaultInjected { drone, .. } if drone.as_str() == "bravo"),
        "{event:?}"
    );

    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let sample = timeout_at(deadline, truth.recv_async())
            .await
            .expect("truth shows the death")
            .expect("open");
        let t: SimTruth = tacos_bus::decode(&sample).expect("truth decodes");
        if t.vehicles.get(1).is_some_and(|v| !v.alive) {
            assert!(t.vehicles[0].alive, "alfa lives on");
            break;
        }
    }
    // Bravo is silent from now on. Drain what it sent before the fault (a live vehicle would
    // keep this loop busy until the deadline), then expect nothing at all for 2.5 s: heartbeats
    // are 1 Hz and LOCAL_POSITION_NED 30 Hz, so a live vehicle would be heard.
    let mut buf = [0u8; 2048];
    let drain_deadline = Instant::now() + Duration::from_secs(1);
    while let Ok(Ok(_)) = timeout_at(drain_deadline, bravo.socket.recv_from(&mut buf)).await {}
    let heard = timeout(
        Duration::from_millis(2500),
        bravo.socket.recv_from(&mut buf),
    )
    .await;
    assert!(heard.is_err(), "a dead vehicle still talks");

    sitl.stop().await;
    session.close().await.expect("close");
}

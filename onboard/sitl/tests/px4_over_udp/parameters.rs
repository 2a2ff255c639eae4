//! PX4's parameter protocol and the geofence upload, over UDP as a ground station speaks them.

use super::*;

/// What the writer does at link-up, over real UDP: parameters read and set (INT32 byte for
/// byte), a fence uploaded and read back, each reply addressed to this client.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parameters_and_the_geofence_over_udp() {
    let socket = consecutive_sockets(1).await.remove(0);
    let mavlink_port = socket.local_addr().expect("address").port();
    let bus = BusArgs::loopback(
        unique_swarm("setup"),
        Some("tcp/127.0.0.1:0".into()),
        vec![],
    );
    let sitl = Sitl::start(1, mavlink_port, bus);
    let mut px4 = Client::new(socket, sitl.sitl_base_port, 1);
    px4.wait_for(Duration::from_secs(10), "a heartbeat", |_, m| {
        matches!(m, MavMessage::HEARTBEAT(_)).then_some(())
    })
    .await;
    let id = tacos_sitl::params::param_id;
    let read = |name: &str| {
        MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
            param_index: -1,
            target_system: 1,
            target_component: 1,
            param_id: id(name),
        })
    };
    let value_of = |name: &'static str| {
        move |_: &MavHeader, m: &MavMessage| param_value(m).filter(|(n, _, _)| n == name)
    };
    px4.send(&read("COM_OBL_RC_ACT")).await;
    let (_, raw, kind) = px4
        .wait_for(
            Duration::from_secs(2),
            "COM_OBL_RC_ACT",
            value_of("COM_OBL_RC_ACT"),
        )
        .await;
    assert_eq!(
        (raw.to_bits(), kind),
        (0, MavParamType::MAV_PARAM_TYPE_INT32),
        "PX4's default"
    );
    px4.send(&MavMessage::PARAM_SET(PARAM_SET_DATA {
        param_value: f32::from_bits(5),
        target_system: 1,
        target_component: 1,
        param_id: id("COM_OBL_RC_ACT"),
        param_type: MavParamType::MAV_PARAM_TYPE_INT32,
    }))
    .await;
    let (_, raw, _) = px4
        .wait_for(
            Duration::from_secs(2),
            "the echo",
            value_of("COM_OBL_RC_ACT"),
        )
        .await;
    assert_eq!(raw.to_bits(), 5);
    px4.send(&read("COM_OF_LOSS_T")).await;
    let (_, value, kind) = px4
        .wait_for(
            Duration::from_secs(2),
            "COM_OF_LOSS_T",
            value_of("COM_OF_LOSS_T"),
        )
        .await;
    assert_eq!((value, kind), (1.0, MavParamType::MAV_PARAM_TYPE_REAL32));

    // The fence: count, a request per item, the ack; then the read-back.
    let fence = MavMissionType::MAV_MISSION_TYPE_FENCE;
    let corners = [(-1000, -1000), (-1000, 1000), (1000, 1000), (1000, -1000)];
    let item = |seq: u16| {
        let (dlat, dlon) = corners[usize::from(seq)];
        MISSION_ITEM_INT_DATA {
            param1: 4.0,
            x: 473_977_420 + dlat,
            y: 85_455_940 + dlon,
            seq,
            command: MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            target_system: 1,
            target_component: 1,
            frame: MavFrame::MAV_FRAME_GLOBAL,
            autocontinue: 1,
            mission_type: fence,
            ..Default::default()
        }
    };
    // PX4 addresses its mission messages to the client. The stand-in's pure link does that
    // (`link::handle_from`), but the simulation does not pass it the sender yet, so for now
    // they go to the broadcast address (0, 0).
    let to_us = |target_system: u8, target_component: u8| {
        let to = (u32::from(target_system), target_component);
        assert!(
            to == (GCS_SYSTEM, GCS_COMPONENT) || to == (0, 0),
            "addressed to {to:?}"
        );
    };
    px4.send(&MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
        count: 4,
        target_system: 1,
        target_component: 1,
        mission_type: fence,
        opaque_id: 0,
    }))
    .await;
    for seq in 0..4u16 {
        let asked = px4
            .wait_for(
                Duration::from_secs(2),
                "MISSION_REQUEST_INT",
                |_, m| match m {
                    MavMessage::MISSION_REQUEST_INT(r) if r.mission_type == fence => {
                        Some((r.seq, r.target_system, r.target_component))
                    }
                    _ => None,
                },
            )
            .await;
        assert_eq!(asked.0, seq);
        to_us(asked.1, asked.2);
        px4.send(&MavMessage::MISSION_ITEM_INT(item(seq))).await;
    }
    let ack = px4
        .wait_for(Duration::from_secs(2), "MISSION_ACK", |_, m| match m {
            MavMessage::MISSION_ACK(a) if a.mission_type == fence => Some(a.clone()),
            _ => None,
        })
        .await;
    assert_eq!(ack.mavtype, MavMissionResult::MAV_MISSION_ACCEPTED);
    to_us(ack.target_system, ack.target_component);
    px4.send(&MavMessage::MISSION_REQUEST_LIST(
        MISSION_REQUEST_LIST_DATA {
            target_system: 1,
            target_component: 1,
            mission_type: fence,
        },
    ))
    .await;
    let count = px4
        .wait_for(Duration::from_secs(2), "MISSION_COUNT", |_, m| match m {
            MavMessage::MISSION_COUNT(c) if c.mission_type == fence => Some(c.count),
            _ => None,
        })
        .await;
    assert_eq!(count, 4);
    for seq in 0..4u16 {
        px4.send(&MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq,
            target_system: 1,
            target_component: 1,
            mission_type: fence,
        }))
        .await;
        let got = px4
            .wait_for(Duration::from_secs(2), "MISSION_ITEM_INT", |_, m| match m {
                MavMessage::MISSION_ITEM_INT(i) if i.mission_type == fence => Some(i.clone()),
                _ => None,
            })
            .await;
        let want = item(seq);
        assert_eq!(
            (got.seq, got.x, got.y, got.param1),
            (seq, want.x, want.y, 4.0)
        );
        assert_eq!(got.command, want.command);
    }
    px4.send(&MavMessage::MISSION_ACK(MISSION_ACK_DATA {
        target_system: 1,
        target_component: 1,
        mavtype: MavMissionResult::MAV_MISSION_ACCEPTED,
        mission_type: fence,
        opaque_id: 0,
    }))
    .await;
    sitl.stop().await;
}

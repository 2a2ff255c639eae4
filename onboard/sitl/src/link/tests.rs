//! Tests of the MAVLink ↔ vehicle link: commands, acks, protocols, as PX4 answers them.

use super::*;
use crate::streams::LinkProfile;
use crate::telemetry;
use crate::vehicle::VehicleParams;
use mavlink::dialects::common::{COMMAND_LONG_DATA, MavAutopilot, MavModeFlag, MavState};
use tacos_shared::px4_mode::{self, Px4Mode};
use tacos_shared::scenario::Scenario;

fn vehicle() -> Vehicle {
    let lab = Scenario::builtin("lab").expect("lab is valid");
    Vehicle::new(VehicleParams {
        readiness_delay: 0.0,
        ..VehicleParams::from_limits(&lab.limits)
    })
}

fn streams() -> Streams {
    Streams::new(LinkProfile::Onboard, 0.0)
}

fn header(system_id: u32) -> MavHeader {
    MavHeader {
        system_id,
        component_id: AUTOPILOT_COMPONENT,
        sequence: 7,
    }
}

#[test]
fn frames_round_trip_and_several_fit_in_one_datagram() {
    let v = vehicle();
    let mut datagram = encode(header(3), &telemetry::heartbeat(&v));
    datagram.extend(encode(header(3), &telemetry::local_position(&v)));
    assert_eq!(datagram[0], mavlink::MAV_STX_V2);
    let (messages, bad) = decode_datagram(&datagram);
    assert_eq!(bad, 0);
    assert_eq!(messages.len(), 2);
    assert_eq!(messages[0].0.system_id, 3);
    let MavMessage::HEARTBEAT(hb) = &messages[0].1 else {
        panic!("{messages:?}")
    };
    assert_eq!(Px4Mode::from_custom_mode(hb.custom_mode), Px4Mode::Hold);
    assert_eq!(hb.autopilot, MavAutopilot::MAV_AUTOPILOT_PX4);
    assert!(
        hb.base_mode
            .contains(MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    );
    assert!(
        !hb.base_mode
            .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED)
    );
    assert_eq!(hb.system_status, MavState::MAV_STATE_STANDBY);
}

#[test]
fn garbage_is_skipped() {
    let v = vehicle();
    let mut datagram = vec![0xfd, 0x09, 0x00, 0x13, 0x37];
    datagram.extend(encode(header(1), &telemetry::heartbeat(&v)));
    let (messages, _) = decode_datagram(&datagram);
    assert_eq!(messages.len(), 1);
    assert!(decode_datagram(&[]).0.is_empty());
    assert!(decode_datagram(&[0xfd; 300]).0.is_empty());
}

fn command(target_system: u8, command: MavCmd, params: [f32; 7]) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: params[0],
        param2: params[1],
        param3: params[2],
        param4: params[3],
        param5: params[4],
        param6: params[5],
        param7: params[6],
        command,
        target_system,
        target_component: 1,
        confirmation: 0,
    })
}

fn results(handled: Handled) -> Vec<MavResult> {
    match handled {
        Handled::Command { results, .. } => results,
        other => panic!("{other:?}"),
    }
}

const ARM: [f32; 7] = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];

#[test]
fn commands_for_other_systems_or_components_are_ignored() {
    let mut v = vehicle();
    let mut s = streams();
    let arm = command(2, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, ARM);
    assert_eq!(handle(&mut v, &mut s, 1, &arm, 0.0), Handled::NotForUs);
    let MavMessage::COMMAND_LONG(mut to_camera) = arm.clone() else {
        panic!()
    };
    to_camera.target_component = 100;
    let to_camera = MavMessage::COMMAND_LONG(to_camera);
    assert_eq!(
        handle(&mut v, &mut s, 2, &to_camera, 0.0),
        Handled::NotForUs
    );
    assert!(!v.armed());
    assert_eq!(
        results(handle(&mut v, &mut s, 2, &arm, 0.0)),
        vec![MavResult::MAV_RESULT_ACCEPTED]
    );
    assert!(v.armed());
    assert_eq!(
        command_ack(
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            MavResult::MAV_RESULT_ACCEPTED,
            245,
            191
        ),
        MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
            command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            result: MavResult::MAV_RESULT_ACCEPTED,
            progress: 0,
            result_param2: 0,
            target_system: 245,
            target_component: 191,
        })
    );
}

#[test]
fn do_set_mode_is_acked_twice() {
    let mut v = vehicle();
    let mut s = streams();
    let mode = |main: u8, sub: u8| {
        command(
            1,
            MavCmd::MAV_CMD_DO_SET_MODE,
            [1.0, f32::from(main), f32::from(sub), 0.0, 0.0, 0.0, 0.0],
        )
    };
    assert_eq!(
        results(handle(
            &mut v,
            &mut s,
            1,
            &mode(px4_mode::MAIN_AUTO, px4_mode::AUTO_LOITER),
            0.0
        )),
        vec![
            MavResult::MAV_RESULT_ACCEPTED,
            MavResult::MAV_RESULT_ACCEPTED
        ]
    );
    handle(
        &mut v,
        &mut s,
        1,
        &command(1, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, ARM),
        0.0,
    );
    // Armed with no setpoint stream: the receiver accepts, commander refuses.
    assert_eq!(
        results(handle(
            &mut v,
            &mut s,
            1,
            &mode(px4_mode::MAIN_OFFBOARD, 0),
            0.0
        )),
        vec![
            MavResult::MAV_RESULT_ACCEPTED,
            MavResult::MAV_RESULT_TEMPORARILY_REJECTED
        ]
    );
    assert_eq!(v.mode(), Px4Mode::Hold);
}

#[test]
fn message_intervals_and_requests() {
    let mut v = vehicle();
    let mut s = streams();
    let interval = |id: f32, us: f32| {
        command(
            1,
            MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
            [id, us, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
    };
    assert_eq!(
        results(handle(&mut v, &mut s, 1, &interval(32.0, 50_000.0), 0.0)),
        vec![MavResult::MAV_RESULT_ACCEPTED]
    );
    assert!(
        s.period(Stream::LocalPosition)
            .is_some_and(|p| (p - 0.05).abs() < 1e-12)
    );
    assert_eq!(
        results(handle(&mut v, &mut s, 1, &interval(0.0, 50_000.0), 0.0)),
        vec![MavResult::MAV_RESULT_FAILED],
        "HEARTBEAT's rate is fixed"
    );
    let request = |id: f32| {
        command(
            1,
            MavCmd::MAV_CMD_REQUEST_MESSAGE,
            [id, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
    };
    assert_eq!(
        handle(&mut v, &mut s, 1, &request(242.0), 0.0),
        Handled::Command {
            command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
            results: vec![MavResult::MAV_RESULT_ACCEPTED],
            requested: Some(Stream::HomePosition),
        }
    );
    assert_eq!(
        handle(&mut v, &mut s, 1, &request(147.0), 0.0),
        Handled::Command {
            command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
            results: vec![MavResult::MAV_RESULT_DENIED],
            requested: None,
        }
    );
}

fn setpoint(mask: u16, frame: MavFrame) -> SET_POSITION_TARGET_LOCAL_NED_DATA {
    SET_POSITION_TARGET_LOCAL_NED_DATA {
        time_boot_ms: 0,
        x: 1.0,
        y: 2.0,
        z: -3.0,
        vx: 0.5,
        vy: f32::NAN,
        vz: 0.0,
        afx: 0.0,
        afy: 0.0,
        afz: 0.0,
        yaw: 0.0,
        yaw_rate: 0.0,
        type_mask: PositionTargetTypemask::from_bits_truncate(mask),
        target_system: 1,
        target_component: 1,
        coordinate_frame: frame,
    }
}

#[test]
fn type_mask_selects_the_fields() {
    // Position only: velocity, acceleration, yaw and yaw rate ignored (what MAVSDK sends).
    let position_only = 0b0000_1101_1111_1000;
    let r = setpoint_reference(&setpoint(position_only, MavFrame::MAV_FRAME_LOCAL_NED))
        .expect("usable");
    assert_eq!(r.position, [Some(1.0), Some(2.0), Some(-3.0)]);
    assert_eq!(r.velocity, [None; 3]);
    assert_eq!(r.acceleration, [None; 3]);
    // Position + velocity; the NaN vy is dropped.
    let r = setpoint_reference(&setpoint(
        0b0000_1101_1100_0000,
        MavFrame::MAV_FRAME_LOCAL_NED,
    ))
    .expect("usable");
    assert_eq!(r.velocity, [Some(0.5), None, Some(0.0)]);
    // Everything ignored, or another frame: nothing to fly.
    assert!(setpoint_reference(&setpoint(0x0fff, MavFrame::MAV_FRAME_LOCAL_NED)).is_none());
    assert!(setpoint_reference(&setpoint(position_only, MavFrame::MAV_FRAME_BODY_FRD)).is_none());
}

/// What goes out with the next telemetry: the queued replies as messages.
fn sent(v: &Vehicle, s: &mut Streams) -> Vec<MavMessage> {
    let frame = crate::geo::LocalFrame {
        origin: Default::default(),
        spawn_enu: tacos_shared::Vec3::zeros(),
    };
    s.due(1e9)
        .into_iter()
        .filter(|st| matches!(st, Stream::Reply(_)))
        .map(|st| telemetry::stream_message(st, v, &frame))
        .collect()
}

fn param_request(name: &str, index: i16, target_system: u8) -> MavMessage {
    MavMessage::PARAM_REQUEST_READ(mavlink::dialects::common::PARAM_REQUEST_READ_DATA {
        param_index: index,
        target_system,
        target_component: 1,
        param_id: crate::params::param_id(name),
    })
}

fn param_values(messages: &[MavMessage]) -> Vec<(String, f32, MavParamType, u16, u16)> {
    messages
        .iter()
        .filter_map(|m| match m {
            MavMessage::PARAM_VALUE(p) => Some((
                name_of(&p.param_id[..]),
                p.param_value,
                p.param_type,
                p.param_index,
                p.param_count,
            )),
            _ => None,
        })
        .collect()
}

use mavlink::dialects::common::MavParamType;

#[test]
fn parameters_are_read_and_set_as_px4_does() {
    let mut v = vehicle();
    let mut s = streams();
    s.due(0.0);
    let int32 = MavParamType::MAV_PARAM_TYPE_INT32;
    // By name: COM_OBL_RC_ACT = 0, an INT32.
    assert_eq!(
        handle(
            &mut v,
            &mut s,
            1,
            &param_request("COM_OBL_RC_ACT", -1, 1),
            0.0
        ),
        Handled::Protocol { replies: 1 }
    );
    assert_eq!(
        param_values(&sent(&v, &mut s)),
        vec![("COM_OBL_RC_ACT".into(), 0.0, int32, 0, 8)]
    );
    // By index: 1 is COM_OF_LOSS_T = 1.0, a REAL32.
    handle(&mut v, &mut s, 1, &param_request("", 1, 1), 0.0);
    assert_eq!(
        param_values(&sent(&v, &mut s)),
        vec![(
            "COM_OF_LOSS_T".into(),
            1.0,
            MavParamType::MAV_PARAM_TYPE_REAL32,
            1,
            8
        )]
    );
    // Unknown: no answer at all. Another system's: not ours.
    assert_eq!(
        handle(
            &mut v,
            &mut s,
            1,
            &param_request("NO_SUCH_PARAM", -1, 1),
            0.0
        ),
        Handled::Protocol { replies: 0 }
    );
    assert_eq!(
        handle(
            &mut v,
            &mut s,
            1,
            &param_request("COM_OBL_RC_ACT", -1, 2),
            0.0
        ),
        Handled::NotForUs
    );
    assert!(sent(&v, &mut s).is_empty());
    // Set 5 byte for byte: echoed, and the vehicle now holds on offboard loss.
    let set = |value: f32, name: &str| {
        MavMessage::PARAM_SET(mavlink::dialects::common::PARAM_SET_DATA {
            param_value: value,
            target_system: 1,
            target_component: 1,
            param_id: crate::params::param_id(name),
            param_type: int32,
        })
    };
    handle(
        &mut v,
        &mut s,
        1,
        &set(f32::from_bits(5), "COM_OBL_RC_ACT"),
        0.0,
    );
    let echo = param_values(&sent(&v, &mut s));
    assert_eq!(echo.len(), 1);
    assert_eq!((echo[0].1.to_bits(), echo[0].2), (5, int32));
    assert_eq!(
        v.px4_params().offboard_loss_action(),
        crate::params::OffboardLossAction::Hold
    );
    handle(&mut v, &mut s, 1, &set(1.0, "NO_SUCH_PARAM"), 0.0);
    assert!(sent(&v, &mut s).is_empty(), "no echo for an unknown name");
    // The whole table.
    let list = MavMessage::PARAM_REQUEST_LIST(mavlink::dialects::common::PARAM_REQUEST_LIST_DATA {
        target_system: 1,
        target_component: 0,
    });
    assert_eq!(
        handle(&mut v, &mut s, 1, &list, 0.0),
        Handled::Protocol { replies: 8 }
    );
    let all = param_values(&sent(&v, &mut s));
    assert_eq!(
        all.iter().map(|p| p.3).collect::<Vec<_>>(),
        (0..8).collect::<Vec<_>>()
    );
}

#[test]
fn the_geofence_is_uploaded_and_read_back_to_its_sender() {
    use mavlink::dialects::common::{
        MISSION_COUNT_DATA, MISSION_ITEM_INT_DATA, MISSION_REQUEST_INT_DATA,
        MISSION_REQUEST_LIST_DATA,
    };
    let mut v = vehicle();
    let mut s = streams();
    s.due(0.0);
    let fence = MavMissionType::MAV_MISSION_TYPE_FENCE;
    let writer = (1, 191);
    let from_writer = |v: &mut Vehicle, s: &mut Streams, m: MavMessage| -> Vec<MavMessage> {
        handle_from(v, s, 1, writer, &m, 0.0);
        sent(v, s)
    };
    let item = |seq: u16| {
        MavMessage::MISSION_ITEM_INT(MISSION_ITEM_INT_DATA {
            param1: 4.0,
            x: 473_977_420 + i32::from(seq % 2) * 1000,
            y: 85_455_940 + i32::from(seq / 2) * 1000,
            seq,
            command: MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            target_system: 1,
            target_component: 1,
            frame: MavFrame::MAV_FRAME_GLOBAL,
            autocontinue: 1,
            mission_type: fence,
            ..Default::default()
        })
    };
    let count = MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
        count: 4,
        target_system: 1,
        target_component: 1,
        mission_type: fence,
        opaque_id: 0,
    });
    let mut out = from_writer(&mut v, &mut s, count);
    for seq in 0..4u16 {
        match out.as_slice() {
            [MavMessage::MISSION_REQUEST_INT(r)] => {
                assert_eq!((r.seq, r.mission_type), (seq, fence));
                assert_eq!((r.target_system, r.target_component), writer);
            }
            other => panic!("expected a request for {seq}, got {other:?}"),
        }
        out = from_writer(&mut v, &mut s, item(seq));
    }
    match out.as_slice() {
        [MavMessage::MISSION_ACK(a)] => {
            assert_eq!(
                (
                    a.mavtype,
                    a.mission_type,
                    a.target_system,
                    a.target_component
                ),
                (MavMissionResult::MAV_MISSION_ACCEPTED, fence, 1, 191)
            );
        }
        other => panic!("expected the ack, got {other:?}"),
    }
    assert_eq!(v.geofence().items().len(), 4);

    let list = MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
        target_system: 1,
        target_component: 1,
        mission_type: fence,
    });
    match from_writer(&mut v, &mut s, list).as_slice() {
        [MavMessage::MISSION_COUNT(c)] => assert_eq!((c.count, c.mission_type), (4, fence)),
        other => panic!("expected the count, got {other:?}"),
    }
    for seq in 0..4u16 {
        let request = MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq,
            target_system: 1,
            target_component: 1,
            mission_type: fence,
        });
        match (from_writer(&mut v, &mut s, request).as_slice(), item(seq)) {
            ([MavMessage::MISSION_ITEM_INT(got)], MavMessage::MISSION_ITEM_INT(want)) => {
                assert_eq!(
                    (got.seq, got.x, got.y, got.command),
                    (seq, want.x, want.y, want.command)
                );
                assert_eq!(
                    (got.param1, got.frame, got.mission_type),
                    (4.0, want.frame, fence)
                );
                assert_eq!((got.target_system, got.target_component), writer);
            }
            (other, _) => panic!("expected item {seq}, got {other:?}"),
        }
    }
    // A mission (not a fence) is not modelled.
    let mission = MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
        count: 1,
        target_system: 1,
        target_component: 1,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        opaque_id: 0,
    });
    match from_writer(&mut v, &mut s, mission).as_slice() {
        [MavMessage::MISSION_ACK(a)] => {
            assert_eq!(a.mavtype, MavMissionResult::MAV_MISSION_UNSUPPORTED)
        }
        other => panic!("{other:?}"),
    }
}

//! MAVLink ↔ [`Vehicle`]: framing, and what an incoming message does to the vehicle and its
//! link's streams. Pure (bytes in, bytes out); what goes out about the vehicle is in
//! `telemetry`, the sockets live in `runtime`.
//!
//! Commands are answered at once ([`Handled::Command`]: the caller sends the acks). The
//! parameter protocol ([`crate::params`]) and the geofence's mission protocol
//! ([`crate::fence`]) are answered through the link's [`Streams`]: their replies are queued
//! there and go out with the next telemetry, before the streams that are due.

use crate::motion::Reference;
use crate::params::name_of;
use crate::streams::{Reply, Stream, Streams};
use crate::vehicle::Vehicle;
use mavlink::dialects::common::{
    COMMAND_ACK_DATA, MavCmd, MavFrame, MavMessage, MavMissionResult, MavMissionType, MavResult,
    PositionTargetTypemask, SET_POSITION_TARGET_LOCAL_NED_DATA,
};
use mavlink::{MavHeader, MavlinkReader};

/// MAV_COMP_ID_AUTOPILOT1.
pub const AUTOPILOT_COMPONENT: u8 = 1;
/// MAV_COMP_ID_MISSIONPLANNER: PX4's mission manager takes it as its own.
pub const MISSION_PLANNER_COMPONENT: u8 = 190;

/// Encodes one MAVLink v2 frame.
pub fn encode(header: MavHeader, message: &MavMessage) -> Vec<u8> {
    let mut out = Vec::with_capacity(64);
    // Writing into a Vec cannot fail; an error here would be a bug in the message itself.
    if let Err(e) = mavlink::write_v2_msg(&mut out, header, message) {
        tracing::error!("could not encode MAVLink message: {e}");
        out.clear();
    }
    out
}

/// Every CRC-valid frame of the common dialect in one datagram (v1 or v2), in order. Frames that
/// do not parse are skipped; the count of those comes back too.
pub fn decode_datagram(bytes: &[u8]) -> (Vec<(MavHeader, MavMessage)>, usize) {
    let mut reader = MavlinkReader::new(bytes);
    let mut messages = Vec::new();
    let mut bad = 0;
    loop {
        match reader.read_any_message::<MavMessage>() {
            Ok(m) => messages.push(m),
            Err(mavlink::error::MessageReadError::Parse(_)) => bad += 1,
            // End of the datagram.
            Err(mavlink::error::MessageReadError::Io(_)) => break,
        }
    }
    (messages, bad)
}

/// COMMAND_ACK as PX4 sends it: addressed to the command's sender, progress 0.
pub fn command_ack(
    command: MavCmd,
    result: MavResult,
    target_system: u8,
    target_component: u8,
) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command,
        result,
        progress: 0,
        result_param2: 0,
        target_system,
        target_component,
    })
}

/// What an incoming message did, for the replies, the runtime's counters and logs.
#[derive(Debug, Clone, PartialEq)]
pub enum Handled {
    /// A command was executed. `results` holds one COMMAND_ACK result each, in the order they
    /// go out: two for DO_SET_MODE (PX4's MAVLink receiver accepts it at once, then commander
    /// answers), one otherwise. `requested` is a message REQUEST_MESSAGE asked for, sent
    /// before the ack.
    Command {
        command: MavCmd,
        results: Vec<MavResult>,
        requested: Option<Stream>,
    },
    Setpoint,
    /// A setpoint in a frame the simulator does not fly (PX4 ignores those too).
    IgnoredSetpoint,
    /// A message of the parameter or mission protocol: `replies` were queued on the link's
    /// streams (0: PX4 says nothing, e.g. to a parameter name it does not have).
    Protocol {
        replies: usize,
    },
    /// Addressed to another system or component, or a message the simulator has no use for.
    NotForUs,
}

/// Applies one incoming message to the vehicle with MAVLink system id `system_id` and to its
/// link's `streams` (at sim time `now`). Mission replies go to the broadcast address: use
/// [`handle_from`] to address them to the sender, as PX4 does.
pub fn handle(
    vehicle: &mut Vehicle,
    streams: &mut Streams,
    system_id: u8,
    message: &MavMessage,
    now: f64,
) -> Handled {
    handle_from(vehicle, streams, system_id, (0, 0), message, now)
}

/// [`handle`] for a message from `sender` (its system and component ids, from the frame's
/// header), to which mission replies are addressed.
// MAV_CMD_GET_HOME_POSITION is deprecated, but PX4 still answers it.
#[allow(deprecated)]
pub fn handle_from(
    vehicle: &mut Vehicle,
    streams: &mut Streams,
    system_id: u8,
    sender: (u8, u8),
    message: &MavMessage,
    now: f64,
) -> Handled {
    // PX4 main takes its own system id or 0, and component 1 (autopilot) or 0.
    let for_us = |system: u8, component: u8| {
        (system == 0 || system == system_id) && (component == 0 || component == AUTOPILOT_COMPONENT)
    };
    // Its parameter and mission managers want their own system id exactly; the mission
    // manager also answers for the mission planner component.
    let params_for_us = |system: u8, component: u8| {
        system == system_id && (component == 0 || component == AUTOPILOT_COMPONENT)
    };
    let mission_for_us = |system: u8, component: u8| {
        params_for_us(system, component)
            || (system == system_id && component == MISSION_PLANNER_COMPONENT)
    };
    if let Some(replies) = protocol(vehicle, message, sender, &params_for_us, &mission_for_us) {
        let count = replies.len();
        streams.reply_all(replies);
        return Handled::Protocol { replies: count };
    }
    match message {
        MavMessage::COMMAND_LONG(c) if for_us(c.target_system, c.target_component) => {
            let params = [
                c.param1, c.param2, c.param3, c.param4, c.param5, c.param6, c.param7,
            ];
            let mut requested = None;
            let results = match c.command {
                MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                    vec![streams.set_interval(c.param1, c.param2, now)]
                }
                MavCmd::MAV_CMD_REQUEST_MESSAGE | MavCmd::MAV_CMD_GET_HOME_POSITION => {
                    requested = if c.command == MavCmd::MAV_CMD_GET_HOME_POSITION {
                        Some(Stream::HomePosition)
                    } else {
                        Stream::from_param(c.param1)
                    };
                    // PX4 sends the message, then ACCEPTED; DENIED for one it cannot send.
                    vec![if requested.is_some() {
                        MavResult::MAV_RESULT_ACCEPTED
                    } else {
                        MavResult::MAV_RESULT_DENIED
                    }]
                }
                MavCmd::MAV_CMD_DO_SET_MODE => vec![
                    MavResult::MAV_RESULT_ACCEPTED,
                    vehicle.handle_command(c.command, params),
                ],
                _ => vec![vehicle.handle_command(c.command, params)],
            };
            Handled::Command {
                command: c.command,
                results,
                requested,
            }
        }
        MavMessage::SET_POSITION_TARGET_LOCAL_NED(s)
            if for_us(s.target_system, s.target_component) =>
        {
            match setpoint_reference(s) {
                Some(reference) => {
                    vehicle.handle_setpoint(reference);
                    Handled::Setpoint
                }
                None => Handled::IgnoredSetpoint,
            }
        }
        _ => Handled::NotForUs,
    }
}

/// The parameter and mission protocols: `None` when `message` is neither (or not for us),
/// else the replies, in order.
fn protocol(
    vehicle: &mut Vehicle,
    message: &MavMessage,
    sender: (u8, u8),
    params_for_us: &dyn Fn(u8, u8) -> bool,
    mission_for_us: &dyn Fn(u8, u8) -> bool,
) -> Option<Vec<Reply>> {
    let fence = MavMissionType::MAV_MISSION_TYPE_FENCE;
    let index = |i: usize| u16::try_from(i).ok().map(Reply::ParamValue);
    // Missions and rally points are not modelled: nothing to download, no upload taken.
    let unsupported = |mission_type| {
        vec![Reply::MissionAck(
            mission_type,
            MavMissionResult::MAV_MISSION_UNSUPPORTED,
        )]
    };
    Some(match message {
        MavMessage::PARAM_REQUEST_READ(r) if params_for_us(r.target_system, r.target_component) => {
            let params = vehicle.px4_params();
            let found = match usize::try_from(r.param_index) {
                Ok(i) => (i < params.len()).then_some(i),
                // -1: by name.
                Err(_) => params.index_of(&name_of(&r.param_id[..])),
            };
            found.and_then(index).into_iter().collect()
        }
        MavMessage::PARAM_REQUEST_LIST(r) if params_for_us(r.target_system, r.target_component) => {
            (0..vehicle.px4_params().len()).filter_map(index).collect()
        }
        MavMessage::PARAM_SET(p) if params_for_us(p.target_system, p.target_component) => {
            let params = vehicle.px4_params_mut();
            match params.index_of(&name_of(&p.param_id[..])) {
                Some(i) => {
                    params.set_from_wire(i, p.param_value);
                    index(i).into_iter().collect()
                }
                None => Vec::new(),
            }
        }
        MavMessage::MISSION_COUNT(c) if mission_for_us(c.target_system, c.target_component) => {
            if c.mission_type == fence {
                vehicle.geofence_mut().on_count(c.count, sender)
            } else {
                unsupported(c.mission_type)
            }
        }
        MavMessage::MISSION_ITEM_INT(i) if mission_for_us(i.target_system, i.target_component) => {
            if i.mission_type == fence {
                vehicle.geofence_mut().on_item(i, sender)
            } else {
                unsupported(i.mission_type)
            }
        }
        MavMessage::MISSION_REQUEST_LIST(r)
            if mission_for_us(r.target_system, r.target_component) =>
        {
            if r.mission_type == fence {
                vehicle.geofence_mut().on_request_list(sender)
            } else {
                vec![Reply::MissionCount(r.mission_type)]
            }
        }
        MavMessage::MISSION_REQUEST_INT(r)
            if mission_for_us(r.target_system, r.target_component) =>
        {
            if r.mission_type == fence {
                vehicle.geofence_mut().on_request(r.seq, sender)
            } else {
                vec![Reply::MissionAck(
                    r.mission_type,
                    MavMissionResult::MAV_MISSION_INVALID_SEQUENCE,
                )]
            }
        }
        MavMessage::MISSION_CLEAR_ALL(c) if mission_for_us(c.target_system, c.target_component) => {
            if c.mission_type == fence {
                vehicle.geofence_mut().on_clear(sender)
            } else {
                unsupported(c.mission_type)
            }
        }
        // The client closes a download: nothing to answer.
        MavMessage::MISSION_ACK(a) if mission_for_us(a.target_system, a.target_component) => {
            Vec::new()
        }
        _ => return None,
    })
}

/// The controller reference a SET_POSITION_TARGET_LOCAL_NED asks for, honouring `type_mask`
/// (a set bit = ignore that field). `None` when the frame is not MAV_FRAME_LOCAL_NED or nothing
/// usable is left. Non-finite values count as ignored.
pub fn setpoint_reference(s: &SET_POSITION_TARGET_LOCAL_NED_DATA) -> Option<Reference> {
    if s.coordinate_frame != MavFrame::MAV_FRAME_LOCAL_NED {
        return None;
    }
    let mask = s.type_mask;
    let pick = |value: f32, ignore: PositionTargetTypemask| {
        (!mask.contains(ignore) && value.is_finite()).then_some(f64::from(value))
    };
    use PositionTargetTypemask as M;
    let reference = Reference {
        position: [
            pick(s.x, M::POSITION_TARGET_TYPEMASK_X_IGNORE),
            pick(s.y, M::POSITION_TARGET_TYPEMASK_Y_IGNORE),
            pick(s.z, M::POSITION_TARGET_TYPEMASK_Z_IGNORE),
        ],
        velocity: [
            pick(s.vx, M::POSITION_TARGET_TYPEMASK_VX_IGNORE),
            pick(s.vy, M::POSITION_TARGET_TYPEMASK_VY_IGNORE),
            pick(s.vz, M::POSITION_TARGET_TYPEMASK_VZ_IGNORE),
        ],
        acceleration: [
            pick(s.afx, M::POSITION_TARGET_TYPEMASK_AX_IGNORE),
            pick(s.afy, M::POSITION_TARGET_TYPEMASK_AY_IGNORE),
            pick(s.afz, M::POSITION_TARGET_TYPEMASK_AZ_IGNORE),
        ],
    };
    let anything = reference
        .position
        .iter()
        .chain(&reference.velocity)
        .chain(&reference.acceleration)
        .any(Option::is_some);
    anything.then_some(reference)
}

#[cfg(test)]
mod tests {
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
        assert!(
            setpoint_reference(&setpoint(position_only, MavFrame::MAV_FRAME_BODY_FRD)).is_none()
        );
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
        let list =
            MavMessage::PARAM_REQUEST_LIST(mavlink::dialects::common::PARAM_REQUEST_LIST_DATA {
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
}

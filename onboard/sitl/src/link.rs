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
mod tests;

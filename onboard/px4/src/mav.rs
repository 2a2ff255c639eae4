//! MAVLink v2 framing over byte buffers: the messages the writer sends and a tolerant decoder of
//! datagrams. Pure (no sockets), so the encodings are tested on their own.

use crate::commands::{CommandLong, mav_cmd};
use crate::convert::{NedTarget, type_mask};
use crate::fence::FenceRequest;
use crate::params::ParamRequest;
use crate::setup::SetupRequest;
use mavlink::dialects::common::{
    COMMAND_LONG_DATA, HEARTBEAT_DATA, MavAutopilot, MavCmd, MavFrame, MavMessage, MavModeFlag,
    MavState, MavType, PositionTargetTypemask, SET_POSITION_TARGET_LOCAL_NED_DATA,
};
use mavlink::{MavHeader, MavlinkReader, error::MessageReadError};

/// MAV_COMP_ID_ONBOARD_COMPUTER: our component id.
pub const OUR_COMPONENT: u8 = 191;
/// MAV_COMP_ID_AUTOPILOT1: the autopilot's component id.
pub const AUTOPILOT_COMPONENT: u8 = 1;

/// Numbers every frame we send needs.
#[derive(Debug, Clone, Copy)]
pub struct Encoder {
    sysid: u8,
    sequence: u8,
}

impl Encoder {
    pub fn new(sysid: u8) -> Self {
        Encoder { sysid, sequence: 0 }
    }

    /// Frames `msg` as MAVLink v2 from (our sysid, component 191), with the next sequence number.
    pub fn encode(&mut self, msg: &MavMessage) -> Vec<u8> {
        let header = MavHeader {
            system_id: u32::from(self.sysid),
            component_id: OUR_COMPONENT,
            sequence: self.sequence,
        };
        self.sequence = self.sequence.wrapping_add(1);
        let mut out = Vec::with_capacity(64);
        // Writing into a Vec cannot fail; an error here would be a mavlink-crate bug, and the
        // frame is then simply empty (the caller skips empty frames).
        if mavlink::write_v2_msg(&mut out, header, msg).is_err() {
            out.clear();
        }
        out
    }
}

/// Our HEARTBEAT: an onboard controller, not an autopilot.
pub fn heartbeat() -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
        autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

/// SET_POSITION_TARGET_LOCAL_NED for `target` (already in the vehicle's NED frame).
pub fn set_position_target(
    target: &NedTarget,
    time_boot_ms: u32,
    target_system: u8,
    target_component: u8,
) -> MavMessage {
    let f = |v: f64| v as f32;
    MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
        time_boot_ms,
        x: f(target.position.x),
        y: f(target.position.y),
        z: f(target.position.z),
        vx: f(target.velocity.x),
        vy: f(target.velocity.y),
        vz: f(target.velocity.z),
        afx: f(target.acceleration.x),
        afy: f(target.acceleration.y),
        afz: f(target.acceleration.z),
        yaw: target.yaw.map_or(0.0, f),
        yaw_rate: 0.0,
        type_mask: PositionTargetTypemask::from_bits_truncate(type_mask(target)),
        target_system,
        target_component,
        coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
    })
}

fn mav_cmd(command: u16) -> Option<MavCmd> {
    Some(match command {
        mav_cmd::NAV_LAND => MavCmd::MAV_CMD_NAV_LAND,
        mav_cmd::NAV_TAKEOFF => MavCmd::MAV_CMD_NAV_TAKEOFF,
        mav_cmd::DO_SET_MODE => MavCmd::MAV_CMD_DO_SET_MODE,
        mav_cmd::COMPONENT_ARM_DISARM => MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        mav_cmd::SET_MESSAGE_INTERVAL => MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
        mav_cmd::REQUEST_MESSAGE => MavCmd::MAV_CMD_REQUEST_MESSAGE,
        _ => return None,
    })
}

/// COMMAND_LONG for `cmd`; `None` for a command id this writer does not know.
pub fn command_long(
    cmd: &CommandLong,
    target_system: u8,
    target_component: u8,
) -> Option<MavMessage> {
    let [param1, param2, param3, param4, param5, param6, param7] = cmd.params;
    Some(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1,
        param2,
        param3,
        param4,
        param5,
        param6,
        param7,
        command: mav_cmd(cmd.command)?,
        target_system,
        target_component,
        confirmation: cmd.confirmation,
    }))
}

fn param_id(name: &str) -> mavlink::types::CharArray<16> {
    let mut id = [0u8; 16];
    for (slot, byte) in id.iter_mut().zip(name.bytes()) {
        *slot = byte;
    }
    mavlink::types::CharArray::new(id)
}

/// A parameter name as PARAM_VALUE carries it (NUL-padded, 16 bytes).
pub fn param_name(id: &[u8]) -> String {
    status_text(id)
}

/// The message for one setup step (parameters, geofence), addressed to the autopilot.
pub fn setup_message(
    request: &SetupRequest,
    target_system: u8,
    target_component: u8,
) -> MavMessage {
    use mavlink::dialects::common::{
        MISSION_ACK_DATA, MISSION_COUNT_DATA, MISSION_ITEM_INT_DATA, MISSION_REQUEST_INT_DATA,
        MISSION_REQUEST_LIST_DATA, MavMissionResult, MavMissionType, MavParamType,
        PARAM_REQUEST_READ_DATA, PARAM_SET_DATA,
    };
    let fence = MavMissionType::MAV_MISSION_TYPE_FENCE;
    match request {
        SetupRequest::Param(ParamRequest::Read(name)) => {
            MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
                param_index: -1,
                target_system,
                target_component,
                param_id: param_id(name),
            })
        }
        SetupRequest::Param(ParamRequest::Set(name, value)) => {
            let (param_value, param_type) = value.to_wire();
            MavMessage::PARAM_SET(PARAM_SET_DATA {
                param_value,
                target_system,
                target_component,
                param_id: param_id(name),
                param_type: if param_type == crate::params::TYPE_INT32 {
                    MavParamType::MAV_PARAM_TYPE_INT32
                } else {
                    MavParamType::MAV_PARAM_TYPE_REAL32
                },
            })
        }
        SetupRequest::Fence(FenceRequest::Count(count)) => {
            MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: *count,
                target_system,
                target_component,
                mission_type: fence,
                opaque_id: 0,
            })
        }
        SetupRequest::Fence(FenceRequest::Item { seq, count, vertex }) => {
            MavMessage::MISSION_ITEM_INT(MISSION_ITEM_INT_DATA {
                param1: f32::from(*count),
                x: vertex.lat_e7,
                y: vertex.lon_e7,
                seq: *seq,
                command: MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                target_system,
                target_component,
                frame: MavFrame::MAV_FRAME_GLOBAL,
                autocontinue: 1,
                mission_type: fence,
                ..Default::default()
            })
        }
        SetupRequest::Fence(FenceRequest::RequestList) => {
            MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
                target_system,
                target_component,
                mission_type: fence,
            })
        }
        SetupRequest::Fence(FenceRequest::RequestItem(seq)) => {
            MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                seq: *seq,
                target_system,
                target_component,
                mission_type: fence,
            })
        }
        SetupRequest::Fence(FenceRequest::Ack) => MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system,
            target_component,
            mavtype: MavMissionResult::MAV_MISSION_ACCEPTED,
            mission_type: fence,
            opaque_id: 0,
        }),
    }
}

/// The text of a STATUSTEXT (NUL-padded, at most 50 bytes); bytes that are not UTF-8 are
/// replaced, never a panic.
pub fn status_text(text: &[u8]) -> String {
    let end = text.iter().position(|b| *b == 0).unwrap_or(text.len());
    String::from_utf8_lossy(text.get(..end).unwrap_or_default())
        .trim()
        .to_owned()
}

/// The MAV_CMD number of a decoded command enum.
pub fn command_id(cmd: MavCmd) -> u32 {
    cmd as u32
}

/// What one datagram held.
#[derive(Debug, Default)]
pub struct Datagram {
    pub messages: Vec<(MavHeader, MavMessage)>,
    /// Frames that had a valid CRC but could not be parsed (unknown enum value, bad length …).
    pub parse_errors: usize,
}

impl Datagram {
    /// A datagram with nothing usable in it (garbage, bad CRC, or only unparseable frames).
    pub fn is_malformed(&self) -> bool {
        self.messages.is_empty() || self.parse_errors > 0
    }
}

/// Decodes every MAVLink (v1 or v2) frame in one UDP datagram. Bytes that are not a CRC-valid
/// frame of the common dialect are skipped; never panics.
pub fn decode_datagram(bytes: &[u8]) -> Datagram {
    let mut out = Datagram::default();
    let mut reader = MavlinkReader::new(bytes);
    // Each iteration consumes at least one frame or ends the input, so this terminates; the
    // bound is a second guard.
    for _ in 0..=bytes.len() {
        match reader.read_any_message::<MavMessage>() {
            Ok(m) => out.messages.push(m),
            Err(MessageReadError::Parse(_)) => out.parse_errors += 1,
            Err(MessageReadError::Io(_)) => break,
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_shared::Vec3;

    #[test]
    fn our_frames_decode_back() {
        let mut enc = Encoder::new(245);
        let target = NedTarget {
            position: Vec3::new(7.0, 12.0, -10.0),
            velocity: Vec3::new(1.0, 2.0, 3.0),
            acceleration: Vec3::zeros(),
            yaw: None,
        };
        let mut bytes = enc.encode(&heartbeat());
        bytes.extend(enc.encode(&set_position_target(&target, 1234, 1, 1)));
        let arm = command_long(&CommandLong::arm(), 1, 1);
        assert!(arm.is_some());
        bytes.extend(arm.map(|m| enc.encode(&m)).unwrap_or_default());
        let d = decode_datagram(&bytes);
        assert!(!d.is_malformed());
        assert_eq!(d.messages.len(), 3);
        let (h, _) = &d.messages[0];
        assert_eq!((h.system_id, h.component_id, h.sequence), (245, 191, 0));
        assert_eq!(d.messages[2].0.sequence, 2);
        match &d.messages[1].1 {
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(sp) => {
                assert_eq!((sp.x, sp.y, sp.z, sp.vz), (7.0, 12.0, -10.0, 3.0));
                assert_eq!(sp.coordinate_frame, MavFrame::MAV_FRAME_LOCAL_NED);
                assert_eq!(sp.type_mask.bits(), 1024 | 2048);
                assert_eq!((sp.target_system, sp.target_component), (1, 1));
            }
            other => panic!("expected a setpoint, got {other:?}"),
        }
        match &d.messages[2].1 {
            MavMessage::COMMAND_LONG(c) => {
                assert_eq!(
                    (command_id(c.command), c.param1, c.confirmation),
                    (400, 1.0, 0)
                );
            }
            other => panic!("expected COMMAND_LONG, got {other:?}"),
        }
    }

    #[test]
    fn status_texts_are_read_up_to_their_padding() {
        let mut raw = [0u8; 50];
        raw[..13].copy_from_slice(b"Arming denied");
        assert_eq!(status_text(&raw), "Arming denied");
        assert_eq!(status_text(&[0xff, b'a']), "\u{fffd}a");
        assert_eq!(
            status_text(&[b'x'; 50]).len(),
            50,
            "a full buffer has no NUL"
        );
        for cmd in [
            CommandLong::message_interval(32, 2e4),
            CommandLong::request_message(33),
        ] {
            assert!(
                command_long(&cmd, 1, 1).is_some(),
                "{} is encodable",
                cmd.command
            );
        }
    }

    #[test]
    fn garbage_is_malformed_not_a_panic() {
        for junk in [
            &b""[..],
            b"hello",
            &[0xFD; 300],
            &[0xFD, 9, 0, 0, 0, 1, 1, 0, 0, 0, 1, 2, 3],
        ] {
            assert!(decode_datagram(junk).is_malformed());
        }
        // A valid frame with one corrupted payload byte fails its CRC.
        let mut bytes = Encoder::new(1).encode(&heartbeat());
        bytes[12] ^= 0x55;
        assert!(decode_datagram(&bytes).is_malformed());
    }
}

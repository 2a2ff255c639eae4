//! MAVLink ↔ [`Vehicle`]: what PX4 puts on the wire for a vehicle's state, and what an incoming
//! message does to it. Pure (bytes in, bytes out); the sockets live in `runtime`.

use crate::motion::Reference;
use crate::vehicle::{LandedState, Vehicle};
use mavlink::dialects::common::{
    COMMAND_ACK_DATA, EXTENDED_SYS_STATE_DATA, HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA,
    MavAutopilot, MavCmd, MavFrame, MavLandedState, MavMessage, MavModeFlag, MavResult, MavState,
    MavType, MavVtolState, PositionTargetTypemask, SET_POSITION_TARGET_LOCAL_NED_DATA,
};
use mavlink::{MavHeader, MavlinkReader};
use tacos_shared::px4_mode::Px4Mode;

/// MAV_COMP_ID_AUTOPILOT1.
pub const AUTOPILOT_COMPONENT: u8 = 1;
/// The MAVLink protocol version field of HEARTBEAT.
const MAVLINK_VERSION: u8 = 3;

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

/// HEARTBEAT as PX4 sends it.
pub fn heartbeat(vehicle: &Vehicle) -> MavMessage {
    let mode = vehicle.mode();
    let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        | MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED;
    match mode {
        Px4Mode::Takeoff | Px4Mode::Hold | Px4Mode::Land => {
            base |=
                MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED | MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED;
        }
        Px4Mode::Offboard => base |= MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED,
        Px4Mode::Manual | Px4Mode::Position => {
            base |= MavModeFlag::MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        }
        Px4Mode::Other { .. } => {}
    }
    if vehicle.armed() {
        base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
    }
    let system_status = if vehicle.landed() {
        MavState::MAV_STATE_STANDBY
    } else {
        MavState::MAV_STATE_ACTIVE
    };
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: vehicle.custom_mode(),
        mavtype: MavType::MAV_TYPE_QUADROTOR,
        autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
        base_mode: base,
        system_status,
        mavlink_version: MAVLINK_VERSION,
    })
}

/// LOCAL_POSITION_NED in the vehicle's own frame (origin at its home).
pub fn local_position(vehicle: &Vehicle) -> MavMessage {
    let p = vehicle.position();
    let v = vehicle.velocity();
    MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
        time_boot_ms: time_boot_ms(vehicle.time()),
        x: p.x as f32,
        y: p.y as f32,
        z: p.z as f32,
        vx: v.x as f32,
        vy: v.y as f32,
        vz: v.z as f32,
    })
}

pub fn extended_sys_state(vehicle: &Vehicle) -> MavMessage {
    let landed_state = match vehicle.landed_state() {
        LandedState::OnGround => MavLandedState::MAV_LANDED_STATE_ON_GROUND,
        LandedState::Takeoff => MavLandedState::MAV_LANDED_STATE_TAKEOFF,
        LandedState::InAir => MavLandedState::MAV_LANDED_STATE_IN_AIR,
        LandedState::Landing => MavLandedState::MAV_LANDED_STATE_LANDING,
    };
    MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
        vtol_state: MavVtolState::MAV_VTOL_STATE_UNDEFINED,
        landed_state,
    })
}

pub fn command_ack(command: MavCmd, result: MavResult) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA { command, result })
}

fn time_boot_ms(seconds: f64) -> u32 {
    // Wraps after 49 days, as PX4's does.
    ((seconds * 1000.0) as u64 % (u64::from(u32::MAX) + 1)) as u32
}

/// What an incoming message did, for the runtime's counters and logs.
#[derive(Debug, Clone, PartialEq)]
pub enum Handled {
    /// A command was executed; [`command_ack`] of the two is the reply.
    Command {
        command: MavCmd,
        result: MavResult,
    },
    Setpoint,
    /// A setpoint in a frame the simulator does not fly (PX4 ignores those too).
    IgnoredSetpoint,
    /// Addressed to another system, or a message the simulator has no use for.
    NotForUs,
}

/// Applies one incoming message to the vehicle with MAVLink system id `system_id`.
pub fn handle(vehicle: &mut Vehicle, system_id: u8, message: &MavMessage) -> Handled {
    let for_us = |target: u8| target == 0 || target == system_id;
    match message {
        MavMessage::COMMAND_LONG(c) if for_us(c.target_system) => {
            let params = [
                c.param1, c.param2, c.param3, c.param4, c.param5, c.param6, c.param7,
            ];
            let result = vehicle.handle_command(c.command, params);
            Handled::Command {
                command: c.command,
                result,
            }
        }
        MavMessage::SET_POSITION_TARGET_LOCAL_NED(s) if for_us(s.target_system) => {
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
    use crate::vehicle::VehicleParams;
    use mavlink::dialects::common::COMMAND_LONG_DATA;
    use tacos_shared::scenario::Scenario;

    fn vehicle() -> Vehicle {
        let lab = Scenario::builtin("lab").expect("lab is valid");
        Vehicle::new(VehicleParams::from_limits(&lab.limits))
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
        let mut datagram = encode(header(3), &heartbeat(&v));
        datagram.extend(encode(header(3), &local_position(&v)));
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
        datagram.extend(encode(header(1), &heartbeat(&v)));
        let (messages, _) = decode_datagram(&datagram);
        assert_eq!(messages.len(), 1);
        assert!(decode_datagram(&[]).0.is_empty());
        assert!(decode_datagram(&[0xfd; 300]).0.is_empty());
    }

    fn command(target_system: u8, command: MavCmd, param1: f32) -> MavMessage {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1,
            param2: 0.0,
            param3: 0.0,
            param4: 0.0,
            param5: 0.0,
            param6: 0.0,
            param7: 0.0,
            command,
            target_system,
            target_component: 1,
            confirmation: 0,
        })
    }

    #[test]
    fn commands_for_other_systems_are_ignored() {
        let mut v = vehicle();
        let arm = command(2, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0);
        assert_eq!(handle(&mut v, 1, &arm), Handled::NotForUs);
        assert!(!v.armed());
        match handle(&mut v, 2, &arm) {
            Handled::Command { command, result } => {
                assert_eq!(result, MavResult::MAV_RESULT_ACCEPTED);
                assert_eq!(
                    command_ack(command, result),
                    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                        command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
                        result: MavResult::MAV_RESULT_ACCEPTED
                    })
                );
            }
            other => panic!("{other:?}"),
        }
        assert!(v.armed());
        let MavMessage::HEARTBEAT(hb) = heartbeat(&v) else {
            panic!()
        };
        assert!(
            hb.base_mode
                .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED)
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
}

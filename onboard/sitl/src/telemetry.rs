//! What PX4 puts on the wire about a vehicle: the streamed messages and STATUSTEXT, built from
//! a [`Vehicle`] and its place on the Earth. Pure.
//!
//! The stand-in models no attitude: the vehicle is always level and faces north (ATTITUDE yaw
//! 0, GLOBAL_POSITION_INT.hdg 0).

use crate::geo::{LocalFrame, saturating_i32};
use crate::streams::{Reply, Stream};
use crate::vehicle::{LandedState, StatusText, Vehicle};
use mavlink::dialects::common::{
    ATTITUDE_DATA, EXTENDED_SYS_STATE_DATA, GLOBAL_POSITION_INT_DATA, HEARTBEAT_DATA,
    HOME_POSITION_DATA, LOCAL_POSITION_NED_DATA, MISSION_ACK_DATA, MISSION_COUNT_DATA,
    MISSION_ITEM_INT_DATA, MISSION_REQUEST_INT_DATA, MavAutopilot, MavLandedState, MavMessage,
    MavMissionResult, MavMissionType, MavModeFlag, MavSysStatusSensor, MavType, MavVtolState,
    PARAM_VALUE_DATA, STATUSTEXT_DATA, SYS_STATUS_DATA,
};
use tacos_shared::px4_mode::{self, Px4Mode};

/// The MAVLink protocol version field of HEARTBEAT.
const MAVLINK_VERSION: u8 = 3;
/// SYS_STATUS.voltage_battery (mV): a full 4S pack, as SIH simulates one.
const BATTERY_MV: u16 = 16_800;
/// SYS_STATUS.load (per mille).
const LOAD: u16 = 200;

/// The message of `stream` now.
pub fn stream_message(stream: Stream, vehicle: &Vehicle, frame: &LocalFrame) -> MavMessage {
    match stream {
        Stream::Heartbeat => heartbeat(vehicle),
        Stream::SysStatus => sys_status(vehicle),
        Stream::Attitude => attitude(vehicle),
        Stream::LocalPosition => local_position(vehicle),
        Stream::GlobalPosition => global_position(vehicle, frame),
        Stream::HomePosition => home_position(vehicle, frame),
        Stream::ExtendedSysState => extended_sys_state(vehicle),
        Stream::Reply(reply) => reply_message(reply, vehicle),
    }
}

/// A parameter or mission protocol reply, from the vehicle's parameters and geofence now.
/// Mission messages are addressed to the client that spoke the mission protocol last.
pub fn reply_message(reply: Reply, vehicle: &Vehicle) -> MavMessage {
    let fence = vehicle.geofence();
    let (target_system, target_component) = fence.partner();
    let fence_type = MavMissionType::MAV_MISSION_TYPE_FENCE;
    let ack = |mission_type, result| {
        MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system,
            target_component,
            mavtype: result,
            mission_type,
            opaque_id: 0,
        })
    };
    match reply {
        Reply::ParamValue(index) => {
            let params = vehicle.px4_params();
            // The link queues only indices the table has.
            let (name, value) = params
                .get(usize::from(index))
                .unwrap_or(("", crate::params::ParamValue::Real(0.0)));
            let (param_value, param_type) = value.to_wire();
            MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
                param_value,
                param_count: u16::try_from(params.len()).unwrap_or(u16::MAX),
                param_index: index,
                param_id: crate::params::param_id(name),
                param_type,
            })
        }
        Reply::FenceRequest(seq) => MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq,
            target_system,
            target_component,
            mission_type: fence_type,
        }),
        Reply::FenceItem(seq) => match fence.items().get(usize::from(seq)) {
            Some(item) => MavMessage::MISSION_ITEM_INT(MISSION_ITEM_INT_DATA {
                target_system,
                target_component,
                mission_type: fence_type,
                ..item.clone()
            }),
            // Cleared since it was asked for.
            None => ack(fence_type, MavMissionResult::MAV_MISSION_INVALID_SEQUENCE),
        },
        Reply::MissionCount(mission_type) => MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: if mission_type == fence_type {
                fence.count()
            } else {
                0
            },
            target_system,
            target_component,
            mission_type,
            opaque_id: 0,
        }),
        Reply::MissionAck(mission_type, result) => ack(mission_type, result),
    }
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
        // Return, and the other auto modes.
        Px4Mode::Other {
            main: px4_mode::MAIN_AUTO,
            ..
        } => {
            base |=
                MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED | MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED;
        }
        Px4Mode::Other { .. } => {}
    }
    if vehicle.armed() {
        base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
    }
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: vehicle.custom_mode(),
        mavtype: MavType::MAV_TYPE_QUADROTOR,
        autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
        base_mode: base,
        system_status: vehicle.system_status(),
        mavlink_version: MAVLINK_VERSION,
    })
}

/// LOCAL_POSITION_NED in the vehicle's own frame (origin at its spawn point).
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

/// GLOBAL_POSITION_INT: lat/lon, altitude AMSL and above home (mm), velocity NED (cm/s).
pub fn global_position(vehicle: &Vehicle, frame: &LocalFrame) -> MavMessage {
    let p = vehicle.position();
    let v = vehicle.velocity();
    let global = frame.global(&p);
    let cm_s = |x: f64| saturating_i32(x * 100.0).clamp(i16::MIN.into(), i16::MAX.into()) as i16;
    MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
        time_boot_ms: time_boot_ms(vehicle.time()),
        lat: global.lat_e7,
        lon: global.lon_e7,
        alt: global.alt_mm,
        relative_alt: saturating_i32((vehicle.home().z - p.z) * 1000.0),
        vx: cm_s(v.x),
        vy: cm_s(v.y),
        vz: cm_s(v.z),
        hdg: 0,
    })
}

/// HOME_POSITION: home's geodetic position and its place in the local frame.
pub fn home_position(vehicle: &Vehicle, frame: &LocalFrame) -> MavMessage {
    let home = vehicle.home();
    let global = frame.global(&home);
    MavMessage::HOME_POSITION(HOME_POSITION_DATA {
        latitude: global.lat_e7,
        longitude: global.lon_e7,
        altitude: global.alt_mm,
        x: home.x as f32,
        y: home.y as f32,
        z: home.z as f32,
        q: [1.0, 0.0, 0.0, 0.0],
        approach_x: 0.0,
        approach_y: 0.0,
        approach_z: 0.0,
        ..Default::default()
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

/// SYS_STATUS with the basic fields: sensors (the pre-arm check healthy exactly when the vehicle
/// can arm, as PX4 reports it; the AHRS healthy once ready), a full battery, no link errors.
pub fn sys_status(vehicle: &Vehicle) -> MavMessage {
    use MavSysStatusSensor as S;
    let present = S::MAV_SYS_STATUS_SENSOR_3D_GYRO
        | S::MAV_SYS_STATUS_SENSOR_3D_ACCEL
        | S::MAV_SYS_STATUS_SENSOR_3D_MAG
        | S::MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
        | S::MAV_SYS_STATUS_SENSOR_GPS
        | S::MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
        | S::MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
        | S::MAV_SYS_STATUS_SENSOR_YAW_POSITION
        | S::MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
        | S::MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
        | S::MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        | S::MAV_SYS_STATUS_AHRS
        | S::MAV_SYS_STATUS_SENSOR_BATTERY
        | S::MAV_SYS_STATUS_PREARM_CHECK;
    let mut health = present;
    if !vehicle.ready() {
        health.remove(S::MAV_SYS_STATUS_AHRS);
    }
    if !vehicle.can_arm() {
        health.remove(S::MAV_SYS_STATUS_PREARM_CHECK);
    }
    MavMessage::SYS_STATUS(SYS_STATUS_DATA {
        onboard_control_sensors_present: present,
        onboard_control_sensors_enabled: present,
        onboard_control_sensors_health: health,
        load: LOAD,
        voltage_battery: BATTERY_MV,
        current_battery: -1,
        battery_remaining: 100,
        drop_rate_comm: 0,
        errors_comm: 0,
        errors_count1: 0,
        errors_count2: 0,
        errors_count3: 0,
        errors_count4: 0,
        ..Default::default()
    })
}

/// ATTITUDE: level, facing north (the stand-in models no attitude).
pub fn attitude(vehicle: &Vehicle) -> MavMessage {
    MavMessage::ATTITUDE(ATTITUDE_DATA {
        time_boot_ms: time_boot_ms(vehicle.time()),
        roll: 0.0,
        pitch: 0.0,
        yaw: 0.0,
        rollspeed: 0.0,
        pitchspeed: 0.0,
        yawspeed: 0.0,
    })
}

/// The bytes of one STATUSTEXT.
const STATUSTEXT_BYTES: usize = 50;

/// STATUSTEXT: one message for a text of up to 50 bytes (id 0), else 50-byte chunks sharing
/// the non-zero `id`, `chunk_seq` counting from 0, the last one NUL-terminated, as PX4 sends
/// long texts ("Arming denied: Resolve system health failures first" is 51 bytes).
pub fn statustexts(text: &StatusText, id: u16) -> Vec<MavMessage> {
    let message = |chunk: &str, id: u16, chunk_seq: u8| {
        MavMessage::STATUSTEXT(STATUSTEXT_DATA {
            severity: text.severity,
            text: chunk.into(),
            id,
            chunk_seq,
        })
    };
    if text.text.len() <= STATUSTEXT_BYTES {
        return vec![message(&text.text, 0, 0)];
    }
    let id = id.max(1);
    let mut chunks = Vec::new();
    let mut rest = text.text.as_str();
    // Room for at most 256 chunks; PX4's texts are far shorter.
    for chunk_seq in 0..=u8::MAX {
        let mut cut = rest.len().min(STATUSTEXT_BYTES);
        while !rest.is_char_boundary(cut) {
            cut -= 1;
        }
        let (chunk, tail) = rest.split_at(cut);
        chunks.push(message(chunk, id, chunk_seq));
        // A chunk shorter than 50 bytes ends with a NUL: that was the last one.
        if chunk.len() < STATUSTEXT_BYTES {
            break;
        }
        rest = tail;
    }
    chunks
}

fn time_boot_ms(seconds: f64) -> u32 {
    // Wraps after 49 days, as PX4's does.
    ((seconds * 1000.0) as u64 % (u64::from(u32::MAX) + 1)) as u32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::GeoOrigin;
    use crate::vehicle::VehicleParams;
    use mavlink::dialects::common::{MavCmd, MavResult, MavSeverity, MavState};
    use tacos_shared::Vec3;
    use tacos_shared::scenario::Scenario;

    fn vehicle(readiness_delay: f64) -> Vehicle {
        let lab = Scenario::builtin("lab").expect("lab is valid");
        Vehicle::new(VehicleParams {
            readiness_delay,
            ..VehicleParams::from_limits(&lab.limits)
        })
    }

    fn frame() -> LocalFrame {
        LocalFrame {
            origin: GeoOrigin::default(),
            spawn_enu: Vec3::zeros(),
        }
    }

    #[test]
    fn heartbeat_status_follows_readiness_and_arming() {
        let mut v = vehicle(1.0);
        let status = |v: &Vehicle| match heartbeat(v) {
            MavMessage::HEARTBEAT(hb) => (hb.system_status, hb.custom_mode),
            other => panic!("{other:?}"),
        };
        assert_eq!(
            status(&v),
            (MavState::MAV_STATE_UNINIT, Px4Mode::Hold.custom_mode())
        );
        assert_eq!(status(&v).1, 0x0304_0000, "AUTO.LOITER");
        let MavMessage::SYS_STATUS(s) = sys_status(&v) else {
            panic!()
        };
        assert!(
            !s.onboard_control_sensors_health
                .contains(MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK)
        );
        for _ in 0..100 {
            v.step(0.01);
        }
        assert_eq!(status(&v).0, MavState::MAV_STATE_STANDBY);
        let MavMessage::SYS_STATUS(s) = sys_status(&v) else {
            panic!()
        };
        assert!(
            s.onboard_control_sensors_health
                .contains(MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK)
        );
        let arm = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert_eq!(
            v.handle_command(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, arm),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(status(&v).0, MavState::MAV_STATE_ACTIVE);
        let MavMessage::HEARTBEAT(hb) = heartbeat(&v) else {
            panic!()
        };
        assert!(
            hb.base_mode
                .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED)
        );
    }

    #[test]
    fn global_and_home_positions_are_amsl() {
        let mut v = vehicle(0.0);
        let MavMessage::GLOBAL_POSITION_INT(g) = global_position(&v, &frame()) else {
            panic!()
        };
        assert_eq!((g.lat, g.lon), (473_977_420, 85_455_940));
        assert_eq!((g.alt, g.relative_alt, g.hdg), (489_400, 0, 0));
        let MavMessage::HOME_POSITION(h) = home_position(&v, &frame()) else {
            panic!()
        };
        assert_eq!((h.latitude, h.altitude), (473_977_420, 489_400));
        assert_eq!((h.x, h.y, h.z), (0.0, 0.0, 0.0));

        // Two metres up: 2 m above home, 491.4 m AMSL.
        v.handle_command(
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        v.handle_command(
            MavCmd::MAV_CMD_NAV_TAKEOFF,
            [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, 491.4],
        );
        for _ in 0..1000 {
            v.step(0.01);
        }
        let MavMessage::GLOBAL_POSITION_INT(g) = global_position(&v, &frame()) else {
            panic!()
        };
        assert!((g.alt - 491_400).abs() < 100, "{}", g.alt);
        assert!((g.relative_alt - 2_000).abs() < 100, "{}", g.relative_alt);
    }

    #[test]
    fn long_statustexts_go_in_chunks() {
        let short = StatusText {
            severity: MavSeverity::MAV_SEVERITY_INFO,
            text: "Ready for takeoff!".into(),
        };
        let messages = statustexts(&short, 7);
        let [MavMessage::STATUSTEXT(t)] = messages.as_slice() else {
            panic!("{messages:?}")
        };
        assert_eq!((t.id, t.chunk_seq), (0, 0));
        assert_eq!(t.text.to_str().ok(), Some("Ready for takeoff!"));

        let long = StatusText {
            severity: MavSeverity::MAV_SEVERITY_CRITICAL,
            text: "Arming denied: Resolve system health failures first".into(),
        };
        let chunks: Vec<_> = statustexts(&long, 7)
            .into_iter()
            .map(|m| match m {
                MavMessage::STATUSTEXT(t) => t,
                other => panic!("{other:?}"),
            })
            .collect();
        assert_eq!(chunks.len(), 2);
        assert!(
            chunks
                .iter()
                .all(|t| t.id == 7 && t.severity == long.severity)
        );
        assert_eq!((chunks[0].chunk_seq, chunks[1].chunk_seq), (0, 1));
        let joined: String = chunks
            .iter()
            .map(|t| t.text.to_str().unwrap_or_default())
            .collect();
        assert_eq!(joined, long.text);
        // Exactly 100 bytes: an empty third chunk ends it.
        let hundred = StatusText {
            severity: MavSeverity::MAV_SEVERITY_INFO,
            text: "x".repeat(100),
        };
        assert_eq!(statustexts(&hundred, 0).len(), 3);
    }
}

use super::*;
use mavlink::dialects::common::{
    COMMAND_LONG_DATA, MavCmd, MavFrame, MavResult, PositionTargetTypemask,
    SET_POSITION_TARGET_LOCAL_NED_DATA,
};
use tacos_shared::px4_mode::{self, Px4Mode};

/// A small world: a tower in the middle, two drones with homes far from the origin, a
/// hidden target at a car, a walking target, and a scripted link drop.
const WORLD: &str = r#"
name = "t"
[limits]
takeoff_altitude = 4.0
max_speed = 4.0
max_accel = 3.0
drone_radius = 0.5
safety_distance = 2.0
detection_radius = 3.0
detection_altitude = 10.0
[bounds]
min = [-200.0, -200.0, 0.0]
max = [200.0, 200.0, 60.0]
[[obstacles]]
name = "tower"
center = [0.0, 0.0, 0.0]
semi_axes = [5.0, 5.0, 30.0]
[[landmarks]]
name = "car_1"
kind = "car"
position = [70.0, -105.0, 0.0]
[[drones]]
id = "alfa"
home = [60.0, -120.0, 0.0]
[[drones]]
id = "bravo"
home = [-60.0, 120.0, 0.0]
[[targets]]
name = "suspect"
hidden_at = "car_1"
[[targets]]
name = "walker"
start = [0.0, 50.0, 0.0]
motion = { type = "constant_velocity", velocity = [1.0, 0.0, 0.0] }
[[faults]]
at_s = 3.0
drone = "bravo"
kind = { link_drops = { duration_s = 2.0 } }
"#;

/// AMSL of the ground everywhere in `WORLD` (its homes are at z = 0).
const GROUND: f32 = 489.4;

/// `WORLD`, its vehicles ready at once.
fn sim() -> Simulation {
    let scenario = Scenario::from_toml(WORLD).expect("valid");
    let px4 = Px4Options {
        readiness_delay_s: 0.0,
        ..Px4Options::default()
    };
    Simulation::with_px4(&scenario, &scenario.drones, &px4)
}

/// The writer's ids.
const CLIENT: MavHeader = MavHeader {
    system_id: 245,
    component_id: 191,
    sequence: 0,
};

fn send(s: &mut Simulation, i: usize, message: &MavMessage) -> Option<Response> {
    s.handle_mavlink(i, &CLIENT, message)
}

/// Every COMMAND_ACK result in `replies`, in order, checking they are addressed to CLIENT.
fn acks(replies: &[MavMessage]) -> Vec<MavResult> {
    replies
        .iter()
        .filter_map(|m| match m {
            MavMessage::COMMAND_ACK(a) => {
                assert_eq!((a.target_system, a.target_component), (245, 191));
                Some(a.result)
            }
            _ => None,
        })
        .collect()
}

fn texts(messages: &[MavMessage]) -> Vec<String> {
    messages
        .iter()
        .filter_map(|m| match m {
            MavMessage::STATUSTEXT(t) => Some(t.text.to_str().unwrap_or_default().to_string()),
            _ => None,
        })
        .collect()
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

/// The final result of a command.
fn result(response: Option<Response>) -> Option<MavResult> {
    match response?.handled {
        Handled::Command { results, .. } => results.last().copied(),
        _ => None,
    }
}

fn position_setpoint(ned: Vec3) -> MavMessage {
    MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
        time_boot_ms: 0,
        x: ned.x as f32,
        y: ned.y as f32,
        z: ned.z as f32,
        vx: 0.0,
        vy: 0.0,
        vz: 0.0,
        afx: 0.0,
        afy: 0.0,
        afz: 0.0,
        yaw: 0.0,
        yaw_rate: 0.0,
        type_mask: PositionTargetTypemask::from_bits_truncate(0b0000_1101_1111_1000),
        target_system: 1,
        target_component: 1,
        coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
    })
}

/// Streams `setpoint` to vehicle 0 at 20 Hz for `seconds`, collecting events.
fn stream(s: &mut Simulation, setpoint: &MavMessage, seconds: f64, events: &mut Vec<WorldEvent>) {
    for _ in 0..(seconds / 0.05).round() as usize {
        send(s, 0, setpoint);
        events.extend(s.advance(0.05));
    }
}

#[test]
fn a_local_ned_setpoint_lands_at_the_right_world_place() {
    let mut s = sim();
    let arm = command(
        1,
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(
        result(send(&mut s, 0, &arm)),
        Some(MavResult::MAV_RESULT_ACCEPTED)
    );
    let takeoff = command(
        1,
        MavCmd::MAV_CMD_NAV_TAKEOFF,
        [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, GROUND + 4.0],
    );
    assert_eq!(
        result(send(&mut s, 0, &takeoff)),
        Some(MavResult::MAV_RESULT_ACCEPTED)
    );
    s.advance(6.0);
    assert!((s.vehicles()[0].position_enu() - Vec3::new(60.0, -120.0, 4.0)).norm() < 0.15);

    // 10 m north, 5 m east of home, 4 m up: world (65, -110, 4).
    let mut events = Vec::new();
    let sp = position_setpoint(Vec3::new(10.0, 5.0, -4.0));
    stream(&mut s, &sp, 1.2, &mut events);
    let offboard = command(
        1,
        MavCmd::MAV_CMD_DO_SET_MODE,
        [
            1.0,
            f32::from(px4_mode::MAIN_OFFBOARD),
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        ],
    );
    assert_eq!(
        result(send(&mut s, 0, &offboard)),
        Some(MavResult::MAV_RESULT_ACCEPTED)
    );
    stream(&mut s, &sp, 8.0, &mut events);
    let at = s.vehicles()[0].position_enu();
    assert!(
        (at - Vec3::new(65.0, -110.0, 4.0)).norm() < 0.1,
        "at {at:?}"
    );
    assert!(s.vehicles()[1].vehicle.landed(), "bravo never moved");

    // Passing within 3 m of car_1 at (70, -105) below 10 m: the suspect is detected by alfa.
    let sp = position_setpoint(Vec3::new(14.0, 9.0, -4.0));
    stream(&mut s, &sp, 4.0, &mut events);
    let detections: Vec<_> = events
        .iter()
        .filter(|e| matches!(e, WorldEvent::Detection { .. }))
        .collect();
    assert_eq!(detections.len(), 1, "{events:?}");
    assert!(
        matches!(detections[0], WorldEvent::Detection { drone, landmark: Some(l), .. }
        if drone.as_str() == "alfa" && l == "car_1")
    );
}

#[test]
fn scripted_link_drop_blocks_mavlink_then_ends() {
    let mut s = sim();
    let events = s.advance(2.9);
    assert!(events.is_empty());
    assert!(s.link_up(1));
    let events = s.advance(0.2);
    assert_eq!(events.len(), 1);
    assert!(
        matches!(&events[0], WorldEvent::FaultInjected { drone, .. } if drone.as_str() == "bravo")
    );
    assert!(!s.link_up(1) && s.link_up(0));
    let arm = command(
        2,
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert!(send(&mut s, 1, &arm).is_none(), "dropped");
    assert!(!s.vehicles()[1].vehicle.armed());
    let truth = s.truth();
    assert!(truth.vehicles[1].link_down && truth.vehicles[1].alive);
    s.advance(2.0);
    assert!(s.link_up(1));
    assert_eq!(
        result(send(&mut s, 1, &arm)),
        Some(MavResult::MAV_RESULT_ACCEPTED)
    );
}

#[test]
fn a_link_drop_in_offboard_ends_in_hold() {
    let mut s = sim();
    let alfa = DroneId::new("alfa").expect("valid");
    let arm = command(
        1,
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    send(&mut s, 0, &arm);
    // As the writer does: hold on offboard loss (PX4's default, 0, returns).
    let hold_on_loss = MavMessage::PARAM_SET(mavlink::dialects::common::PARAM_SET_DATA {
        param_value: f32::from_bits(5),
        target_system: 1,
        target_component: 1,
        param_id: crate::params::param_id("COM_OBL_RC_ACT"),
        param_type: mavlink::dialects::common::MavParamType::MAV_PARAM_TYPE_INT32,
    });
    send(&mut s, 0, &hold_on_loss);
    let mut events = Vec::new();
    let sp = position_setpoint(Vec3::new(0.0, 0.0, -3.0));
    stream(&mut s, &sp, 1.2, &mut events);
    let offboard = command(
        1,
        MavCmd::MAV_CMD_DO_SET_MODE,
        [
            1.0,
            f32::from(px4_mode::MAIN_OFFBOARD),
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        ],
    );
    assert_eq!(
        result(send(&mut s, 0, &offboard)),
        Some(MavResult::MAV_RESULT_ACCEPTED)
    );
    stream(&mut s, &sp, 3.0, &mut events);
    assert!(
        s.inject(&alfa, FaultKind::LinkDrops { duration_s: 5.0 })
            .is_some()
    );
    // The writer keeps streaming, but nothing gets through.
    stream(&mut s, &sp, 1.5, &mut events);
    assert_eq!(
        Px4Mode::from_custom_mode(s.truth().vehicles[0].custom_mode),
        Px4Mode::Hold
    );
    assert!(
        s.vehicles()[0].vehicle.armed() && !s.vehicles()[0].vehicle.landed(),
        "holding in the air"
    );
}

#[test]
fn a_dead_vehicle_falls_and_is_reported() {
    let mut s = sim();
    let alfa = DroneId::new("alfa").expect("valid");
    let arm = command(
        1,
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    send(&mut s, 0, &arm);
    let takeoff = command(
        1,
        MavCmd::MAV_CMD_NAV_TAKEOFF,
        [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, GROUND + 4.0],
    );
    send(&mut s, 0, &takeoff);
    s.advance(5.0);
    let event = s
        .inject(&alfa, FaultKind::VehicleDies)
        .expect("alfa exists");
    assert!(matches!(event, WorldEvent::FaultInjected { .. }));
    assert!(
        s.inject(
            &DroneId::new("zulu").expect("valid"),
            FaultKind::VehicleDies
        )
        .is_none()
    );
    assert!(send(&mut s, 0, &arm).is_none());
    s.advance(3.0);
    let truth = s.truth();
    assert!(!truth.vehicles[0].alive && truth.vehicles[0].landed && !truth.vehicles[0].armed);
    assert!(truth.vehicles[0].position.z.abs() < 1e-9);
}

#[test]
fn commands_are_answered_like_px4_answers_them() {
    let scenario = Scenario::from_toml(WORLD).expect("valid");
    // PX4's defaults: not ready for the first seconds.
    let mut s = Simulation::new(&scenario, &scenario.drones);
    let arm = command(
        1,
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    let reply = send(&mut s, 0, &arm).expect("link up").replies;
    assert_eq!(
        acks(&reply),
        vec![MavResult::MAV_RESULT_TEMPORARILY_REJECTED]
    );
    assert!(
        matches!(reply.last(), Some(MavMessage::COMMAND_ACK(_))),
        "the ack comes last"
    );
    assert_eq!(
        texts(&reply),
        vec![
            "Preflight Fail: heading estimate invalid",
            // 51 bytes: two chunks.
            "Arming denied: Resolve system health failures firs",
            "t"
        ]
    );
    s.advance(2.5);
    let said = texts(&s.telemetry(0));
    assert!(said.contains(&"Ready for takeoff!".to_string()), "{said:?}");
    assert_eq!(
        acks(&send(&mut s, 0, &arm).expect("up").replies),
        vec![MavResult::MAV_RESULT_ACCEPTED]
    );

    // DO_SET_MODE: ACCEPTED by the receiver, then commander's answer after its reason.
    let offboard = command(
        1,
        MavCmd::MAV_CMD_DO_SET_MODE,
        [
            1.0,
            f32::from(px4_mode::MAIN_OFFBOARD),
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        ],
    );
    let reply = send(&mut s, 0, &offboard).expect("up").replies;
    assert_eq!(
        acks(&reply),
        vec![
            MavResult::MAV_RESULT_ACCEPTED,
            MavResult::MAV_RESULT_TEMPORARILY_REJECTED
        ]
    );
    assert!(matches!(reply.first(), Some(MavMessage::COMMAND_ACK(_))));
    assert_eq!(
        texts(&reply),
        vec!["Switching to Offboard is currently not available"]
    );

    // REQUEST_MESSAGE: the message, then the ack.
    let request = command(
        1,
        MavCmd::MAV_CMD_REQUEST_MESSAGE,
        [242.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    let reply = send(&mut s, 0, &request).expect("up").replies;
    let [MavMessage::HOME_POSITION(home), MavMessage::COMMAND_ACK(_)] = reply.as_slice() else {
        panic!("{reply:?}")
    };
    assert_eq!(home.altitude, 489_400);
    assert_eq!((home.x, home.y, home.z), (0.0, 0.0, 0.0));
}

#[test]
fn telemetry_streams_at_px4s_rates_with_amsl_altitudes() {
    let mut s = sim();
    let first = s.telemetry(0);
    let ids: Vec<u32> = first
        .iter()
        .filter(|m| !matches!(m, MavMessage::STATUSTEXT(_)))
        .map(mavlink::Message::message_id)
        .collect();
    assert_eq!(ids, vec![0, 1, 32, 33, 242, 245]);
    let Some(MavMessage::GLOBAL_POSITION_INT(g)) = first
        .iter()
        .find(|m| matches!(m, MavMessage::GLOBAL_POSITION_INT(_)))
    else {
        panic!("{first:?}")
    };
    // alfa's home is 60 m east and 120 m south of the origin.
    let origin = crate::geo::GeoOrigin::default().global(&Vec3::zeros());
    assert!(g.lat < origin.lat_e7 && g.lon > origin.lon_e7);
    assert_eq!((g.alt, g.relative_alt), (489_400, 0));

    let mut count = std::collections::HashMap::<u32, usize>::new();
    for _ in 0..100 {
        s.advance(0.01);
        for m in s.telemetry(0) {
            *count.entry(mavlink::Message::message_id(&m)).or_default() += 1;
        }
    }
    assert_eq!(count.get(&0), Some(&1), "HEARTBEAT at 1 Hz only");
    assert_eq!(count.get(&32), Some(&30));
    assert_eq!(count.get(&33), Some(&50));
    assert_eq!(count.get(&245), Some(&5));
    assert_eq!(count.get(&1), Some(&5));

    // A dropped link sends nothing.
    s.advance(2.2);
    assert!(!s.link_up(1) && s.telemetry(1).is_empty());
}

#[test]
fn truth_and_targets_are_reported() {
    let mut s = sim();
    s.advance(1.0);
    let truth = s.truth();
    assert!((truth.sim_time - 1.0).abs() < 1e-6);
    assert_eq!(truth.vehicles.len(), 2);
    assert_eq!(truth.vehicles[0].position, Vec3::new(60.0, -120.0, 0.0));
    assert!(truth.min_pair_distance.is_infinite(), "nobody airborne yet");
    let targets = s.targets_message();
    assert_eq!(
        targets.targets.len(),
        1,
        "the hidden suspect is not published"
    );
    assert_eq!(targets.targets[0].name, "walker");
    assert!((targets.targets[0].position - Vec3::new(1.0, 50.0, 0.0)).norm() < 1e-6);
}

//! The autopilot set up before it may arm: parameters and the fence written and read back, and
//! arming refused without the parameter protocol unless the set-up is skipped.

use super::*;

fn is_param(m: &MavMessage) -> bool {
    matches!(
        m,
        MavMessage::PARAM_REQUEST_READ(_)
            | MavMessage::PARAM_REQUEST_LIST(_)
            | MavMessage::PARAM_SET(_)
    )
}

fn is_arm(m: &MavMessage) -> bool {
    matches!(m, MavMessage::COMMAND_LONG(c) if c.command as u32 == 400)
}

const FENCE: MavMissionType = MavMissionType::MAV_MISSION_TYPE_FENCE;

#[test]
fn the_autopilot_is_set_up_before_it_may_arm() {
    // The box around home (100, -50, 2): 200 m west and east, 50 m south, 150 m north, up to
    // 62 m (60 m above home); the fence is that box grown by the default 1 m margin.
    // Left in OFFBOARD (as PX4 is after an offboard flight): the arm switches to Hold first.
    let rig = Rig::start_with("setup", &["--geofence=-100,-100,0,300,100,62"], |ap| {
        ap.position_ned = Some([0.0, 0.0, 0.0]);
        ap.custom_mode = tacos_shared::px4_mode::Px4Mode::Offboard.custom_mode();
    });
    rig.ports
        .send_command(CommandSample::new(1, CommandKind::Arm, 0.0))
        .expect("send command");
    let r = rig
        .wait_result(Duration::from_secs(5), 1)
        .unwrap_or_else(|| panic!("{}", rig.fail("no result for arm")));
    assert_eq!(
        r.outcome(),
        Some(CommandOutcome::Accepted),
        "{}",
        rig.fail(r.reason().unwrap_or(""))
    );
    let ap = rig.autopilot.state();

    // The failsafe parameters and the fence's altitude limit and action, in PX4's types.
    use Param::{Int, Real};
    for (name, want) in [
        ("COM_OBL_RC_ACT", Int(5)),
        ("COM_OF_LOSS_T", Real(1.0)),
        ("NAV_DLL_ACT", Int(0)),
        ("COM_RCL_EXCEPT", Int(4)),
        ("NAV_RCL_ACT", Int(2)),
        ("COM_RC_IN_MODE", Int(1)),
        ("GF_ACTION", Int(2)),
        ("GF_MAX_VER_DIST", Real(61.0)),
    ] {
        assert_eq!(ap.param(name), Some(want), "{name}");
    }
    // Only what differed from PX4's defaults was set, each in its parameter's type.
    let sets: Vec<_> = ap
        .received
        .iter()
        .filter_map(|r| match &r.msg {
            MavMessage::PARAM_SET(p) => Some((
                String::from_utf8_lossy(&p.param_id[..])
                    .trim_end_matches('\0')
                    .to_owned(),
                p.param_type,
            )),
            _ => None,
        })
        .collect();
    assert_eq!(
        sets,
        vec![
            (
                "COM_OBL_RC_ACT".to_owned(),
                MavParamType::MAV_PARAM_TYPE_INT32
            ),
            (
                "COM_RCL_EXCEPT".to_owned(),
                MavParamType::MAV_PARAM_TYPE_INT32
            ),
            (
                "GF_MAX_VER_DIST".to_owned(),
                MavParamType::MAV_PARAM_TYPE_REAL32
            ),
        ]
    );

    // The fence: one inclusion polygon of four vertices, accepted, around the vehicle.
    assert_eq!(
        ap.fence_results,
        vec![MavMissionResult::MAV_MISSION_ACCEPTED]
    );
    assert_eq!(ap.fence.len(), 4);
    for item in &ap.fence {
        assert!(is_inclusion_vertex(item), "{item:?}");
        assert_eq!(item.param1, 4.0, "vertex count");
        assert_eq!(item.frame, MavFrame::MAV_FRAME_GLOBAL);
    }
    let v = ap.fence_vertices();
    let lat_of = |north_m: f64| ORIGIN_LAT_E7 + (north_m / 111_319.49 * 1e7).round() as i32;
    let lon_scale = 111_319.49 * (f64::from(ORIGIN_LAT_E7) / 1e7).to_radians().cos();
    let lon_of = |east_m: f64| ORIGIN_LON_E7 + (east_m / lon_scale * 1e7).round() as i32;
    let near = |a: i32, b: i32| (a - b).abs() <= 2;
    let (min_lat, max_lat) = (v.iter().map(|p| p.0).min(), v.iter().map(|p| p.0).max());
    let (min_lon, max_lon) = (v.iter().map(|p| p.1).min(), v.iter().map(|p| p.1).max());
    assert!(
        near(min_lat.unwrap_or(0), lat_of(-51.0)) && near(max_lat.unwrap_or(0), lat_of(151.0)),
        "latitudes {v:?}"
    );
    assert!(
        near(min_lon.unwrap_or(0), lon_of(-201.0)) && near(max_lon.unwrap_or(0), lon_of(201.0)),
        "longitudes {v:?}"
    );

    // Read back (list, every item, closed by the writer's ack), and only then the arm.
    let writer_sent =
        |pred: &dyn Fn(&MavMessage) -> bool| ap.received.iter().filter(|r| pred(&r.msg)).count();
    assert_eq!(
        writer_sent(
            &|m| matches!(m, MavMessage::MISSION_REQUEST_LIST(l) if l.mission_type == FENCE)
        ),
        1
    );
    assert_eq!(
        writer_sent(
            &|m| matches!(m, MavMessage::MISSION_REQUEST_INT(q) if q.mission_type == FENCE)
        ),
        4
    );
    let read_back_closed = last_at(
        &ap,
        |m| matches!(m, MavMessage::MISSION_ACK(a) if a.mission_type == FENCE),
    );
    let last_param = last_at(&ap, is_param);
    let arm = first_at(&ap, is_arm);
    assert!(
        read_back_closed.is_some()
            && last_param.is_some()
            && arm > read_back_closed
            && arm > last_param,
        "{}",
        rig.fail("armed before the setup was confirmed")
    );
    let hold = commands_of(&ap, 176);
    assert_eq!(hold.len(), 1, "one switch to Hold");
    assert_eq!((hold[0].1.param2, hold[0].1.param3), (4.0, 3.0));
    assert!(arm.is_some_and(|arm| hold[0].0 < arm));
    drop(ap);
    assert!(rig.writer.log_text().contains("autopilot set up"));
}

#[test]
fn without_the_parameter_protocol_arming_is_refused_unless_the_setup_is_skipped() {
    let no_params = |ap: &mut ApState| ap.param_protocol = false;
    let rig = Rig::start_with("noparam", &[], no_params);
    rig.ports
        .send_command(CommandSample::new(1, CommandKind::Arm, 0.0))
        .expect("send command");
    // Four rounds of three one-second tries for the first parameter, 2 s apart (18 s), then
    // the refusal.
    let r = rig
        .wait_result(Duration::from_secs(25), 1)
        .unwrap_or_else(|| panic!("{}", rig.fail("no result for arm")));
    assert_eq!(r.outcome(), Some(CommandOutcome::Rejected));
    let reason = r.reason().unwrap_or("").to_owned();
    assert!(reason.contains("COM_OBL_RC_ACT"), "{reason}");
    assert!(
        commands_of(&rig.autopilot.state(), 400).is_empty(),
        "an ARM was sent"
    );
    assert_eq!(
        rig.autopilot
            .state()
            .received
            .iter()
            .filter(|r| is_param(&r.msg))
            .count(),
        12,
        "asked three times in each of four rounds"
    );
    drop(rig);

    // `--no-autopilot-setup`: the same autopilot arms, and is not asked about parameters.
    let rig = Rig::start_with("skip", &["--no-autopilot-setup"], no_params);
    rig.ports
        .send_command(CommandSample::new(1, CommandKind::Arm, 0.0))
        .expect("send command");
    let r = rig
        .wait_result(Duration::from_secs(3), 1)
        .unwrap_or_else(|| panic!("{}", rig.fail("no result for arm")));
    assert_eq!(r.outcome(), Some(CommandOutcome::Accepted));
    assert!(rig.autopilot.state().armed);
    let ap = rig.autopilot.state();
    assert!(
        !ap.received.iter().any(|r| is_param(&r.msg)
            || matches!(
                r.msg,
                MavMessage::MISSION_COUNT(_) | MavMessage::MISSION_REQUEST_LIST(_)
            )),
        "setup messages despite --no-autopilot-setup"
    );
}

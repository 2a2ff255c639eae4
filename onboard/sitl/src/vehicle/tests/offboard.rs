//! OFFBOARD as PX4 has it: a second of setpoints before the switch, a stream too slow does not
//! count, the setpoints flown, and the loss of the stream (COM_OBL_RC_ACT, COM_OF_LOSS_T).

use super::*;

#[test]
fn offboard_needs_a_second_of_setpoints_when_armed() {
    let mut v = airborne(5.0);
    assert_eq!(
        offboard(&mut v),
        MavResult::MAV_RESULT_TEMPORARILY_REJECTED,
        "no stream at all"
    );
    assert_eq!(
        texts(&mut v),
        vec!["Switching to Offboard is currently not available"]
    );
    let here = v.position();
    stream(&mut v, here, 0.5);
    assert_eq!(
        offboard(&mut v),
        MavResult::MAV_RESULT_TEMPORARILY_REJECTED,
        "only 0.5 s of stream"
    );
    stream(&mut v, here, 0.6);
    assert_eq!(offboard(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(v.mode(), Px4Mode::Offboard);
}

#[test]
fn a_slow_stream_does_not_count() {
    let mut v = airborne(5.0);
    let here = v.position();
    // 1 Hz for 3 s: each setpoint restarts the stream.
    for _ in 0..3 {
        v.handle_setpoint(Reference::hold(here));
        run(&mut v, 1.0);
    }
    v.handle_setpoint(Reference::hold(here));
    assert_eq!(offboard(&mut v), MavResult::MAV_RESULT_TEMPORARILY_REJECTED);
}

/// Sets a PX4 parameter the way PARAM_SET does (the value's four bytes).
fn set_param(v: &mut Vehicle, name: &str, value: ParamValue) {
    let params = v.px4_params_mut();
    let i = params.index_of(name).expect("a known parameter");
    params.set_from_wire(i, value.to_wire().0);
    assert_eq!(v.px4_params().value(name), Some(value));
}

#[test]
fn offboard_flies_the_setpoints_then_fails_safe_to_hold() {
    let (mut v, _) = offboard_at(5.0);
    // What the writer sets (PX4's default is 0: return).
    set_param(&mut v, COM_OBL_RC_ACT, ParamValue::Int(5));
    let goal = Vec3::new(12.0, -6.0, -7.0);
    stream(&mut v, goal, 15.0);
    assert_eq!(v.mode(), Px4Mode::Offboard);
    assert!((v.position() - goal).norm() < 0.1, "at {:?}", v.position());
    assert_eq!(v.system_status(), MavState::MAV_STATE_ACTIVE);

    // Setpoints stop (the last one 0.05 s before the stream ended): still offboard just
    // before COM_OF_LOSS_T, hold just after.
    run(&mut v, 0.9);
    assert_eq!(v.mode(), Px4Mode::Offboard);
    run(&mut v, 0.1);
    assert_eq!(v.mode(), Px4Mode::Hold);
    assert_eq!(
        v.system_status(),
        MavState::MAV_STATE_CRITICAL,
        "a failsafe"
    );
    let held = v.position();
    run(&mut v, 5.0);
    assert!(
        (v.position() - held).norm() < 0.05,
        "holds where hold began"
    );
    // Asking for the mode it is in ends the failsafe.
    assert_eq!(loiter(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(v.system_status(), MavState::MAV_STATE_ACTIVE);
}

/// The stream back after the offboard-loss hold: OFFBOARD again once it has streamed as long as
/// a switch needs, as PX4 SITL did under a restarted writer. A hold asked for stays a hold.
#[test]
fn the_offboard_loss_hold_ends_when_the_stream_is_back() {
    let (mut v, _) = offboard_at(5.0);
    set_param(&mut v, COM_OBL_RC_ACT, ParamValue::Int(5));
    let here = v.position();
    stream(&mut v, here, 2.0);
    run(&mut v, 1.5);
    assert_eq!(v.mode(), Px4Mode::Hold);
    stream(&mut v, here, 0.5);
    assert_eq!(
        v.mode(),
        Px4Mode::Hold,
        "half a second of stream is not enough"
    );
    stream(&mut v, here, 0.6);
    assert_eq!(v.mode(), Px4Mode::Offboard);
    assert_eq!(v.system_status(), MavState::MAV_STATE_ACTIVE);

    assert_eq!(loiter(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    stream(&mut v, here, 3.0);
    assert_eq!(v.mode(), Px4Mode::Hold, "a commanded hold is no failsafe");
}

/// Offboard at (12, -6, -7) (home is the spawn point), then the setpoints stop.
fn offboard_lost_away_from_home(action: i32) -> (Vehicle, Vec3) {
    let (mut v, _) = offboard_at(5.0);
    set_param(&mut v, COM_OBL_RC_ACT, ParamValue::Int(action));
    let goal = Vec3::new(12.0, -6.0, -7.0);
    stream(&mut v, goal, 15.0);
    assert!((v.position() - goal).norm() < 0.1);
    run(&mut v, 1.0);
    (v, goal)
}

#[test]
fn offboard_loss_returns_by_default_then_lands_at_home() {
    assert_eq!(
        Vehicle::new(params()).px4_params().offboard_loss_action(),
        crate::params::OffboardLossAction::Return,
        "PX4's default COM_OBL_RC_ACT = 0"
    );
    for action in [0, 3] {
        let (mut v, goal) = offboard_lost_away_from_home(action);
        assert_eq!(v.mode(), RETURN, "COM_OBL_RC_ACT {action}");
        assert_eq!(v.system_status(), MavState::MAV_STATE_CRITICAL);
        // Back to above home at the altitude it had, then down.
        let mut steps = 0;
        while v.landed_state() == LandedState::InAir {
            step_checked(&mut v);
            steps += 1;
            assert!(steps < 1000, "never over home: {:?}", v.position());
            assert!((v.position().z - goal.z).abs() < 0.3, "{:?}", v.position());
        }
        assert_eq!(v.landed_state(), LandedState::Landing);
        let p = v.position();
        assert!(p.x.hypot(p.y) <= RETURN_ACCEPTANCE, "over home at {p:?}");
        run(&mut v, 20.0);
        assert!(v.landed() && !v.armed(), "landed and disarmed");
        assert!(v.position().norm() < 0.3, "at home: {:?}", v.position());
        assert!(!v.take_ground_strike());
        assert_eq!(v.mode(), Px4Mode::Offboard, "back to the mode asked for");
    }
}

#[test]
fn offboard_loss_lands_where_it_is_or_stops_the_motors() {
    let (mut v, goal) = offboard_lost_away_from_home(4);
    assert_eq!(v.mode(), Px4Mode::Land);
    assert_eq!(v.system_status(), MavState::MAV_STATE_CRITICAL);
    run(&mut v, 20.0);
    assert!(v.landed() && !v.armed());
    let p = v.position();
    assert!(
        (p.x - goal.x).hypot(p.y - goal.y) < 0.3,
        "landed below where it was: {p:?}"
    );
    assert!(!v.take_ground_strike());

    // 7 (Disarm): it falls, which is the failsafe, not a strike.
    let (mut v, _) = offboard_at(5.0);
    set_param(&mut v, COM_OBL_RC_ACT, ParamValue::Int(7));
    // A fall is not bounded by the controller's limits: plain steps.
    for _ in 0..110 {
        v.step(DT);
    }
    assert!(!v.armed() && !v.landed(), "disarmed in the air");
    for _ in 0..300 {
        v.step(DT);
    }
    assert!(v.landed());
    assert!(!v.take_ground_strike());
}

#[test]
fn com_of_loss_t_is_the_timeout() {
    let (mut v, here) = offboard_at(5.0);
    set_param(&mut v, COM_OBL_RC_ACT, ParamValue::Int(5));
    set_param(&mut v, COM_OF_LOSS_T, ParamValue::Real(3.0));
    stream(&mut v, here, 1.0);
    run(&mut v, 2.9);
    assert_eq!(v.mode(), Px4Mode::Offboard, "3 s are not over");
    run(&mut v, 0.2);
    assert_eq!(v.mode(), Px4Mode::Hold);
}

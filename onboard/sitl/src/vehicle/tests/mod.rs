//! Tests of the simulated vehicle against the PX4 behaviour measured on PX4 SITL: readiness,
//! arming, take-off, modes, landing, failsafes, a dead vehicle; OFFBOARD in `offboard.rs`.

use super::*;
use crate::params::{COM_OBL_RC_ACT, COM_OF_LOSS_T, ParamValue};
use mavlink::dialects::common::{MavCmd, MavResult};
use tacos_shared::px4_mode;

mod offboard;

const DT: f64 = 0.01;
const GROUND: f64 = 489.4;

fn params() -> VehicleParams {
    VehicleParams {
        limits: MotionLimits {
            max_speed: 4.0,
            max_climb_speed: 3.0,
            max_descent_speed: 1.5,
            max_accel: 3.0,
        },
        default_takeoff_height: MIS_TAKEOFF_ALT,
        land_speed: 0.7,
        ground_amsl: GROUND,
        readiness_delay: 0.0,
    }
}

/// A vehicle that is ready and has said so ("Ready for takeoff!" collected).
fn ready_vehicle() -> Vehicle {
    let mut v = Vehicle::new(params());
    v.step(DT);
    assert_eq!(texts(&mut v), vec![text::READY]);
    v
}

fn arm(v: &mut Vehicle) -> MavResult {
    v.handle_command(
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    )
}

fn disarm(v: &mut Vehicle, param2: f32) -> MavResult {
    v.handle_command(
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [0.0, param2, 0.0, 0.0, 0.0, 0.0, 0.0],
    )
}

/// NAV_TAKEOFF with param7 as given (AMSL, or NaN).
fn takeoff_amsl(v: &mut Vehicle, param7: f32) -> MavResult {
    v.handle_command(
        MavCmd::MAV_CMD_NAV_TAKEOFF,
        [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, param7],
    )
}

/// NAV_TAKEOFF to `height` metres above the spawn point, the way a client must send it.
fn takeoff(v: &mut Vehicle, height: f64) -> MavResult {
    takeoff_amsl(v, (GROUND + height) as f32)
}

fn set_mode(v: &mut Vehicle, main: u8, sub: u8) -> MavResult {
    v.handle_command(
        MavCmd::MAV_CMD_DO_SET_MODE,
        [1.0, f32::from(main), f32::from(sub), 0.0, 0.0, 0.0, 0.0],
    )
}

fn offboard(v: &mut Vehicle) -> MavResult {
    set_mode(v, px4_mode::MAIN_OFFBOARD, 0)
}

fn loiter(v: &mut Vehicle) -> MavResult {
    set_mode(v, px4_mode::MAIN_AUTO, px4_mode::AUTO_LOITER)
}

fn texts(v: &mut Vehicle) -> Vec<String> {
    v.take_status_texts().into_iter().map(|t| t.text).collect()
}

/// Steps for `seconds`, checking the envelope on every step the vehicle is flying.
fn run(v: &mut Vehicle, seconds: f64) {
    let steps = (seconds / DT).round() as usize;
    for _ in 0..steps {
        step_checked(v);
    }
}

fn step_checked(v: &mut Vehicle) {
    let before = (v.velocity(), v.landed());
    v.step(DT);
    let limits = v.params().limits;
    assert!(
        v.velocity().norm() <= limits.max_speed + 1e-9,
        "speed {}",
        v.velocity().norm()
    );
    assert!(v.velocity().z >= -limits.max_climb_speed - 1e-9);
    assert!(v.velocity().z <= limits.max_descent_speed + 1e-9);
    if v.mode() == Px4Mode::Takeoff {
        assert!(v.velocity().z >= -TAKEOFF_SPEED - 1e-9, "take-off climb");
    }
    // Touchdown, or the floor under a vehicle that has not landed, is a contact, not a
    // commanded acceleration.
    if !before.1 && !v.landed() && v.position().z < 0.0 {
        let accel = (v.velocity() - before.0).norm() / DT;
        assert!(accel <= limits.max_accel + 1e-6, "accel {accel}");
    }
    assert!(v.position().z <= 0.0, "below the ground");
}

/// Offboard setpoints that sink onto `spot` as the onboard's touchdown does: a point going
/// down with a descent of 0.8 m/s as the velocity feed-forward, which PX4's land detector needs.
fn sink_onto(v: &mut Vehicle, spot: Vec3, seconds: f64) {
    let steps = (seconds / DT).round() as usize;
    for i in 0..steps {
        if i % 5 == 0 {
            let z = (v.position().z + 0.2).min(spot.z + 0.5);
            v.handle_setpoint(Reference {
                position: [Some(spot.x), Some(spot.y), Some(z)],
                velocity: [None, None, Some(0.8)],
                acceleration: [None; 3],
            });
        }
        step_checked(v);
    }
}

fn airborne(height: f64) -> Vehicle {
    let mut v = Vehicle::new(params());
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(takeoff(&mut v, height), MavResult::MAV_RESULT_ACCEPTED);
    run(&mut v, 15.0);
    v.take_status_texts();
    v
}

/// Airborne at `height` and switched to offboard, setpoints streaming at where it hovers
/// (returned with it).
fn offboard_at(height: f64) -> (Vehicle, Vec3) {
    let mut v = airborne(height);
    let here = v.position();
    stream(&mut v, here, 1.2);
    assert_eq!(offboard(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    (v, here)
}

fn stream(v: &mut Vehicle, target: Vec3, seconds: f64) {
    let steps = (seconds / DT).round() as usize;
    for i in 0..steps {
        if i % 5 == 0 {
            v.handle_setpoint(Reference::hold(target));
        }
        step_checked(v);
    }
}

#[test]
fn boots_in_loiter_not_ready_then_ready() {
    let mut v = Vehicle::new(VehicleParams {
        readiness_delay: 2.0,
        ..params()
    });
    assert!(!v.armed() && v.landed());
    assert_eq!(v.mode(), Px4Mode::Hold, "AUTO.LOITER");
    assert_eq!(v.landed_state(), LandedState::OnGround);
    assert_eq!(v.system_status(), MavState::MAV_STATE_UNINIT);
    assert!((v.amsl() - GROUND).abs() < 1e-9 && (v.home_amsl() - GROUND).abs() < 1e-9);
    run(&mut v, 0.5);
    assert_eq!(texts(&mut v), vec![text::HEADING_INVALID]);
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_TEMPORARILY_REJECTED);
    assert!(!v.armed());
    assert_eq!(
        texts(&mut v),
        vec![text::HEADING_INVALID, text::ARMING_DENIED]
    );
    run(&mut v, 1.0);
    assert_eq!(texts(&mut v), vec![text::HEADING_INVALID], "repeated");
    assert_eq!(v.system_status(), MavState::MAV_STATE_UNINIT);
    run(&mut v, 0.6);
    assert_eq!(texts(&mut v), vec![text::READY]);
    assert_eq!(v.system_status(), MavState::MAV_STATE_STANDBY);
    run(&mut v, 3.0);
    assert!(texts(&mut v).is_empty(), "said once");
    assert_eq!(
        arm(&mut v),
        MavResult::MAV_RESULT_ACCEPTED,
        "in AUTO.LOITER"
    );
    assert_eq!(texts(&mut v), vec![text::ARMED]);
    assert_eq!(v.system_status(), MavState::MAV_STATE_ACTIVE);
    assert_eq!(
        arm(&mut v),
        MavResult::MAV_RESULT_ACCEPTED,
        "again: no change"
    );
}

#[test]
fn arm_takeoff_hold_reaches_the_amsl_altitude() {
    let mut v = ready_vehicle();
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    assert!(v.armed());
    assert_eq!(takeoff(&mut v, 8.0), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(v.mode(), Px4Mode::Takeoff);
    run(&mut v, 2.0);
    assert_eq!(v.landed_state(), LandedState::Takeoff);
    assert!(v.position().z < -0.5, "climbing: {}", v.position().z);
    assert!(
        (v.velocity().z + TAKEOFF_SPEED).abs() < 0.01,
        "at MPC_TKO_SPEED: {}",
        v.velocity().z
    );
    let mut switched_at = None;
    for _ in 0..1300 {
        step_checked(&mut v);
        if switched_at.is_none() && v.mode() == Px4Mode::Hold {
            switched_at = Some(v.position().z);
        }
    }
    let switched_at = switched_at.expect("take-off ends in AUTO.LOITER");
    assert!(
        (switched_at + 8.0).abs() <= TAKEOFF_ACCEPTANCE + 1e-9 && (switched_at + 8.0) > 0.5,
        "within NAV_MC_ALT_RAD: {switched_at}"
    );
    assert_eq!(v.landed_state(), LandedState::InAir);
    assert!((v.position().z + 8.0).abs() < 0.15, "at {}", v.position().z);
    assert!((v.amsl() - (GROUND + 8.0)).abs() < 0.15);
    assert!(v.position().xy().norm() < 1e-6, "straight up");
    run(&mut v, 5.0);
    assert!(
        (v.position().z + 8.0).abs() < 0.15 && v.armed(),
        "and it stays there"
    );
    assert_eq!(texts(&mut v), vec![text::ARMED, text::TAKEOFF_DETECTED]);
}

#[test]
fn takeoff_without_altitude_climbs_mis_takeoff_alt() {
    let mut v = Vehicle::new(params());
    arm(&mut v);
    assert_eq!(
        takeoff_amsl(&mut v, f32::NAN),
        MavResult::MAV_RESULT_ACCEPTED
    );
    run(&mut v, 10.0);
    assert!((v.position().z + MIS_TAKEOFF_ALT).abs() < 0.15);
    assert!(texts(&mut v).contains(&"Using default takeoff altitude: 2.5 m".to_string()));
}

#[test]
fn a_relative_takeoff_altitude_stays_on_the_ground_then_disarms() {
    let mut v = ready_vehicle();
    arm(&mut v);
    v.take_status_texts();
    // 5 m "above home" is 5 m above sea level: far below the vehicle.
    assert_eq!(takeoff_amsl(&mut v, 5.0), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(texts(&mut v), vec![text::ALREADY_HIGHER]);
    assert_eq!(v.mode(), Px4Mode::Takeoff);
    run(&mut v, DISARM_PREFLIGHT - 0.1);
    assert!(
        v.armed() && v.landed() && v.position().z == 0.0,
        "never left"
    );
    run(&mut v, 0.2);
    assert!(!v.armed());
    assert_eq!(texts(&mut v), vec![text::DISARMED_PREFLIGHT]);
}

#[test]
fn takeoff_while_disarmed_is_accepted_and_flown_once_armed() {
    let mut v = Vehicle::new(params());
    assert_eq!(takeoff(&mut v, 3.0), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(v.mode(), Px4Mode::Takeoff);
    run(&mut v, 2.0);
    assert!(v.landed() && v.position().z == 0.0);
    assert_eq!(v.system_status(), MavState::MAV_STATE_STANDBY, "armable");
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    run(&mut v, 10.0);
    assert_eq!(v.mode(), Px4Mode::Hold);
    assert!((v.position().z + 3.0).abs() < 0.15, "{}", v.position().z);
}

#[test]
fn a_takeoff_below_in_the_air_holds_where_it_is() {
    let mut v = airborne(5.0);
    assert_eq!(takeoff(&mut v, 2.0), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(texts(&mut v), vec![text::ALREADY_HIGHER]);
    run(&mut v, 5.0);
    assert_eq!(v.mode(), Px4Mode::Hold);
    assert!((v.position().z + 5.0).abs() < 0.15);
}

#[test]
fn disarm_in_the_air_needs_force() {
    let mut v = airborne(5.0);
    assert_eq!(
        disarm(&mut v, 0.0),
        MavResult::MAV_RESULT_TEMPORARILY_REJECTED
    );
    assert_eq!(texts(&mut v), vec![text::DISARMING_DENIED]);
    assert!(v.armed());
    assert_eq!(
        disarm(&mut v, FORCE_DISARM_MAGIC),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert!(!v.armed());
    for _ in 0..500 {
        v.step(DT);
    }
    assert!(v.landed() && v.position().z == 0.0, "it fell");
}

#[test]
fn hold_while_moving_brakes_and_returns_within_limits() {
    let (mut v, _) = offboard_at(5.0);
    // Full speed, then a hold command mid-flight.
    let far = Vec3::new(200.0, 0.0, -5.0);
    stream(&mut v, far, 5.0);
    assert!(v.velocity().norm() > 3.9, "at full speed");
    assert_eq!(loiter(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    let held = v.position();
    stream(&mut v, far, 10.0);
    assert_eq!(
        v.mode(),
        Px4Mode::Hold,
        "setpoints do not move a holding vehicle"
    );
    assert!((v.position() - held).norm() < 0.1);
}

#[test]
fn velocity_setpoints_are_honoured_and_vertical_speeds_are_px4s() {
    let mut v = airborne(5.0);
    let vel = Reference::velocity(Vec3::new(0.0, 2.0, 0.0));
    for _ in 0..120 {
        v.handle_setpoint(vel);
        step_checked(&mut v);
    }
    assert_eq!(offboard(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    for _ in 0..300 {
        v.handle_setpoint(vel);
        step_checked(&mut v);
    }
    assert!(
        (v.velocity() - Vec3::new(0.0, 2.0, 0.0)).norm() < 0.01,
        "{:?}",
        v.velocity()
    );
    let up = Reference::velocity(Vec3::new(0.0, 0.0, -10.0));
    for _ in 0..300 {
        v.handle_setpoint(up);
        step_checked(&mut v);
    }
    assert!((v.velocity().z + 3.0).abs() < 0.01, "{}", v.velocity().z);
    let down = Reference::velocity(Vec3::new(0.0, 0.0, 10.0));
    for _ in 0..300 {
        v.handle_setpoint(down);
        step_checked(&mut v);
    }
    assert!((v.velocity().z - 1.5).abs() < 0.01, "{}", v.velocity().z);
}

#[test]
fn land_descends_touches_down_disarms_and_moves_home() {
    let (mut v, _) = offboard_at(5.0);
    let away = Vec3::new(6.0, 3.0, -5.0);
    stream(&mut v, away, 10.0);
    assert!(v.home().norm() < 1e-9, "home is where it armed");
    assert_eq!(
        v.handle_command(MavCmd::MAV_CMD_NAV_LAND, [0.0; 7]),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(v.mode(), Px4Mode::Land);
    run(&mut v, 1.0);
    assert_eq!(v.landed_state(), LandedState::Landing);
    v.take_status_texts();
    let mut touchdown = None;
    for _ in 0..3000 {
        step_checked(&mut v);
        if touchdown.is_none() && v.landed() {
            touchdown = Some(v.time());
        }
        if !v.armed() {
            break;
        }
    }
    let touchdown = touchdown.expect("it touched down");
    assert!(!v.armed(), "auto-disarmed");
    let waited = v.time() - touchdown;
    assert!(
        (DISARM_AFTER_LANDING - 0.02..DISARM_AFTER_LANDING + 0.05).contains(&waited),
        "{waited}"
    );
    assert_eq!(
        texts(&mut v),
        vec![text::LANDING_DETECTED, text::DISARMED_LANDING]
    );
    assert_eq!(v.landed_state(), LandedState::OnGround);
    assert_eq!(v.position().z, 0.0);
    assert!(
        (v.home() - Vec3::new(6.0, 3.0, 0.0)).norm() < 0.1,
        "home moved to the touchdown: {:?}",
        v.home()
    );
    assert!((v.home_amsl() - GROUND).abs() < 1e-9);
}

#[test]
fn after_an_offboard_flight_it_is_back_in_offboard_and_refuses_to_arm() {
    let (mut v, here) = offboard_at(5.0);
    stream(&mut v, here, 1.0);
    v.handle_command(MavCmd::MAV_CMD_NAV_LAND, [0.0; 7]);
    run(&mut v, 20.0);
    assert!(!v.armed() && v.landed());
    assert_eq!(v.mode(), Px4Mode::Offboard, "back to the last armable mode");
    assert_eq!(v.system_status(), MavState::MAV_STATE_UNINIT);
    v.take_status_texts();
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_TEMPORARILY_REJECTED);
    assert_eq!(texts(&mut v), vec![text::ARMING_DENIED]);

    // Setpoints streaming again make it armable in OFFBOARD ...
    let mut w = v.clone();
    stream(&mut w, Vec3::zeros(), 0.2);
    assert_eq!(w.system_status(), MavState::MAV_STATE_STANDBY);
    assert_eq!(arm(&mut w), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(w.mode(), Px4Mode::Offboard);

    // ... and so does AUTO.LOITER, accepted while disarmed.
    assert_eq!(loiter(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(v.system_status(), MavState::MAV_STATE_STANDBY);
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(v.mode(), Px4Mode::Hold);
    assert_eq!(takeoff(&mut v, 2.0), MavResult::MAV_RESULT_ACCEPTED);
    run(&mut v, 8.0);
    assert!((v.position().z + 2.0).abs() < 0.15);
}

#[test]
fn a_flight_without_offboard_disarms_into_loiter() {
    let mut v = airborne(3.0);
    v.handle_command(MavCmd::MAV_CMD_NAV_LAND, [0.0; 7]);
    run(&mut v, 20.0);
    assert!(!v.armed());
    assert_eq!(v.mode(), Px4Mode::Hold);
    assert_eq!(v.system_status(), MavState::MAV_STATE_STANDBY);
}

#[test]
fn offboard_while_disarmed_is_accepted_but_arming_needs_setpoints() {
    let mut v = Vehicle::new(params());
    assert_eq!(offboard(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    assert_eq!(v.mode(), Px4Mode::Offboard);
    assert_eq!(v.system_status(), MavState::MAV_STATE_UNINIT);
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_TEMPORARILY_REJECTED);
    run(&mut v, 3.0);
    assert_eq!(v.mode(), Px4Mode::Offboard, "no failsafe while disarmed");
    let up = Vec3::new(0.0, 0.0, -2.0);
    stream(&mut v, up, 0.1);
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    stream(&mut v, up, 6.0);
    assert!((v.position() - up).norm() < 0.1, "{:?}", v.position());
}

#[test]
fn flying_into_the_ground_is_a_strike_and_a_landing_or_a_fall_is_not() {
    // Offboard setpoints 20 m below the ground: the vehicle descends at full vertical speed
    // and hits it.
    let (mut v, here) = offboard_at(5.0);
    let mut strikes = 0;
    for i in 0..1000 {
        if i % 5 == 0 {
            v.handle_setpoint(Reference::hold(Vec3::new(here.x, here.y, 20.0)));
        }
        step_checked(&mut v);
        strikes += usize::from(v.take_ground_strike());
    }
    assert_eq!(strikes, 1, "one strike, reported once");
    assert!(
        !v.landed() && v.position().z == 0.0,
        "on the floor, but PX4's land detector wants a commanded descent"
    );

    // Setpoints that come down to the ground itself slow to a gentle touchdown; PX4 detects the
    // landing once the setpoint asks for a descent as fast as its landing's.
    let (mut v, here) = offboard_at(5.0);
    stream(&mut v, Vec3::new(here.x, here.y, 0.0), 20.0);
    assert!(!v.take_ground_strike() && !v.landed());
    sink_onto(&mut v, Vec3::new(here.x, here.y, 0.0), 2.0);
    assert!(v.landed() && !v.take_ground_strike());

    let mut v = airborne(5.0);
    v.handle_command(MavCmd::MAV_CMD_NAV_LAND, [0.0; 7]);
    run(&mut v, 30.0);
    assert!(v.landed() && !v.take_ground_strike(), "a landing");

    let mut v = airborne(5.0);
    v.kill();
    for _ in 0..1000 {
        v.step(DT);
    }
    assert!(
        v.landed() && !v.take_ground_strike(),
        "a fall without power"
    );
}

#[test]
fn armed_on_the_ground_disarms_after_the_preflight_timeout() {
    let mut v = Vehicle::new(params());
    arm(&mut v);
    run(&mut v, DISARM_PREFLIGHT - 0.1);
    assert!(v.armed());
    run(&mut v, 0.2);
    assert!(!v.armed());
    assert_eq!(v.mode(), Px4Mode::Hold);
}

#[test]
fn home_moves_at_every_arming() {
    let (mut v, _) = offboard_at(4.0);
    stream(&mut v, Vec3::new(5.0, -2.0, -1.0), 10.0);
    sink_onto(&mut v, Vec3::new(5.0, -2.0, 0.0), 10.0);
    assert!(v.landed() && !v.armed());
    let spot = v.position();
    assert!((v.home() - spot).norm() < 1e-9, "set at touchdown");
    stream(&mut v, spot, 0.2);
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    assert!((v.home() - spot).norm() < 1e-9);
}

#[test]
fn unknown_commands_are_unsupported_and_manual_modes_unflyable() {
    let mut v = Vehicle::new(params());
    assert_eq!(
        v.handle_command(MavCmd::MAV_CMD_DO_REPOSITION, [0.0; 7]),
        MavResult::MAV_RESULT_UNSUPPORTED
    );
    // Disarmed, any mode is accepted, but a manual one cannot be armed without a remote.
    assert_eq!(
        set_mode(&mut v, px4_mode::MAIN_POSCTL, 0),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(v.mode(), Px4Mode::Position);
    assert_eq!(v.system_status(), MavState::MAV_STATE_UNINIT);
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_TEMPORARILY_REJECTED);
    assert_eq!(loiter(&mut v), MavResult::MAV_RESULT_ACCEPTED);
    arm(&mut v);
    assert_eq!(
        set_mode(&mut v, px4_mode::MAIN_POSCTL, 0),
        MavResult::MAV_RESULT_TEMPORARILY_REJECTED,
        "armed"
    );
    let no_custom = [
        0.0,
        f32::from(px4_mode::MAIN_AUTO),
        f32::from(px4_mode::AUTO_LAND),
        0.0,
        0.0,
        0.0,
        0.0,
    ];
    assert_eq!(
        v.handle_command(MavCmd::MAV_CMD_DO_SET_MODE, no_custom),
        MavResult::MAV_RESULT_UNSUPPORTED
    );
    assert_eq!(
        v.handle_command(
            MavCmd::MAV_CMD_DO_SET_MODE,
            [1.0, f32::NAN, 0.0, 0.0, 0.0, 0.0, 0.0]
        ),
        MavResult::MAV_RESULT_DENIED
    );
}

#[test]
fn a_dead_vehicle_falls_and_stays_down() {
    let mut v = airborne(5.0);
    v.kill();
    for _ in 0..500 {
        v.step(DT);
    }
    assert!(!v.alive() && !v.armed() && v.landed());
    assert_eq!(arm(&mut v), MavResult::MAV_RESULT_FAILED);
    assert!(!v.armed());
}

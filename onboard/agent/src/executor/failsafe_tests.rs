//! Tests of the executor's failsafes: a silent ground station, silent neighbours, PX4 taking the
//! drone out of offboard.

use super::tests::{cmd, lab, state, state_of};
use super::*;

#[test]
fn failsafe_holds_then_lands() {
    let mut ex = lab();
    let p = Vec3::new(-40.0, -100.0, 10.0);
    ex.on_vehicle(&state(p, true, Px4Mode::Offboard));
    ex.on_command(
        &cmd(
            1,
            Action::Goto {
                target: Vec3::new(-40.0, -60.0, 10.0),
            },
        ),
        0.0,
    );
    ex.tick(0.5);
    ex.set_failsafe(Some(FailsafeStage::Holding), 1.0);
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::Failsafe(_))
    ));
    assert_eq!(
        ex.tick(1.1).steering,
        Some(Steering::Toward(Goal::fixed(p)))
    );
    ex.set_failsafe(Some(FailsafeStage::Landing), 5.0);
    let out = ex.tick(5.0);
    assert!(
        out.commands.is_empty(),
        "it first descends, apart from its neighbours"
    );
    assert_eq!(
        out.steering,
        Some(Steering::Toward(Goal::fixed(Vec3::new(-40.0, -100.0, 1.0))))
    );
    ex.on_vehicle(&state(
        Vec3::new(-40.0, -100.0, 1.0),
        true,
        Px4Mode::Offboard,
    ));
    assert!(matches!(ex.tick(9.0).steering, Some(Steering::Sink { .. })));
}

/// The failsafe acts on the state: a drone airborne while the ground has been silent past a
/// bound holds or lands, whatever happened since the stage was set, and takes only land and
/// hold until the ground is heard again.
#[test]
fn the_failsafe_acts_on_the_state_not_on_changes_of_stage() {
    let mut ex = lab();
    let ground = Vec3::new(-50.0, -132.5, 0.0);
    ex.on_vehicle(&state(ground, false, Px4Mode::Hold));
    // Silent long enough to land while on the ground: nothing to do yet.
    ex.set_failsafe(Some(FailsafeStage::Landing), 40.0);
    assert!(ex.tick(40.0).commands.is_empty());
    // A take-off from a ground that does not beat is refused, with the reason.
    assert!(ex.on_command(&cmd(1, Action::ArmTakeoff), 40.1));
    match state_of(&ex) {
        ActionState::Failed(FailureReason::Failsafe(why)) => {
            assert!(why.contains("only land and hold"), "{why}")
        }
        other => panic!("a take-off was taken in the failsafe: {other:?}"),
    }
    // Airborne all the same (the pilot took it off by hand): the next tick lands it.
    let up = Vec3::new(-50.0, -132.5, 5.0);
    ex.on_vehicle(&state(up, true, Px4Mode::Offboard));
    ex.set_failsafe(Some(FailsafeStage::Landing), 41.0);
    assert_eq!(
        ex.tick(41.0).steering,
        Some(Steering::Toward(Goal::fixed(Vec3::new(-50.0, -132.5, 1.0)))),
        "it descends to hand over to PX4's landing"
    );
    // Holding: a goto is refused and the drone keeps its hold; a landing is taken.
    let mut ex = lab();
    let p = Vec3::new(-40.0, -100.0, 10.0);
    ex.on_vehicle(&state(p, true, Px4Mode::Offboard));
    ex.set_failsafe(Some(FailsafeStage::Holding), 5.0);
    let goto = Action::Goto {
        target: Vec3::new(-40.0, -60.0, 10.0),
    };
    ex.on_command(&cmd(2, goto.clone()), 5.1);
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::Failsafe(_))
    ));
    ex.set_failsafe(Some(FailsafeStage::Holding), 5.2);
    assert_eq!(
        ex.tick(5.2).steering,
        Some(Steering::Toward(Goal::fixed(p)))
    );
    ex.on_command(&cmd(3, Action::Land), 5.3);
    ex.set_failsafe(Some(FailsafeStage::Holding), 5.4);
    assert_eq!(
        ex.tick(5.4).steering,
        Some(Steering::Toward(Goal::fixed(Vec3::new(-40.0, -100.0, 1.0)))),
        "the landing goes on under the hold stage"
    );
    // Landing: a hold is refused and the landing goes on.
    ex.set_failsafe(Some(FailsafeStage::Landing), 5.5);
    ex.on_command(&cmd(5, Action::Hold), 5.6);
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::Failsafe(_))
    ));
    assert!(matches!(ex.task, Task::Land { .. }));
    // Heard again: work is taken again.
    ex.set_failsafe(None, 6.0);
    ex.on_command(&cmd(6, goto), 6.1);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
}

/// Every neighbour silent: an airborne drone stops its goto and holds where it is, takes only
/// land and hold meanwhile, and takes work again once a neighbour is heard. On the ground it
/// may still take off.
#[test]
fn silent_neighbours_make_an_airborne_drone_hold_and_take_only_land_and_hold() {
    let mut ex = lab();
    let pad = Vec3::new(-50.0, -132.5, 0.0);
    ex.on_vehicle(&state(pad, false, Px4Mode::Hold));
    ex.set_peers_silent(true);
    assert!(ex.on_command(&cmd(1, Action::ArmTakeoff), 0.0));
    assert!(
        !matches!(state_of(&ex), ActionState::Failed(_)),
        "a take-off on the ground is taken: {:?}",
        state_of(&ex)
    );

    let mut ex = lab();
    let p = Vec3::new(-40.0, -100.0, 10.0);
    ex.on_vehicle(&state(p, true, Px4Mode::Offboard));
    let goto = Action::Goto {
        target: Vec3::new(-40.0, -60.0, 10.0),
    };
    ex.on_command(&cmd(1, goto.clone()), 0.0);
    ex.set_peers_silent(false);
    assert!(matches!(ex.tick(0.1).steering, Some(Steering::Toward(g)) if g.position.y == -60.0));
    let moved = Vec3::new(-40.0, -95.0, 10.0);
    ex.on_vehicle(&state(moved, true, Px4Mode::Offboard));
    ex.set_peers_silent(true);
    match state_of(&ex) {
        ActionState::Failed(FailureReason::Failsafe(why)) => {
            assert!(why.contains("no neighbour heard"), "{why}")
        }
        other => panic!("the goto went on with every neighbour silent: {other:?}"),
    }
    assert_eq!(
        ex.tick(0.2).steering,
        Some(Steering::Toward(Goal::fixed(moved))),
        "it holds where it was when the silence was noticed"
    );
    // A goto is refused with the reason; a landing is taken and goes on.
    ex.on_command(&cmd(2, goto.clone()), 0.3);
    match state_of(&ex) {
        ActionState::Failed(FailureReason::Failsafe(why)) => {
            assert!(why.contains("only land and hold"), "{why}")
        }
        other => panic!("a goto was taken with every neighbour silent: {other:?}"),
    }
    ex.set_peers_silent(true);
    assert_eq!(
        ex.tick(0.4).steering,
        Some(Steering::Toward(Goal::fixed(moved)))
    );
    // Heard again: the hold stays until the ground gives work, which is taken.
    ex.set_peers_silent(false);
    assert_eq!(
        ex.tick(0.5).steering,
        Some(Steering::Toward(Goal::fixed(moved)))
    );
    ex.on_command(&cmd(3, goto), 0.6);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    ex.on_command(&cmd(4, Action::Land), 0.7);
    ex.set_peers_silent(true);
    assert_eq!(
        ex.tick(0.8).steering,
        Some(Steering::Toward(Goal::fixed(Vec3::new(-40.0, -95.0, 1.0)))),
        "a landing goes on with every neighbour silent"
    );
}

/// A drone taken off and hovering in OFFBOARD, PX4 having accepted the switch at 0.1 s.
fn hovering_in_offboard(up: Vec3) -> Executor {
    let mut ex = lab();
    let pad = Vec3::new(up.x, up.y, 0.0);
    ex.on_vehicle(&state(pad, false, Px4Mode::Hold));
    ex.on_command(&cmd(1, Action::ArmTakeoff), 0.0);
    let offboard = ex.tick(0.0).commands[0];
    super::tests::accept(&mut ex, &offboard, 0.1);
    ex.on_vehicle(&state(pad, false, Px4Mode::Offboard));
    let arm = ex.tick(0.1).commands[0];
    super::tests::accept(&mut ex, &arm, 0.2);
    ex.on_vehicle(&state(up, true, Px4Mode::Offboard));
    ex.tick(6.0);
    assert_eq!(state_of(&ex), ActionState::Done);
    ex
}

/// PX4 taking a hovering drone out of OFFBOARD (its own failsafe, a geofence, an RC pilot) is
/// reported for as long as it lasts, with PX4's mode; a hold asked for takes the drone back.
#[test]
fn px4_taking_a_hovering_drone_out_of_offboard_is_reported_until_a_hold_takes_it_back() {
    let up = Vec3::new(-50.0, -132.5, 10.0);
    let mut ex = hovering_in_offboard(up);
    assert_eq!(ex.autopilot_took_over(), None);
    let rtl = Px4Mode::Other {
        main: tacos_shared::px4_mode::MAIN_AUTO,
        sub: tacos_shared::px4_mode::AUTO_RTL,
    };
    ex.on_vehicle(&state(up, true, rtl));
    let out = ex.tick(7.0);
    assert_eq!(ex.autopilot_took_over(), Some(rtl));
    assert!(out.commands.is_empty(), "TACOS does not fight PX4 for it");
    assert_eq!(ex.mode(), DroneMode::Flying);

    ex.on_command(&cmd(2, Action::Hold), 8.0);
    let out = ex.tick(8.0);
    let offboard = out.commands[0];
    assert_eq!(offboard.kind(), Some(CommandKind::Offboard));
    assert_eq!(ex.autopilot_took_over(), None, "asked back, not taken");
    super::tests::accept(&mut ex, &offboard, 8.2);
    ex.on_vehicle(&state(up, true, Px4Mode::Offboard));
    ex.tick(8.3);
    assert_eq!(ex.autopilot_took_over(), None);
    assert_eq!(state_of(&ex), ActionState::Done);

    // PX4 takes it again, then lands and disarms it: on the ground nobody flies it.
    ex.on_vehicle(&state(up, true, Px4Mode::Hold));
    ex.tick(12.0);
    assert_eq!(ex.autopilot_took_over(), Some(Px4Mode::Hold));
    ex.on_vehicle(&state(Vec3::new(up.x, up.y, 0.0), false, Px4Mode::Land));
    ex.tick(30.0);
    assert_eq!(ex.autopilot_took_over(), None);
    assert_eq!(ex.mode(), DroneMode::Idle);
}

/// A drone PX4 flies out of offboard (here an RC pilot's Position mode) is left to PX4 by both
/// failsafes: no offboard switch, no landing, however long the silence. When PX4 gives it back
/// (offboard again), the failsafe's stage applies as usual.
#[test]
fn the_failsafes_leave_a_drone_px4_flies_to_px4() {
    let up = Vec3::new(-50.0, -132.5, 10.0);
    let mut ex = hovering_in_offboard(up);
    ex.on_vehicle(&state(up, true, Px4Mode::Position));
    ex.tick(7.0);
    assert_eq!(ex.autopilot_took_over(), Some(Px4Mode::Position));

    ex.set_peers_silent(true);
    assert!(ex.tick(7.5).commands.is_empty(), "silent neighbours");
    ex.set_peers_silent(false);
    for (stage, t) in [
        (FailsafeStage::Holding, 8.0),
        (FailsafeStage::Landing, 40.0),
    ] {
        ex.set_failsafe(Some(stage), t);
        let out = ex.tick(t);
        assert!(out.commands.is_empty(), "{stage:?}: {:?}", out.commands);
        assert_eq!(ex.autopilot_took_over(), Some(Px4Mode::Position));
        assert_eq!(ex.task, Task::Hold, "{stage:?}");
    }
    // A hold heard in the landing stage (a pilot's, sent before the ground's first beat after
    // the silence) is refused, with why: taken, it would take the drone back from PX4 only for
    // the next tick's landing stage to land it.
    ex.on_command(&cmd(2, Action::Hold), 40.1);
    match state_of(&ex) {
        ActionState::Failed(FailureReason::Failsafe(why)) => {
            assert!(why.contains("only a landing"), "{why}")
        }
        other => panic!("a hold taken in the landing stage: {other:?}"),
    }
    ex.set_failsafe(Some(FailsafeStage::Landing), 40.2);
    assert!(ex.tick(40.2).commands.is_empty(), "still PX4's");
    assert_eq!(ex.autopilot_took_over(), Some(Px4Mode::Position));

    // A restarted onboard beside a vehicle PX4 holds (its offboard-loss failsafe) has no task:
    // neither failsafe takes it either.
    let mut idle = lab();
    idle.on_vehicle(&state(up, true, Px4Mode::Hold));
    idle.tick(0.0);
    idle.set_peers_silent(true);
    idle.set_failsafe(Some(FailsafeStage::Holding), 5.0);
    assert!(idle.tick(5.0).commands.is_empty());
    assert_eq!(idle.task, Task::Idle);

    // PX4 flies it in offboard again: the landing stage lands it.
    ex.on_vehicle(&state(up, true, Px4Mode::Offboard));
    ex.tick(41.0);
    assert_eq!(ex.autopilot_took_over(), None);
    ex.set_failsafe(Some(FailsafeStage::Landing), 41.5);
    assert!(matches!(ex.task, Task::Land { .. }));
}

/// A goto PX4 cuts short by leaving OFFBOARD fails, naming PX4's mode, and the drone is then
/// reported as PX4's.
#[test]
fn a_goto_cut_short_by_px4_fails_with_its_mode_and_the_drone_is_reported_as_px4s() {
    let up = Vec3::new(-50.0, -132.5, 10.0);
    let mut ex = hovering_in_offboard(up);
    let goto = Action::Goto {
        target: Vec3::new(-50.0, -100.0, 10.0),
    };
    ex.on_command(&cmd(2, goto), 7.0);
    ex.tick(7.0);
    ex.on_vehicle(&state(up, true, Px4Mode::Position));
    ex.tick(7.5);
    match state_of(&ex) {
        ActionState::Failed(FailureReason::Rejected(why)) => {
            assert!(why.contains("left offboard for Position"), "{why}")
        }
        other => panic!("the goto should fail: {other:?}"),
    }
    assert_eq!(ex.autopilot_took_over(), Some(Px4Mode::Position));
}

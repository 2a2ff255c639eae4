//! Tests of the executor: one drone's mode machine, fed states, results and the time.

use super::*;
use tacos_shared::scenario::Scenario;

pub(super) fn lab() -> Executor {
    let s = Scenario::builtin("city").expect("city");
    Executor::new(ExecutorConfig::new(s.limits, s.world))
}

pub(super) fn state(position: Vec3, armed: bool, mode: Px4Mode) -> VehicleStateSample {
    VehicleStateSample {
        link_ok: 1,
        armed: u32::from(armed),
        custom_mode: mode.custom_mode(),
        landed: u32::from(position.z < 0.1),
        position: position.into(),
        ..Default::default()
    }
}

pub(super) fn accept(ex: &mut Executor, cmd: &CommandSample, now: f64) {
    let r = CommandResultSample {
        seq: cmd.seq,
        kind: cmd.kind,
        outcome: CommandOutcome::Accepted as u32,
        ..Default::default()
    };
    ex.on_result(&r, now);
}

pub(super) fn cmd(seq: u64, action: Action) -> ActionCommand {
    ActionCommand {
        ground: 1,
        seq,
        sent_at: 0.0,
        task_id: None,
        action,
    }
}

pub(super) fn state_of(ex: &Executor) -> ActionState {
    ex.progress().map(|p| p.state.clone()).expect("an action")
}

#[test]
fn takeoff_switches_to_offboard_on_the_pad_arms_there_lifts_off_and_the_planner_climbs() {
    let mut ex = lab();
    let home = Vec3::new(-50.0, -132.5, 0.0);
    ex.on_vehicle(&state(home, false, Px4Mode::Hold));
    assert_eq!(ex.mode(), DroneMode::Idle);
    assert!(ex.on_command(&cmd(1, Action::ArmTakeoff), 0.0));
    let out = ex.tick(0.0);
    assert_eq!(out.commands.len(), 1);
    assert_eq!(out.commands[0].kind(), Some(CommandKind::Offboard));
    assert_eq!(out.steering, Some(Steering::Still(home)), "the pad streams");
    accept(&mut ex, &out.commands[0], 0.1);
    ex.on_vehicle(&state(home, false, Px4Mode::Offboard));
    let out = ex.tick(0.1);
    assert_eq!(out.commands[0].kind(), Some(CommandKind::Arm));
    assert_eq!(out.steering, Some(Steering::Still(home)));
    accept(&mut ex, &out.commands[0], 0.2);
    ex.on_vehicle(&state(home, true, Px4Mode::Offboard));
    let climb_to = home + Vec3::new(0.0, 0.0, 10.0);
    let out = ex.tick(0.3);
    assert!(out.commands.is_empty(), "{:?}", out.commands);
    assert_eq!(
        out.steering,
        Some(Steering::Still(climb_to)),
        "straight up while the autopilot says it is on the ground"
    );
    ex.on_vehicle(&state(
        home + Vec3::new(0.0, 0.0, 5.0),
        true,
        Px4Mode::Offboard,
    ));
    let out = ex.tick(3.0);
    assert_eq!(
        out.steering,
        Some(Steering::Toward(Goal::fixed(climb_to))),
        "off the ground, the planner flies the climb"
    );
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    ex.on_vehicle(&state(
        home + Vec3::new(0.1, 0.0, 9.95),
        true,
        Px4Mode::Offboard,
    ));
    let out = ex.tick(6.0);
    assert!(out.commands.is_empty());
    assert_eq!(state_of(&ex), ActionState::Done);
    assert_eq!(ex.mode(), DroneMode::Flying);
    assert_eq!(out.steering, Some(Steering::Toward(Goal::fixed(climb_to))));
}

#[test]
fn a_takeoff_already_in_offboard_arms_at_once_and_one_armed_in_hold_asks_for_offboard() {
    // After an offboard flight PX4 is back in OFFBOARD on the ground.
    let mut ex = lab();
    let home = Vec3::new(-50.0, -132.5, 0.0);
    ex.on_vehicle(&state(home, false, Px4Mode::Offboard));
    ex.on_command(&cmd(1, Action::ArmTakeoff), 0.0);
    let arm = ex.tick(0.0).commands[0];
    assert_eq!(arm.kind(), Some(CommandKind::Arm));
    // The writer armed it through AUTO.LOITER (PX4 was not ready in OFFBOARD): OFFBOARD again.
    accept(&mut ex, &arm, 0.5);
    ex.on_vehicle(&state(home, true, Px4Mode::Hold));
    let out = ex.tick(0.6);
    assert_eq!(
        out.commands.first().and_then(|c| c.kind()),
        Some(CommandKind::Offboard)
    );
    // Disarmed by PX4 before it climbed: the take-off fails and says so.
    ex.on_vehicle(&state(home, false, Px4Mode::Hold));
    ex.tick(11.0);
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::InvalidForMode(_))
    ));
}

#[test]
fn goto_before_takeoff_is_refused_by_mode() {
    let mut ex = lab();
    ex.on_vehicle(&state(Vec3::new(-50.0, -132.5, 0.0), false, Px4Mode::Hold));
    ex.on_command(
        &cmd(
            1,
            Action::Goto {
                target: Vec3::new(0.0, -100.0, 10.0),
            },
        ),
        0.0,
    );
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::InvalidForMode(_))
    ));
    assert!(ex.tick(0.0).commands.is_empty());
}

#[test]
fn goto_into_a_skyscraper_or_out_of_bounds_is_unreachable_but_through_one_is_flown() {
    let mut ex = lab();
    ex.on_vehicle(&state(
        Vec3::new(-40.0, -40.0, 10.0),
        true,
        Px4Mode::Offboard,
    ));
    ex.on_command(
        &cmd(
            1,
            Action::Goto {
                target: Vec3::new(-18.0, -18.0, 10.0),
            },
        ),
        0.0,
    );
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::Unreachable(_))
    ));
    ex.on_command(
        &cmd(
            3,
            Action::Goto {
                target: Vec3::new(-40.0, 400.0, 10.0),
            },
        ),
        0.0,
    );
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::Unreachable(_))
    ));
    // The straight line crosses skyscraper_1 and skyscraper_4: the planner goes round.
    let far = Vec3::new(40.0, 40.0, 10.0);
    ex.on_command(&cmd(4, Action::Goto { target: far }), 1.0);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    assert_eq!(
        ex.tick(1.0).steering,
        Some(Steering::Toward(Goal::fixed(far)))
    );
}

#[test]
fn goto_steers_the_planner_and_completes_on_arrival() {
    let mut ex = lab();
    let start = Vec3::new(-40.0, -100.0, 10.0);
    let goal = Vec3::new(-40.0, -80.0, 10.0);
    ex.on_vehicle(&state(start, true, Px4Mode::Offboard));
    ex.on_command(&cmd(5, Action::Goto { target: goal }), 0.0);
    let out = ex.tick(0.0);
    assert!(out.commands.is_empty(), "already in offboard");
    assert_eq!(out.steering, Some(Steering::Toward(Goal::fixed(goal))));
    ex.on_vehicle(&state(
        Vec3::new(-40.0, -90.0, 10.0),
        true,
        Px4Mode::Offboard,
    ));
    ex.tick(2.0);
    match state_of(&ex) {
        ActionState::Running { progress } => assert!((progress - 0.5).abs() < 0.01),
        other => panic!("{other:?}"),
    }
    ex.on_vehicle(&state(goal, true, Px4Mode::Offboard));
    ex.tick(4.0);
    assert_eq!(state_of(&ex), ActionState::Done);
    // Then it holds the goal, still through the planner (so it keeps giving way).
    assert_eq!(
        ex.tick(5.0).steering,
        Some(Steering::Toward(Goal::fixed(goal)))
    );
}

#[test]
fn a_goto_still_closing_in_runs_past_its_deadline_and_fails_once_it_stalls() {
    let mut ex = lab();
    let start = Vec3::new(-40.0, -100.0, 10.0);
    ex.on_vehicle(&state(start, true, Px4Mode::Offboard));
    let goal = Vec3::new(-40.0, -80.0, 10.0);
    ex.on_command(&cmd(5, Action::Goto { target: goal }), 0.0);
    // Slowly through a crowd: 1 m every 5 s, well past the deadline that stops a drone
    // that does not move (see the test below).
    for step in 1..=10 {
        let t = 5.0 * f64::from(step);
        let at = Vec3::new(-40.0, -100.0 + f64::from(step), 10.0);
        ex.on_vehicle(&state(at, true, Px4Mode::Offboard));
        ex.tick(t);
        assert!(
            matches!(state_of(&ex), ActionState::Running { .. }),
            "at {t} s"
        );
    }
    // Then it stops 10 m short: 30 s later it has failed.
    ex.tick(75.0);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    ex.tick(81.0);
    assert_eq!(state_of(&ex), ActionState::Failed(FailureReason::TimedOut));
}

#[test]
fn a_goto_that_never_arrives_times_out() {
    let mut ex = lab();
    let start = Vec3::new(-40.0, -100.0, 10.0);
    ex.on_vehicle(&state(start, true, Px4Mode::Offboard));
    let goal = Vec3::new(-40.0, -80.0, 10.0);
    ex.on_command(&cmd(5, Action::Goto { target: goal }), 0.0);
    ex.tick(30.0);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    ex.tick(40.0);
    assert_eq!(state_of(&ex), ActionState::Failed(FailureReason::TimedOut));
    assert_eq!(
        ex.tick(41.0).steering,
        Some(Steering::Toward(Goal::fixed(start)))
    );
}

#[test]
fn a_goto_fails_at_once_when_the_vehicle_disarms_under_it() {
    let mut ex = lab();
    let start = Vec3::new(-40.0, -100.0, 10.0);
    ex.on_vehicle(&state(start, true, Px4Mode::Offboard));
    ex.on_command(
        &cmd(
            5,
            Action::Goto {
                target: Vec3::new(-40.0, -80.0, 10.0),
            },
        ),
        0.0,
    );
    ex.tick(1.0);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    // Pressed into the ground: it touched down and PX4 disarmed it.
    ex.on_vehicle(&state(
        Vec3::new(-40.0, -95.0, 0.0),
        false,
        Px4Mode::Offboard,
    ));
    ex.tick(2.0);
    assert_eq!(state_of(&ex), ActionState::Failed(disarmed_in_flight()));
    assert_eq!(ex.mode(), DroneMode::Idle);
}

fn station(p: Vec3) -> Station {
    Station::At(Goal {
        position: p,
        velocity: Vec3::new(1.0, 0.0, 0.0),
    })
}

#[test]
fn tracking_follows_the_station_is_done_on_reaching_it_and_reports_a_lost_target() {
    let mut ex = lab();
    let p = Vec3::new(-40.0, -100.0, 12.0);
    ex.on_vehicle(&state(p, true, Px4Mode::Offboard));
    ex.on_command(
        &cmd(
            1,
            Action::StartTracking {
                target: "van".into(),
            },
        ),
        0.0,
    );
    assert_eq!(ex.mode(), DroneMode::Tracking);
    assert_eq!(ex.following(), Some(("van", 12.0)));
    // Not seen yet: it waits where it is.
    ex.on_station(Station::Unseen, 1.0);
    assert_eq!(
        ex.tick(1.0).steering,
        Some(Steering::Toward(Goal::fixed(p)))
    );
    let far = p + Vec3::new(20.0, 0.0, 0.0);
    ex.on_station(station(far), 1.5);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    match ex.tick(1.5).steering {
        Some(Steering::Toward(goal)) => {
            assert_eq!(goal.position, far);
            assert_eq!(goal.velocity, Vec3::new(1.0, 0.0, 0.0));
        }
        other => panic!("{other:?}"),
    }
    ex.on_vehicle(&state(
        far + Vec3::new(1.0, 0.0, 0.0),
        true,
        Px4Mode::Offboard,
    ));
    ex.on_station(station(far + Vec3::new(2.0, 0.0, 0.0)), 10.0);
    assert_eq!(state_of(&ex), ActionState::Done);
    assert_eq!(ex.mode(), DroneMode::Tracking, "still following");
    // Observations stop: the done action is reported failed with the reason, and it holds.
    ex.on_station(Station::Lost, 20.0);
    assert_eq!(
        state_of(&ex),
        ActionState::Failed(FailureReason::TargetLost("van".into()))
    );
    assert_eq!(ex.mode(), DroneMode::Flying);
    assert!(ex.following().is_none());
}

#[test]
fn a_target_never_seen_fails_the_tracking_and_stop_tracking_holds() {
    let mut ex = lab();
    let p = Vec3::new(-40.0, -100.0, 12.0);
    ex.on_vehicle(&state(p, true, Px4Mode::Offboard));
    let track = Action::StartTracking {
        target: "ghost".into(),
    };
    ex.on_command(&cmd(1, track.clone()), 0.0);
    ex.on_station(Station::Unseen, 2.0);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    ex.on_station(Station::Unseen, 3.5);
    assert_eq!(
        state_of(&ex),
        ActionState::Failed(FailureReason::TargetLost("ghost".into()))
    );
    ex.on_command(&cmd(2, track), 4.0);
    ex.on_station(station(p + Vec3::new(5.0, 0.0, 0.0)), 4.1);
    ex.on_command(&cmd(3, Action::StopTracking), 5.0);
    assert_eq!(state_of(&ex), ActionState::Done);
    assert_eq!(ex.mode(), DroneMode::Flying);
    assert_eq!(
        ex.tick(5.0).steering,
        Some(Steering::Toward(Goal::fixed(p)))
    );
}

#[test]
fn rejected_and_timed_out_commands_fail_the_action() {
    let mut ex = lab();
    ex.on_vehicle(&state(Vec3::new(-50.0, -132.5, 0.0), false, Px4Mode::Hold));
    ex.on_command(&cmd(1, Action::ArmTakeoff), 0.0);
    let arm = ex.tick(0.0).commands[0];
    ex.on_result(
        &CommandResultSample {
            seq: arm.seq,
            kind: arm.kind,
            outcome: CommandOutcome::Rejected as u32,
            mav_result: 2, // MAV_RESULT_DENIED
            ..Default::default()
        },
        0.5,
    );
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::Rejected(_))
    ));
    ex.on_command(&cmd(2, Action::ArmTakeoff), 1.0);
    let arm = ex.tick(1.0).commands[0];
    ex.on_result(
        &CommandResultSample {
            seq: arm.seq,
            kind: arm.kind,
            outcome: CommandOutcome::TimedOut as u32,
            ..Default::default()
        },
        4.0,
    );
    assert_eq!(state_of(&ex), ActionState::Failed(FailureReason::TimedOut));
}

#[test]
fn a_refusal_says_why_in_the_autopilots_words_and_a_stale_position_is_unavailable() {
    let mut ex = lab();
    ex.on_vehicle(&state(Vec3::new(-50.0, -132.5, 0.0), false, Px4Mode::Hold));
    ex.on_command(&cmd(1, Action::ArmTakeoff), 0.0);
    let arm = ex.tick(0.0).commands[0];
    let refused = CommandResultSample::new(arm.seq, arm.kind, CommandOutcome::Rejected, 1)
        .with_reason("Arm was refused (TEMPORARILY_REJECTED): PX4 says \"Arming denied\"");
    // Temporary refusals are asked again a few times; the last one fails with the words.
    for i in 0..=RETRIES_AFTER_TEMPORARY_REJECTION {
        let now = f64::from(i);
        let again = ex.tick(now).commands.first().copied().unwrap_or(arm);
        ex.on_result(
            &CommandResultSample {
                seq: again.seq,
                ..refused
            },
            now,
        );
    }
    match state_of(&ex) {
        ActionState::Failed(FailureReason::Rejected(why)) => {
            assert!(why.contains("Arming denied"), "{why}")
        }
        other => panic!("expected a refusal, got {other:?}"),
    }
    assert_eq!(ex.mode(), DroneMode::Idle);
    let mut stale = state(Vec3::new(-50.0, -132.5, 0.0), false, Px4Mode::Hold);
    stale.position_age_ms = POSITION_STALE_MS + 1;
    ex.on_vehicle(&stale);
    assert_eq!(
        ex.mode(),
        DroneMode::Unavailable,
        "heartbeats alone are not enough"
    );
}

#[test]
fn leaving_offboard_mid_goto_fails_it_and_link_loss_makes_the_drone_unavailable() {
    let mut ex = lab();
    let start = Vec3::new(-40.0, -100.0, 10.0);
    ex.on_vehicle(&state(start, true, Px4Mode::Hold));
    ex.on_command(
        &cmd(
            1,
            Action::Goto {
                target: Vec3::new(-40.0, -60.0, 10.0),
            },
        ),
        0.0,
    );
    let off = ex.tick(0.0).commands[0];
    accept(&mut ex, &off, 0.1);
    ex.on_vehicle(&state(start, true, Px4Mode::Offboard));
    ex.tick(1.0);
    ex.on_vehicle(&state(start, true, Px4Mode::Hold));
    ex.tick(3.0);
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::Rejected(_))
    ));

    let mut lost = state(start, true, Px4Mode::Hold);
    lost.link_ok = 0;
    ex.on_vehicle(&lost);
    ex.tick(4.0);
    assert_eq!(ex.mode(), DroneMode::Unavailable);
}

fn reject_temporarily(ex: &mut Executor, cmd: &CommandSample, now: f64) {
    ex.on_result(
        &CommandResultSample {
            seq: cmd.seq,
            kind: cmd.kind,
            outcome: CommandOutcome::Rejected as u32,
            mav_result: MAV_RESULT_TEMPORARILY_REJECTED,
            ..Default::default()
        },
        now,
    );
}

#[test]
fn a_temporarily_rejected_offboard_switch_is_asked_again_a_few_times() {
    let mut ex = lab();
    let p = Vec3::new(-40.0, -100.0, 10.0);
    ex.on_vehicle(&state(p, true, Px4Mode::Hold));
    ex.on_command(&cmd(1, Action::Hold), 0.0);
    let first = ex.tick(0.0).commands[0];
    assert_eq!(first.kind(), Some(CommandKind::Offboard));
    reject_temporarily(&mut ex, &first, 0.1);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    assert!(ex.tick(0.3).commands.is_empty(), "not before the pause");
    let second = ex.tick(0.7).commands[0];
    assert_eq!(second.kind(), Some(CommandKind::Offboard));
    assert_ne!(second.seq, first.seq);
    accept(&mut ex, &second, 0.8);
    assert_eq!(state_of(&ex), ActionState::Done);

    // Refused again and again: after the retries, the action fails with the refusal.
    ex.on_vehicle(&state(p, true, Px4Mode::Hold));
    ex.on_command(&cmd(2, Action::Hold), 10.0);
    let mut command = ex.tick(10.0).commands[0];
    let mut now = 10.0;
    for _ in 0..RETRIES_AFTER_TEMPORARY_REJECTION {
        reject_temporarily(&mut ex, &command, now);
        now += 1.0;
        command = ex.tick(now).commands[0];
    }
    reject_temporarily(&mut ex, &command, now);
    assert!(matches!(
        state_of(&ex),
        ActionState::Failed(FailureReason::Rejected(_))
    ));
}

#[test]
fn repeated_sequence_numbers_are_ignored() {
    let mut ex = lab();
    ex.on_vehicle(&state(Vec3::new(-50.0, -132.5, 0.0), false, Px4Mode::Hold));
    assert!(ex.on_command(&cmd(7, Action::ArmTakeoff), 0.0));
    assert!(!ex.on_command(&cmd(7, Action::ArmTakeoff), 0.1));
    assert_eq!(ex.tick(0.2).commands.len(), 1);
}

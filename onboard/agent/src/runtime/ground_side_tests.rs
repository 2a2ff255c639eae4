//! Tests of the ground side as the callbacks drive it: decoded (or undecodable) actions and
//! heartbeats, an executor, the time.

use super::*;
use crate::executor::ExecutorConfig;
use tacos_shared::action::Action;
use tacos_shared::ipc::VehicleStateSample;
use tacos_shared::messages::{ActionState, FailsafeStage, FailureReason};
use tacos_shared::px4_mode::Px4Mode;
use tacos_shared::scenario::Scenario;

const HOLD_S: f64 = 3.0;

/// An idle drone on the ground of the city, its autopilot heard, and the ground side of a
/// fresh onboard started at 0.
fn drone() -> (GroundSide, Executor) {
    let s = Scenario::builtin("city").expect("city");
    let mut executor = Executor::new(ExecutorConfig::new(s.limits, s.world));
    executor.on_vehicle(&VehicleStateSample {
        link_ok: 1,
        custom_mode: Px4Mode::Hold.custom_mode(),
        landed: 1,
        position: [-50.0, -132.5, 0.0],
        ..Default::default()
    });
    let ground = GroundSide::new(
        GroundFollower::new(HOLD_S, 2.0),
        FailsafeTimer::new(HOLD_S, 30.0, 0.0),
    );
    (ground, executor)
}

fn beat(ground: u64, stamp: f64) -> Result<GroundHeartbeat, CodecError> {
    Ok(GroundHeartbeat {
        counter: 1,
        ground,
        stamp,
    })
}

fn take_off(seq: u64, sent_at: f64) -> Result<ActionCommand, CodecError> {
    Ok(ActionCommand {
        ground: 7,
        seq,
        sent_at,
        task_id: None,
        action: Action::ArmTakeoff,
    })
}

fn state(executor: &Executor) -> Option<(u64, ActionState)> {
    executor.progress().map(|p| (p.seq, p.state.clone()))
}

#[test]
fn an_action_from_the_followed_ground_reaches_the_executor_and_asks_for_the_status() {
    let (mut ground, mut executor) = drone();
    assert!(
        ground.on_heartbeat(beat(7, 0.0), &mut executor, 0.0),
        "first adoption told"
    );
    assert!(ground.on_action(take_off(1, 0.1), &mut executor, 0.1));
    assert!(matches!(
        state(&executor),
        Some((1, ActionState::Running { .. }))
    ));
    assert_eq!(ground.malformed_actions, 0);
    // The same action again (a repeat on the wire) is stale: nothing changes, no status.
    assert!(!ground.on_action(take_off(1, 0.1), &mut executor, 0.2));
}

#[test]
fn a_malformed_action_is_counted_and_told_and_nothing_reaches_the_executor() {
    let (mut ground, mut executor) = drone();
    assert!(ground.on_action(Err(CodecError::Truncated), &mut executor, 0.1));
    assert_eq!(ground.malformed_actions, 1);
    assert_eq!(state(&executor), None);
}

#[test]
fn a_late_action_is_refused_and_the_refusal_told() {
    let (mut ground, mut executor) = drone();
    ground.on_heartbeat(beat(7, 0.0), &mut executor, 0.0);
    // Sent at 0.5 on the ground's clock, heard 5 s later where beats took no time.
    assert!(ground.on_action(take_off(1, 0.5), &mut executor, 5.5));
    assert_eq!(state(&executor), None);
    assert_eq!(ground.refused.as_ref().map(|r| r.seq), Some(1));
}

/// A drone whose ground beat at 0 and fell silent past the hold time: at 4 the tick has set
/// the failsafe.
fn in_failsafe() -> (GroundSide, Executor) {
    let (mut ground, mut executor) = drone();
    ground.on_heartbeat(beat(7, 0.0), &mut executor, 0.0);
    executor.set_failsafe(ground.failsafe.stage(4.0), 4.0);
    assert_eq!(executor.failsafe(), Some(FailsafeStage::Holding));
    (ground, executor)
}

#[test]
fn a_beat_heard_before_an_action_ends_the_failsafe_the_action_would_meet() {
    // Without the beat the take-off is refused for the failsafe …
    let (mut unheard, mut refusing) = in_failsafe();
    assert!(unheard.on_action(take_off(1, 4.0), &mut refusing, 4.0));
    assert!(matches!(
        state(&refusing),
        Some((1, ActionState::Failed(FailureReason::Failsafe(_))))
    ));
    // … with it, taken.
    let (mut ground, mut executor) = in_failsafe();
    ground.on_heartbeat(beat(7, 4.0), &mut executor, 4.0);
    assert_eq!(executor.failsafe(), None);
    assert!(ground.on_action(take_off(1, 4.0), &mut executor, 4.0));
    assert!(matches!(
        state(&executor),
        Some((1, ActionState::Running { .. }))
    ));
}

#[test]
fn a_second_ground_is_refused_while_the_followed_one_beats_and_adopted_after() {
    let (mut ground, mut executor) = drone();
    assert!(
        ground.on_heartbeat(beat(7, 0.0), &mut executor, 0.0),
        "first adoption told"
    );
    assert!(!ground.on_heartbeat(beat(9, 0.5), &mut executor, 0.5));
    assert_eq!(ground.grounds.followed(), Some(7));
    // The followed one silent past the hold time: the other is adopted, and that is told.
    assert!(ground.on_heartbeat(beat(9, 4.0), &mut executor, 4.0));
    assert_eq!(ground.grounds.followed(), Some(9));
}

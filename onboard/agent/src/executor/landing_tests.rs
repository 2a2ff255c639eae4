//! Tests of the executor's landing (through the planner, onto the floor, disarmed) and of an
//! onboard restarted beside a vehicle in flight.

use super::tests::{accept, cmd, lab, state, state_of};
use super::*;

#[test]
fn a_landing_descends_through_the_planner_sinks_onto_the_floor_and_disarms() {
    let mut ex = lab();
    let high = Vec3::new(-50.0, -132.5, 10.0);
    ex.on_vehicle(&state(high, true, Px4Mode::Offboard));
    ex.on_command(&cmd(1, Action::Land), 0.0);
    let out = ex.tick(0.0);
    assert!(
        out.commands.is_empty(),
        "no NAV_LAND from 10 m: {:?}",
        out.commands
    );
    // City: drone radius 0.5, so the planner's descent ends 1 m above the floor.
    let handoff = Vec3::new(-50.0, -132.5, 1.0);
    assert_eq!(out.steering, Some(Steering::Toward(Goal::fixed(handoff))));
    ex.on_vehicle(&state(
        Vec3::new(-50.0, -132.5, 4.0),
        true,
        Px4Mode::Offboard,
    ));
    assert!(ex.tick(3.0).commands.is_empty(), "still descending");
    let low = Vec3::new(-50.0, -132.5, 1.05);
    ex.on_vehicle(&state(low, true, Px4Mode::Offboard));
    let out = ex.tick(6.0);
    assert!(out.commands.is_empty(), "{:?}", out.commands);
    // Then it sinks at the touchdown speed, the velocity feed-forward PX4's land detector needs.
    assert_eq!(
        out.steering,
        Some(Steering::Sink {
            point: low,
            speed: landing::TOUCHDOWN_SPEED
        })
    );
    // A second later, the vehicle following 0.2 m behind the point.
    let following = Vec3::new(low.x, low.y, low.z - landing::TOUCHDOWN_SPEED + 0.2);
    ex.on_vehicle(&state(following, true, Px4Mode::Offboard));
    let out = ex.tick(7.0);
    assert_eq!(
        out.steering,
        Some(Steering::Sink {
            point: Vec3::new(low.x, low.y, low.z - landing::TOUCHDOWN_SPEED),
            speed: landing::TOUCHDOWN_SPEED
        })
    );
    // Never more than half a metre ahead of the vehicle: held by the floor, it is pressed into
    // it; a vehicle that has not come down yet is not braked at a fixed depth.
    let Some(Steering::Sink { point, .. }) = ex.tick(15.0).steering else {
        panic!("not sinking")
    };
    assert_eq!(point.z, following.z - 0.5);
    // Down: disarmed, then done.
    ex.on_vehicle(&state(
        Vec3::new(-50.0, -132.5, 0.0),
        true,
        Px4Mode::Offboard,
    ));
    let out = ex.tick(9.0);
    let Some(Steering::Sink { point, .. }) = out.steering else {
        panic!("not sinking")
    };
    assert_eq!(point.z, -0.5);
    assert_eq!(
        out.commands.first().and_then(|c| c.kind()),
        Some(CommandKind::Disarm)
    );
    // A refused disarm does not fail the landing: PX4's own disarm after landing follows.
    ex.on_result(
        &CommandResultSample::new(
            out.commands[0].seq,
            out.commands[0].kind,
            CommandOutcome::Rejected,
            4,
        ),
        9.1,
    );
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));
    ex.on_vehicle(&state(
        Vec3::new(-50.0, -132.5, 0.0),
        false,
        Px4Mode::Offboard,
    ));
    ex.tick(11.0);
    assert_eq!(state_of(&ex), ActionState::Done);
    assert_eq!(ex.mode(), DroneMode::Idle);

    // Never detected as landed: PX4's landing takes over, so a landing always lands.
    let mut ex = lab();
    ex.on_vehicle(&state(low, true, Px4Mode::Offboard));
    ex.on_command(&cmd(2, Action::Land), 0.0);
    assert!(matches!(ex.tick(0.0).steering, Some(Steering::Sink { .. })));
    let stuck = Vec3::new(-50.0, -132.5, 0.3);
    let mut state_stuck = state(stuck, true, Px4Mode::Offboard);
    state_stuck.landed = 0;
    ex.on_vehicle(&state_stuck);
    let out = ex.tick(1.05 / landing::TOUCHDOWN_SPEED + 10.1);
    assert_eq!(
        out.commands.first().and_then(|c| c.kind()),
        Some(CommandKind::Land)
    );
    accept(&mut ex, &out.commands[0], 14.0);
    ex.on_vehicle(&state(Vec3::new(-50.0, -132.5, 0.0), false, Px4Mode::Land));
    ex.tick(16.0);
    assert_eq!(state_of(&ex), ActionState::Done);

    // Not in OFFBOARD (PX4's failsafe holds it): PX4 lands it.
    let mut ex = lab();
    ex.on_vehicle(&state(high, true, Px4Mode::Hold));
    ex.on_command(&cmd(3, Action::Land), 0.0);
    assert_eq!(
        ex.tick(0.0).commands.first().and_then(|c| c.kind()),
        Some(CommandKind::Land)
    );
}

/// An onboard restarted beside a vehicle flying in OFFBOARD takes it over: it holds where the
/// vehicle is through the planner, reports itself flying, and takes work. Beside a vehicle in
/// another PX4 mode it leaves the vehicle to PX4 and reports it as PX4's.
#[test]
fn a_restarted_onboard_takes_over_a_vehicle_flying_in_offboard() {
    let p = Vec3::new(-40.0, -100.0, 10.0);
    let mut ex = lab();
    ex.on_vehicle(&state(p, true, Px4Mode::Offboard));
    assert_eq!(ex.mode(), DroneMode::Flying);
    let out = ex.tick(0.0);
    assert_eq!(out.steering, Some(Steering::Toward(Goal::fixed(p))));
    assert!(
        out.commands.is_empty(),
        "already in offboard: {:?}",
        out.commands
    );
    // Drift is corrected: the goal stays where it took over.
    ex.on_vehicle(&state(
        p + Vec3::new(0.6, 0.0, 0.0),
        true,
        Px4Mode::Offboard,
    ));
    assert_eq!(
        ex.tick(0.1).steering,
        Some(Steering::Toward(Goal::fixed(p)))
    );
    let goto = Action::Goto {
        target: Vec3::new(-40.0, -60.0, 10.0),
    };
    ex.on_command(&cmd(1, goto), 0.2);
    assert!(matches!(state_of(&ex), ActionState::Running { .. }));

    let mut ex = lab();
    ex.on_vehicle(&state(p, true, Px4Mode::Hold));
    assert_eq!(ex.tick(0.0).steering, Some(Steering::Still(p)));
    assert_eq!(
        ex.autopilot_took_over(),
        Some(Px4Mode::Hold),
        "PX4 flies it, and the status says so"
    );
}

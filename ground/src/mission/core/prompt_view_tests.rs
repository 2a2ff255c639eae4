//! The swarm as the prompts show it, read from one snapshot: which drones a plan may use, which
//! rest on the ground, the targets followed, the drones' lines, and what the monolithic model
//! may call.

use super::tests::{empty, heard, progress};
use super::*;
use std::time::{Duration, Instant};
use tacos_prompts::ActionName;
use tacos_shared::DroneMode;
use tacos_shared::action::Action;
use tacos_shared::messages::ActionState;
use tacos_shared::scenario::Scenario;

/// The city with alfa heard ten seconds ago (unavailable now) and bravo on the ground.
pub(super) fn alfa_silent_bravo_idle() -> (Scenario, Snapshot) {
    let scenario = Scenario::builtin("city").expect("city");
    let t0 = Instant::now();
    let mut snap = empty(t0);
    heard(&mut snap, "alfa", DroneMode::Flying, None);
    snap.now = t0 + Duration::from_secs(10);
    heard(&mut snap, "bravo", DroneMode::Idle, None);
    (scenario, snap)
}

/// alfa unavailable, bravo idle, charlie following the van, delta flying to a point with its
/// goto a third done.
fn swarm() -> (Scenario, Snapshot) {
    let (scenario, mut snap) = alfa_silent_bravo_idle();
    let tracking = Action::StartTracking {
        target: "van".into(),
    };
    let following = progress(3, tracking, ActionState::Done);
    heard(&mut snap, "charlie", DroneMode::Tracking, following);
    let target = tacos_shared::Vec3::new(10.0, 20.0, 12.0);
    let flying = progress(
        5,
        Action::Goto { target },
        ActionState::Running { progress: 0.33 },
    );
    heard(&mut snap, "delta", DroneMode::Flying, flying);
    (scenario, snap)
}

#[test]
fn one_snapshot_says_which_drones_a_plan_may_use_and_where_each_is() {
    let (scenario, snap) = swarm();
    assert_eq!(
        snap.swarm_ids(&scenario),
        ["alfa", "bravo", "charlie", "delta"]
    );
    assert_eq!(snap.available_ids(&scenario), ["bravo", "charlie", "delta"]);
    assert_eq!(snap.mode_of("alfa"), Some(DroneMode::Unavailable));
    assert_eq!(snap.mode_of("echo"), None);
    assert_eq!(snap.grounded_ids(), ["bravo"]);
    assert_eq!(snap.followed_targets(), ["van"]);
    let lines = snap.drone_lines(&scenario);
    let delta = lines
        .iter()
        .find(|l| l.id == "delta")
        .expect("delta's line");
    assert_eq!(delta.mode, DroneMode::Flying);
    assert_eq!(delta.state.as_deref(), Some("running 33%"));
    let (drones, places) = snap.enums(&scenario);
    assert_eq!(drones, snap.swarm_ids(&scenario));
    assert!(
        places.iter().any(|p| p == "van"),
        "a trackable target is a place: {places:?}"
    );
}

#[test]
fn the_monolithic_model_is_offered_only_what_each_ready_drone_can_do_now() {
    let (scenario, snap) = swarm();
    let mut book = PlanBook::default();
    book.mnl.next_task = 7;
    let callable = snap.callable(&scenario, &book);
    let offered: Vec<(&str, &str)> = callable
        .iter()
        .map(|c| (c.task.as_str(), c.drone.as_str()))
        .collect();
    // alfa is unavailable and delta busy with its goto; bravo and charlie get fresh task ids.
    assert_eq!(offered, [("A8", "bravo"), ("A9", "charlie")]);
    // On the ground: take off only; following: no take-off, and it may stop following.
    assert_eq!(callable[0].actions, [ActionName::ArmTakeoff]);
    assert!(!callable[1].actions.contains(&ActionName::ArmTakeoff));
    assert!(callable[1].actions.contains(&ActionName::StopTracking));
}

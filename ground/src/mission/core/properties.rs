//! Properties of judging a cycle's reply, over random swarms and random replies: whatever a
//! model writes, every call the core would send passes the safety gate against the snapshot of
//! the step that sends it, and no drone or task gets two calls in one step.

use super::*;
use crate::safety::SafetyGate;
use crate::swarm::{SwarmView, test_status};
use proptest::prelude::*;
use std::time::{Duration, Instant};
use tacos_prompts::render::TaskStatus;
use tacos_prompts::{ActionName, Call};
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionProgress, ActionState};
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneMode, Vec3};

const DRONES: [&str; 5] = ["alfa", "bravo", "charlie", "delta", "zulu"];
const TARGETS: [&str; 7] = [
    "car_2",
    "car_3",
    "skyscraper_1",
    "villa_1",
    "van",
    "none",
    "nowhere",
];

/// One drone of the random swarm: its mode, whether its status is stale, whether it is busy
/// with an action, and where it is.
#[derive(Debug, Clone)]
struct Drone {
    mode: DroneMode,
    stale: bool,
    busy: bool,
    x: f64,
    y: f64,
}

fn drone() -> impl Strategy<Value = Drone> {
    let mode = prop::sample::select(vec![
        DroneMode::Idle,
        DroneMode::Flying,
        DroneMode::Tracking,
        DroneMode::Unavailable,
    ]);
    (
        mode,
        any::<bool>(),
        any::<bool>(),
        -150.0..150.0f64,
        -150.0..150.0f64,
    )
        .prop_map(|(mode, stale, busy, x, y)| Drone {
            mode,
            stale,
            busy,
            x,
            y,
        })
}

fn call() -> impl Strategy<Value = Call> {
    let point = prop::option::of((-200.0..200.0f64, -200.0..200.0f64, -5.0..120.0f64));
    (
        0..DRONES.len(),
        1..5u32,
        0..ActionName::ALL.len(),
        0..TARGETS.len(),
        point,
    )
        .prop_map(|(d, task, a, t, xyz)| Call {
            task: format!("T{task}"),
            drone: DRONES[d].into(),
            action: ActionName::ALL[a],
            target: TARGETS[t].into(),
            xyz: xyz.map(|(x, y, z)| [x, y, z]),
        })
}

/// The snapshot of four drones (`zulu` is not in the swarm) at `now`.
fn snapshot(drones: &[Drone], now: Instant) -> Snapshot {
    let mut swarm = SwarmView::default();
    for (name, d) in DRONES.iter().zip(drones) {
        let mut status = test_status(name, d.mode);
        let z = if d.mode.is_airborne() { 10.0 } else { 0.0 };
        status.position = Vec3::new(d.x, d.y, z);
        status.action = d.busy.then_some(ActionProgress {
            seq: 1,
            task_id: None,
            action: Action::Hold,
            state: ActionState::Running { progress: 0.0 },
        });
        let heard = if d.stale {
            now - Duration::from_secs(3)
        } else {
            now
        };
        swarm.apply_status(status, heard);
    }
    Snapshot {
        swarm,
        targets: Vec::new(),
        now,
        ground: 1,
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    #[test]
    fn every_send_passes_the_gate_on_its_snapshot_and_no_drone_or_task_gets_two(
        drones in prop::collection::vec(drone(), 4),
        actions in prop::collection::vec(call(), 0..10),
        running in prop::collection::vec(call(), 0..3),
        served_first in any::<bool>(),
    ) {
        let gate = SafetyGate::new(Scenario::builtin("city").expect("city"));
        let snap = snapshot(&drones, Instant::now() + Duration::from_secs(10));
        let tasks: Vec<(Call, TaskStatus)> =
            running.into_iter().map(|c| (c, TaskStatus::Running)).collect();
        let served: Vec<Call> = actions.iter().take(usize::from(served_first)).cloned().collect();
        let judged = judge_cycle(&actions, None, &served, &snap, &gate, &tasks);
        let mut drones_sent: Vec<&str> = Vec::new();
        let mut tasks_sent: Vec<&str> = Vec::new();
        for (call, checked) in &judged.accepted {
            prop_assert_eq!(checked.drone().as_str(), call.drone.as_str());
            prop_assert!(
                gate.check(&snap.swarm, &call.drone, checked.action(), snap.now).is_ok(),
                "{} was accepted but the gate refuses it", call
            );
            prop_assert!(!drones_sent.contains(&call.drone.as_str()), "{} twice", call.drone);
            prop_assert!(!tasks_sent.contains(&call.task.as_str()), "{} twice", call.task);
            prop_assert!(!served.iter().any(|s| s.drone == call.drone), "{} was served", call.drone);
            prop_assert!(!tasks.iter().any(|(t, _)| t.drone == call.drone), "{} is busy", call.drone);
            drones_sent.push(&call.drone);
            tasks_sent.push(&call.task);
        }
    }
}

/// Four drones flying idle 60 m apart along y = -100, heard just now.
fn four_ready() -> Snapshot {
    let ready = |x: f64| Drone {
        mode: DroneMode::Flying,
        stale: false,
        busy: false,
        x,
        y: -100.0,
    };
    snapshot(
        &[ready(-60.0), ready(0.0), ready(60.0), ready(120.0)],
        Instant::now(),
    )
}

/// The property above is not vacuous: a plain reply to ready drones is sent whole (and of its
/// 400 random cases, 83 sent one call or two, measured once with a counter).
#[test]
fn a_reply_to_ready_drones_is_accepted_whole() {
    let gate = SafetyGate::new(Scenario::builtin("city").expect("city"));
    let snap = four_ready();
    let goto =
        |task: &str, drone: &str, target: &str| Call::named(task, drone, ActionName::Goto, target);
    let actions = [goto("T1", "alfa", "car_2"), goto("T2", "bravo", "car_3")];
    let judged = judge_cycle(&actions, None, &[], &snap, &gate, &[]);
    assert_eq!(judged.rejections, Vec::<String>::new());
    assert_eq!(judged.gate_refusals, Vec::<String>::new());
    // Sent nearest first (`nearest_first`): bravo is closer to its car.
    let sent: Vec<&str> = judged
        .accepted
        .iter()
        .map(|(c, _)| c.drone.as_str())
        .collect();
    assert_eq!(sent, ["bravo", "alfa"]);
}

/// Three drones sent to one car in one reply each get a point of their own, at least the safety
/// distance from the others' (the goal points as `check_live` claims them in turn).
#[test]
fn three_drones_sent_to_one_car_get_points_of_their_own() {
    let gate = SafetyGate::new(Scenario::builtin("city").expect("city"));
    let snap = four_ready();
    let to_car = |task: &str, drone: &str| Call::named(task, drone, ActionName::Goto, "car_7");
    let actions = [
        to_car("T1", "alfa"),
        to_car("T2", "bravo"),
        to_car("T3", "charlie"),
    ];
    let judged = judge_cycle(&actions, None, &[], &snap, &gate, &[]);
    assert_eq!(judged.rejections, Vec::<String>::new());
    let points: Vec<Vec3> = judged
        .accepted
        .iter()
        .filter_map(|(_, c)| match c.action() {
            Action::Goto { target } => Some(*target),
            _ => None,
        })
        .collect();
    assert_eq!(points.len(), 3);
    let apart = gate.scenario().limits.safety_distance;
    for (i, a) in points.iter().enumerate() {
        for b in &points[i + 1..] {
            assert!(
                (a - b).norm() >= apart,
                "{a:?} and {b:?} closer than {apart} m"
            );
        }
    }
}

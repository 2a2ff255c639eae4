//! The Coordinator's request from one snapshot (`coordinator_ask`): the drones it may plan for,
//! the aids that act on the request on and off, and no request when no drone can fly.

use super::prompt_view_tests::alfa_silent_bravo_idle;
use super::tests::{empty, heard};
use super::*;
use crate::mission::aids::{Aid, ModelAids};
use crate::mission::log::Record;
use crate::mission::report::MissionError;
use std::time::{Duration, Instant};
use tacos_shared::DroneMode;
use tacos_shared::scenario::Scenario;

/// alfa silent for ten seconds (unavailable now), bravo and charlie on the ground.
fn swarm() -> (Scenario, Snapshot) {
    let (scenario, mut snap) = alfa_silent_bravo_idle();
    heard(&mut snap, "charlie", DroneMode::Idle, None);
    (scenario, snap)
}

fn ask(
    line: &str,
    snap: &Snapshot,
    scenario: &Scenario,
    aids: ModelAids,
) -> (Result<CoordinatorAsk, MissionError>, Vec<Aid>) {
    let book = PlanBook::default();
    let context = CoordinatorContext {
        snap,
        scenario,
        book: &book,
        history: &[],
        events: &[],
        aids,
    };
    let mut effects = Vec::new();
    let asked = coordinator_ask(&Coordination::Pilot(line.into()), &context, &mut effects);
    let fired = effects
        .iter()
        .filter_map(|e| match e {
            Effect::Note(Record::AidFired { aid, .. }) => Some(*aid),
            _ => None,
        })
        .collect();
    (asked, fired)
}

#[test]
fn the_request_offers_only_the_available_drones_and_holds_the_reply_to_them() {
    let (scenario, snap) = swarm();
    let (asked, fired) = ask("bravo, go to car_3", &snap, &scenario, ModelAids::none());
    let asked = asked.expect("a request");
    assert!(fired.is_empty(), "{fired:?}");
    assert_eq!(asked.check.drones, ["alfa", "bravo", "charlie"]);
    assert_eq!(asked.check.available, ["bravo", "charlie"]);
    assert_eq!(asked.grounded, ["bravo", "charlie"]);
    assert_eq!(asked.check.scope, None, "place-scope is off");
    let offered = asked.schema.to_string();
    assert!(
        offered.contains("\"bravo\"") && !offered.contains("\"alfa\""),
        "{offered}"
    );
    // The request is the last message, with the instruction and the swarm's lines.
    let request = &asked.messages.last().expect("the request").content;
    assert!(request.contains("bravo, go to car_3"), "{request}");
    assert!(
        request.contains("alfa"),
        "the swarm's lines show every drone: {request}"
    );
}

#[test]
fn place_scope_and_whole_swarm_act_on_the_request_only_when_on() {
    let (scenario, snap) = swarm();
    let on = ModelAids::none()
        .with(Aid::PlaceScope, true)
        .with(Aid::WholeSwarm, true);
    let (asked, fired) = ask("bravo, go to car_3", &snap, &scenario, on);
    let asked = asked.expect("a request");
    assert_eq!(fired, [Aid::PlaceScope]);
    assert_eq!(
        asked.check.scope.as_deref(),
        Some(&["car_3".to_owned()][..])
    );
    assert!(!asked.schema.to_string().contains("\"car_4\""));

    let (asked, _) = ask("all drones take off", &snap, &scenario, on);
    let check = asked.expect("a request").check;
    let idle = DroneMode::Idle;
    assert!(check.whole_swarm);
    assert_eq!(
        check.modes,
        vec![("bravo".to_owned(), idle), ("charlie".to_owned(), idle)]
    );
    let (asked, _) = ask("all drones take off", &snap, &scenario, ModelAids::none());
    assert!(!asked.expect("a request").check.whole_swarm);
}

#[test]
fn with_no_drone_available_nothing_is_asked() {
    let scenario = Scenario::builtin("city").expect("city");
    let t0 = Instant::now();
    let mut snap = empty(t0);
    heard(&mut snap, "alfa", DroneMode::Idle, None);
    snap.now = t0 + Duration::from_secs(10);
    let (asked, fired) = ask("alfa, take off", &snap, &scenario, ModelAids::small());
    assert!(matches!(asked, Err(MissionError::NoDroneAvailable)));
    assert!(fired.is_empty());
}

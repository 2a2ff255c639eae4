//! A cycle's request from one snapshot (`supervisor_ask`, `monolithic_ask`): only what can start
//! now is offered, no request when nothing can, and the plan's reasoning shown in `tacos` only.

use super::cycle_ask::{monolithic_ask, supervisor_ask};
use super::tests::{empty, gate, goto, heard};
use super::*;
use crate::mission::config::Mode;
use std::time::Instant;
use tacos_prompts::render::TaskStatus;
use tacos_prompts::{ActionName, Call};
use tacos_shared::DroneMode;

/// alfa on the ground, bravo flying; a plan: alfa takes off, bravo goes to car_2.
fn plan_and_swarm() -> (PlanBook, Snapshot) {
    let mut snap = empty(Instant::now());
    heard(&mut snap, "alfa", DroneMode::Idle, None);
    heard(&mut snap, "bravo", DroneMode::Flying, None);
    let mut book = PlanBook::default();
    let calls = vec![
        Call::named("T1", "alfa", ActionName::ArmTakeoff, "none"),
        goto("T2", "bravo", "car_2"),
    ];
    adopt(&mut book, "REASONING-OF-THE-PLAN".into(), calls);
    (book, snap)
}

#[test]
fn the_supervisor_is_offered_what_can_start_and_sees_the_plan_s_reasoning_in_tacos_only() {
    let gate = gate();
    let (book, snap) = plan_and_swarm();
    let request = supervisor_ask(&book, &snap, &gate, &[], Mode::Tacos).expect("a decision");
    let offered: Vec<&str> = (request.only.iter().flatten())
        .map(|c| c.task.as_str())
        .collect();
    assert_eq!(offered, ["T1", "T2"]);
    assert_eq!(request.drones, 2);
    assert_eq!(request.tasks.len(), 2);
    let prompt = &request.messages.last().expect("the request").content;
    assert!(prompt.contains("REASONING-OF-THE-PLAN"), "{prompt}");
    let wor = supervisor_ask(&book, &snap, &gate, &[], Mode::Wor).expect("a decision");
    let prompt = &wor.messages.last().expect("the request").content;
    assert!(!prompt.contains("REASONING-OF-THE-PLAN"), "{prompt}");
    // The same book and snapshot give the same request.
    assert_eq!(
        supervisor_ask(&book, &snap, &gate, &[], Mode::Tacos),
        Some(request)
    );
}

#[test]
fn with_nothing_that_can_start_the_supervisor_is_not_asked() {
    let gate = gate();
    let (mut book, snap) = plan_and_swarm();
    for task in book.plan.as_mut().expect("a plan").tasks.iter_mut() {
        task.status = TaskStatus::Done;
    }
    assert_eq!(supervisor_ask(&book, &snap, &gate, &[], Mode::Tacos), None);
    assert_eq!(
        supervisor_ask(&PlanBook::default(), &snap, &gate, &[], Mode::Tacos),
        None
    );
}

#[test]
fn the_monolithic_model_is_asked_only_when_a_drone_can_act() {
    let gate = gate();
    let (_, snap) = plan_and_swarm();
    let book = PlanBook::default();
    let (request, offered) =
        monolithic_ask(&book, &snap, gate.scenario(), &[]).expect("two ready drones");
    assert_eq!(offered, 2);
    assert_eq!(request.only, None);
    let schema = request.schema.to_string();
    assert!(
        schema.contains("\"A1\"") && schema.contains("\"A2\""),
        "{schema}"
    );
    let nobody = empty(Instant::now());
    assert_eq!(monolithic_ask(&book, &nobody, gate.scenario(), &[]), None);
}

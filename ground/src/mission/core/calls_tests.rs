//! Events that arrive while a model call is in flight (`CallQueue`): a lost drone while the
//! Supervisor or the Coordinator thinks, a direct command with work queued, a reply from before
//! the work was replaced. No process, no clock, no model.

use super::replan_tests::chase;
use super::*;
use crate::mission::config::Mode;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionUpdate, Overtaken};
use crate::swarm::SwarmChange;
use tacos_shared::DroneId;

/// bravo, chasing the van, is lost: the replan the core asks for.
fn replan_after_a_lost_tracker() -> Coordination {
    let (mut book, snap) = chase();
    let lost = SwarmChange::Left(DroneId::new("bravo").expect("valid"));
    let effects = membership_changed(&mut book, &snap, Mode::Tacos, &lost);
    let replans: Vec<Coordination> = effects
        .into_iter()
        .filter_map(|e| match e {
            Effect::Replan(instruction) => Some(Coordination::Replan(instruction)),
            _ => None,
        })
        .collect();
    let [replan] = &replans[..] else {
        panic!("one replan: {replans:?}")
    };
    replan.clone()
}

#[test]
fn a_drone_lost_while_the_supervisor_thinks_drops_its_call_and_the_replan_goes_first() {
    let replan = replan_after_a_lost_tracker();
    let Coordination::Replan(instruction) = &replan else {
        unreachable!()
    };
    assert!(instruction.contains("van"), "{instruction}");
    let mut calls = CallQueue::default();
    calls.cycle_due(true);
    assert_eq!(calls.next(true), Some(NextCall::Cycle));
    calls.started("supervisor");
    let epoch = calls.epoch();
    // The Supervisor's reply would act on the plan before the loss: its call is dropped.
    let effects = calls.want(replan.clone());
    assert_eq!(
        effects,
        [
            Effect::Note(Record::Event {
                text: "the supervisor's call in flight was dropped, overtaken by a newer \
                       instruction or replan"
                    .into()
            }),
            Effect::DropCall {
                layer: "supervisor",
                by: Overtaken::NewerWork
            },
        ]
    );
    // An outcome meanwhile makes a cycle due: the replan still goes first.
    calls.cycle_due(true);
    assert_eq!(calls.next(true), Some(NextCall::Coordinate(replan)));
    calls.started("coordinator");
    assert_eq!(calls.next(true), None, "one call at a time");
    // The new plan is adopted (its work replaces the old), then its first cycle.
    calls.answered();
    calls.work_replaced();
    assert!(!calls.is_current(epoch), "a reply asked before is not used");
    assert_eq!(calls.next(true), Some(NextCall::Cycle));
    assert_eq!(calls.next(true), None);
}

#[test]
fn a_drone_lost_while_the_coordinator_thinks_waits_behind_it() {
    let replan = replan_after_a_lost_tracker();
    let mut calls = CallQueue::default();
    calls.want(Coordination::Pilot("all drones take off".into()));
    assert_eq!(
        calls.next(true),
        Some(NextCall::Coordinate(Coordination::Pilot(
            "all drones take off".into()
        )))
    );
    calls.started("coordinator");
    // The Coordinator's call is not dropped: its plan is made with the swarm as it is asked,
    // and the replan after it sees the loss.
    assert_eq!(calls.want(replan.clone()), []);
    calls.cycle_due(true);
    assert_eq!(calls.next(true), None);
    assert_eq!(calls.answered(), Some("coordinator"));
    assert_eq!(calls.next(true), Some(NextCall::Coordinate(replan)));
}

#[test]
fn a_direct_command_while_a_call_is_in_flight_drops_it_and_the_work_queued_behind_it() {
    let replan = replan_after_a_lost_tracker();
    let mut calls = CallQueue::default();
    calls.want(Coordination::Pilot("find the dog".into()));
    assert!(matches!(calls.next(true), Some(NextCall::Coordinate(_))));
    calls.started("coordinator");
    calls.want(Coordination::Pilot("all drones take off".into()));
    calls.want(replan);
    calls.cycle_due(true);
    let epoch = calls.epoch();

    let effects = calls.overridden();
    let dropped: Vec<&Effect> = effects
        .iter()
        .filter(|e| matches!(e, Effect::DropCall { .. }))
        .collect();
    assert_eq!(
        dropped,
        [&Effect::DropCall {
            layer: "coordinator",
            by: Overtaken::DirectCommand
        }]
    );
    let told: Vec<&str> = effects
        .iter()
        .filter_map(|e| match e {
            Effect::Tell(MissionUpdate::Event {
                topic: EventTopic::PlanEnded,
                text,
            }) => Some(text.as_str()),
            _ => None,
        })
        .collect();
    assert_eq!(told.len(), 2, "{told:?}");
    assert!(told[0].starts_with("instruction \"all drones take off\" dropped"));
    assert!(told[1].starts_with("replan dropped ("));
    // Nothing runs after the command until the pilot asks again: no queued work, no cycle, and
    // a reply from before would not be used.
    assert!(!calls.is_current(epoch));
    assert_eq!(calls.next(true), None);
    // A second command with nothing in flight drops nothing.
    assert_eq!(calls.overridden(), []);
}

#[test]
fn a_cycle_is_started_only_when_due_and_the_models_have_work() {
    let mut calls = CallQueue::default();
    assert_eq!(calls.next(true), None);
    calls.cycle_due(true);
    assert_eq!(calls.next(false), None, "no plan: no cycle");
    assert_eq!(
        calls.next(true),
        Some(NextCall::Cycle),
        "still due once a plan is in force"
    );
    calls.set_cycle_due(true);
    calls.set_cycle_due(false);
    assert_eq!(calls.next(true), None);
    // Dropping with nothing in flight is nothing.
    assert_eq!(calls.drop_call(Overtaken::SessionClosed), []);
}

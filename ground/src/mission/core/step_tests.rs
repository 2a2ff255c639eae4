//! The core fed inputs (`Core::step`), as the driver feeds it: a lost drone and a direct command
//! while models think, an instruction naming a drone the swarm lacks, a plan held for the
//! pilot and answered, the cycle timeout, the cycle limit. No process, no clock, no model.

use super::cycle_reply_tests::{gate, start_due_cycle};
use super::replan_tests::chase;
use super::*;
use crate::mission::config::{MissionConfig, Mode};
use crate::mission::directives::Directive;
use crate::mission::log::Record;
use crate::mission::report::{MissionUpdate, Overtaken};
use crate::safety::SafetyGate;
use crate::swarm::{SwarmChange, SwarmView, test_status};
use std::time::{Duration, Instant};
use tacos_prompts::render::HistoryEntry;
use tacos_prompts::{ActionName, Call};
use tacos_shared::action::Action;
use tacos_shared::messages::WorldEvent;
use tacos_shared::{DroneId, DroneMode, Vec3};

/// A fresh core of `mode` with the default configuration.
pub(super) fn core(mode: Mode) -> Core {
    Core::new(&MissionConfig {
        mode,
        ..MissionConfig::default()
    })
}

/// alfa, bravo and charlie on the ground, heard at `now`.
pub(super) fn grounded(now: Instant) -> Snapshot {
    super::cycle_reply_tests::grounded(now, None)
}

fn errors(effects: &[Effect]) -> Vec<&str> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Tell(MissionUpdate::Error(text)) => Some(text.as_str()),
            _ => None,
        })
        .collect()
}

fn events(effects: &[Effect]) -> Vec<&str> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Note(Record::Event { text }) => Some(text.as_str()),
            _ => None,
        })
        .collect()
}

fn dropped(effects: &[Effect]) -> Vec<(&'static str, Overtaken)> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::DropCall { layer, by } => Some((*layer, *by)),
            _ => None,
        })
        .collect()
}

fn take_offs() -> Vec<Call> {
    vec![
        Call::named("T1", "alfa", ActionName::ArmTakeoff, "none"),
        Call::named("T2", "bravo", ActionName::ArmTakeoff, "none"),
    ]
}

fn reply(calls: Vec<Call>) -> Input {
    Input::CoordinatorReply {
        instruction: "alfa and bravo, take off".into(),
        grounded: vec!["alfa".into(), "bravo".into(), "charlie".into()],
        answer: Ok(("Both go up.".into(), calls, None)),
    }
}

#[test]
fn a_lost_drone_then_a_direct_command_while_models_think() {
    let (book, snap) = chase();
    let gate = gate();
    let mut core = core(Mode::Tacos);
    core.book = book;
    core.step(Input::Started, &snap, &gate);
    core.calls.cycle_due(true);
    // A Supervisor call in flight (the chase has no decision to make: started by hand).
    assert_eq!(core.next_call(snap.now), Some(NextCall::Cycle));
    core.calls.started("supervisor");
    // bravo, chasing the van, is lost while the Supervisor thinks: its call is dropped, the
    // replan is queued and goes first, and the history remembers the loss.
    let bravo = DroneId::new("bravo").expect("valid");
    let effects = core.step(Input::Membership(SwarmChange::Left(bravo)), &snap, &gate);
    assert_eq!(dropped(&effects), [("supervisor", Overtaken::NewerWork)]);
    assert!(
        effects
            .iter()
            .any(|e| matches!(e, Effect::Note(Record::Replan { .. })))
    );
    assert!(matches!(
        core.history.last(),
        Some(HistoryEntry::Event(text)) if text == "bravo became unavailable"
    ));
    let Some(NextCall::Coordinate(Coordination::Replan(why))) = core.next_call(snap.now) else {
        panic!("the replan goes next")
    };
    assert!(why.contains("van"), "{why}");
    core.calls.started("coordinator");
    // The pilot types `land all` while the Coordinator thinks: the core hands the directive to
    // the engine, which carries it out and feeds the override back.
    let effects = core.step(Input::Pilot("land all".into()), &snap, &gate);
    assert_eq!(
        effects,
        [Effect::Direct {
            text: "land all".into(),
            directive: Directive::LandAll
        }]
    );
    let effects = core.step(Input::Overridden, &snap, &gate);
    assert_eq!(
        dropped(&effects),
        [("coordinator", Overtaken::DirectCommand)]
    );
    assert!(core.book.plan.is_none(), "the plan in force ended");
    assert!(
        effects.iter().any(|e| matches!(
            e,
            Effect::Note(Record::PlanEnded { how }) if how == "interrupted by a direct command"
        )),
        "{effects:?}"
    );
    assert_eq!(
        core.next_call(snap.now),
        None,
        "nothing is asked after the command"
    );
}

#[test]
fn an_instruction_naming_a_drone_the_swarm_lacks_is_refused_before_any_model() {
    let snap = grounded(Instant::now());
    let gate = gate();
    let mut core = core(Mode::Tacos);
    let effects = core.step(Input::Pilot("zulu, take off".into()), &snap, &gate);
    assert_eq!(
        errors(&effects),
        [
            "there is no drone zulu in this swarm (its drones: alfa, bravo, charlie); nothing was \
             sent: address one of those"
        ]
    );
    assert!(
        effects
            .iter()
            .any(|e| matches!(e, Effect::Note(Record::Pilot { .. })))
    );
    assert!(
        !effects
            .iter()
            .any(|e| matches!(e, Effect::InstructionBegun(_)))
    );
    assert_eq!(core.next_call(snap.now), None, "no model is asked");
    // An instruction to the swarm's drones goes to the Coordinator, remembered and begun.
    let effects = core.step(Input::Pilot("alfa, take off".into()), &snap, &gate);
    assert!(effects.contains(&Effect::InstructionBegun("alfa, take off".into())));
    assert!(effects.contains(&Effect::Note(Record::History {
        entry: HistoryEntry::Pilot("alfa, take off".into())
    })));
    assert_eq!(
        core.next_call(snap.now),
        Some(NextCall::Coordinate(Coordination::Pilot(
            "alfa, take off".into()
        )))
    );
}

#[test]
fn a_held_plan_is_shown_and_flies_only_once_the_pilot_approves_what_is_left_of_it() {
    let snap = grounded(Instant::now());
    let gate = gate();
    let mut core = core(Mode::Tacos);
    core.step(Input::Pilot("confirm on".into()), &snap, &gate);
    let effects = core.step(reply(take_offs()), &snap, &gate);
    assert!(core.book.plan.is_none() && core.held.is_some());
    assert!(
        events(&effects)
            .iter()
            .any(|t| t.contains("awaits your approval") && t.contains("T2 bravo arm_takeoff()")),
        "{effects:?}"
    );
    assert_eq!(core.next_call(snap.now), None, "a held plan has no cycle");
    let effects = core.step(Input::Pilot("drop T9".into()), &snap, &gate);
    assert!(events(&effects).iter().any(|t| t.contains("no task T9")));
    core.step(Input::Pilot("drop T2".into()), &snap, &gate);
    core.step(Input::Pilot("approve".into()), &snap, &gate);
    let plan = core
        .book
        .plan
        .as_ref()
        .expect("the approved plan is in force");
    let tasks: Vec<&str> = plan.tasks.iter().map(|t| t.call.task.as_str()).collect();
    assert_eq!(tasks, ["T1"]);
    assert_eq!(core.next_call(snap.now), Some(NextCall::Cycle));
}

#[test]
fn a_rejected_plan_goes_back_to_the_coordinator_with_the_pilot_s_words() {
    let snap = grounded(Instant::now());
    let gate = gate();
    let mut core = core(Mode::Tacos);
    core.step(Input::Pilot("confirm on".into()), &snap, &gate);
    core.step(reply(take_offs()), &snap, &gate);
    core.step(Input::Pilot("reject bravo stays down".into()), &snap, &gate);
    assert!(core.held.is_none() && core.book.plan.is_none());
    let again = "The pilot rejected your plan for \"alfa and bravo, take off\": bravo stays \
                 down. Plan again.";
    assert_eq!(
        core.next_call(snap.now),
        Some(NextCall::Coordinate(Coordination::Pilot(again.into())))
    );
    // A direct command ends a plan still held.
    core.step(reply(take_offs()), &snap, &gate);
    let effects = core.step(Input::Overridden, &snap, &gate);
    assert!(core.held.is_none());
    assert!(
        events(&effects)
            .iter()
            .any(|t| t.contains("awaiting approval ended"))
    );
}

#[test]
fn while_work_is_under_way_a_cycle_is_due_after_the_timeout_and_not_before() {
    let t0 = Instant::now();
    let gate = gate();
    let mut core = core(Mode::Tacos);
    core.step(Input::Started, &grounded(t0), &gate);
    let timeout = core.bounds.cycle_timeout;
    // The plan comes, and its first cycle starts, well after the mission started: the timeout
    // counts from that cycle.
    let t1 = t0 + timeout * 2;
    core.step(reply(take_offs()), &grounded(t1), &gate);
    assert_eq!(
        core.next_call(t1),
        Some(NextCall::Cycle),
        "the plan's first cycle"
    );
    core.step(Input::Tick, &grounded(t1 + timeout / 2), &gate);
    assert_eq!(core.next_call(t1 + timeout / 2), None);
    let later = t1 + timeout + Duration::from_millis(1);
    core.step(Input::Tick, &grounded(later), &gate);
    assert_eq!(core.next_call(later), Some(NextCall::Cycle));
}

#[test]
fn a_plan_past_its_cycles_ends_with_an_error_and_no_cycle_is_asked() {
    let snap = grounded(Instant::now());
    let gate = gate();
    let mut core = core(Mode::Tacos);
    core.step(reply(take_offs()), &snap, &gate);
    let mut effects = Vec::new();
    assert!(core.cycle_allowed(&mut effects));
    if let Some(plan) = core.book.plan.as_mut() {
        plan.cycles = core.bounds.max_cycles_per_plan;
    }
    assert!(!core.cycle_allowed(&mut effects));
    assert!(core.book.plan.is_none());
    assert_eq!(
        errors(&effects),
        ["the plan was not complete after 30 Supervisor cycles"]
    );
}

#[test]
fn the_session_s_end_drops_the_call_in_flight_and_ends_the_log() {
    let snap = grounded(Instant::now());
    let gate = gate();
    let mut core = core(Mode::Mnl);
    core.step(Input::Pilot("alfa, take off".into()), &snap, &gate);
    start_due_cycle(&mut core, &snap, &gate);
    let effects = core.step(Input::Closed, &snap, &gate);
    assert_eq!(
        dropped(&effects),
        [("monolithic", Overtaken::SessionClosed)]
    );
    assert!(matches!(
        effects.last(),
        Some(Effect::Note(Record::MissionEnd { .. }))
    ));
}

/// A mission's worth of inputs, each with its step's snapshot: an instruction, its plan, a
/// cycle whose call is sent, a detection, a lost drone, `land all`, the end.
pub(super) fn a_mission(t0: Instant, gate: &SafetyGate) -> Vec<(Input, Snapshot)> {
    let at = |s: u64| grounded(t0 + Duration::from_secs(s));
    let alfa_up = || {
        let snap = at(3);
        let checked = gate
            .check(&snap.swarm, "alfa", &Action::ArmTakeoff, snap.now)
            .expect("alfa may take off");
        CycleChoice {
            reasoning: "Alfa first.".into(),
            claim: false,
            all_passed: true,
            accepted: vec![(take_offs()[0].clone(), checked)],
            later: Vec::new(),
        }
    };
    let mut lost = at(20);
    lost.swarm = SwarmView::default();
    for name in ["alfa", "charlie"] {
        lost.swarm
            .apply_status(test_status(name, DroneMode::Idle), lost.now);
    }
    vec![
        (Input::Started, at(0)),
        (Input::Pilot("alfa and bravo, take off".into()), at(1)),
        (reply(take_offs()), at(2)),
        (Input::CycleReply(Ok(alfa_up())), at(3)),
        (Input::Sent(Ok(1)), at(3)),
        (Input::Tick, at(4)),
        (
            Input::World(WorldEvent::Detection {
                drone: DroneId::new("alfa").expect("valid"),
                target: "suspect".into(),
                landmark: None,
                position: Vec3::new(10.0, 20.0, 0.0),
            }),
            at(5),
        ),
        (Input::Tick, at(16)),
        (
            Input::Membership(SwarmChange::Left(DroneId::new("bravo").expect("valid"))),
            lost.clone(),
        ),
        (Input::Pilot("land all".into()), lost.clone()),
        (Input::Overridden, lost.clone()),
        (Input::Closed, lost),
    ]
}

/// Feeds `input` to `core` as the driver does (`driver::run_with`): the input, then — unless
/// it asked for something awaited (a send or a direct command, whose result or override is
/// the caller's next input) — `Input::CallDue` while no call is in flight and one is due, with the
/// Coordinator's work fed back (`Input::Coordinate`), all on `snap`. Each step as its trace
/// (from `t0`) and its effects.
pub(super) fn drive(
    core: &mut Core,
    input: Input,
    snap: &Snapshot,
    gate: &SafetyGate,
    t0: Instant,
) -> Vec<(TracedStep, Vec<Effect>)> {
    let one = |core: &mut Core, input: Input| {
        let traced = trace_step(&input, snap, t0);
        (traced, core.step(input, snap, gate))
    };
    let first = one(core, input);
    let awaited =
        (first.1.iter()).any(|e| matches!(e, Effect::Send { .. } | Effect::Direct { .. }));
    let mut steps = vec![first];
    while !awaited && core.calls.in_flight().is_none() && core.has_call_due() {
        let due = one(core, Input::CallDue);
        let work = due.1.iter().find_map(|e| match e {
            Effect::Coordinate(work) => Some(work.clone()),
            _ => None,
        });
        steps.push(due);
        match work {
            Some(work) => steps.push(one(core, Input::Coordinate(work))),
            None => break,
        }
    }
    steps
}

/// Runs `a_mission` on a fresh core as the driver would (`drive`); the effects of every step,
/// and the core's book and history at the end.
fn run(t0: Instant) -> (Vec<Vec<Effect>>, PlanBook, Vec<HistoryEntry>) {
    let gate = gate();
    let mut core = core(Mode::Tacos);
    let mut effects = Vec::new();
    for (input, snap) in a_mission(t0, &gate) {
        let steps = drive(&mut core, input, &snap, &gate, t0);
        effects.extend(steps.into_iter().map(|(_, effects)| effects));
    }
    (effects, core.book, core.history)
}

#[test]
fn the_same_inputs_and_snapshots_give_the_same_effects() {
    let t0 = Instant::now();
    let (first, book, history) = run(t0);
    // The run did what a mission does: alfa's take-off sent, the detection and the loss
    // remembered with the instruction and its plan, the plan ended by the direct command.
    let sent: Vec<&Effect> = first
        .iter()
        .flatten()
        .filter(|e| matches!(e, Effect::Send { .. }))
        .collect();
    assert_eq!(sent.len(), 1, "{first:#?}");
    assert!(book.plan.is_none());
    assert_eq!(history.len(), 4, "{history:?}");
    assert_eq!(run(t0), (first, book, history));
}

#[test]
fn a_cycle_starts_only_with_a_decision_to_make_and_a_plan_stuck_too_long_is_given_up() {
    let t0 = Instant::now();
    let gate = gate();
    let mut core = core(Mode::Tacos);
    // A goto for alfa on the ground, with no take-off (none was added: nobody was grounded
    // when the plan was asked for, as far as the reply says).
    core.step(
        Input::CoordinatorReply {
            instruction: "alfa, to car_2".into(),
            grounded: Vec::new(),
            answer: Ok((
                "Alfa goes.".into(),
                vec![Call::named("T1", "alfa", ActionName::Goto, "car_2")],
                None,
            )),
        },
        &grounded(t0),
        &gate,
    );
    let (start, effects) = core.start_cycle(&grounded(t0), &gate);
    assert!(start.is_none() && effects.is_empty(), "{effects:?}");
    let later = t0 + super::book::STUCK_AFTER + Duration::from_secs(1);
    let (start, effects) = core.start_cycle(&grounded(later), &gate);
    assert!(start.is_none());
    assert!(core.book.plan.is_none(), "the stuck plan was not given up");
    assert!(
        errors(&effects)
            .iter()
            .any(|e| e.starts_with("the plan was given up: nothing has run or could start")),
        "{effects:?}"
    );
    // A plan whose take-offs can start: the cycle starts, and its call is in flight.
    core.step(reply(take_offs()), &grounded(later), &gate);
    let (start, _) = core.start_cycle(&grounded(later), &gate);
    let start = start.expect("a cycle to ask for");
    assert_eq!(
        (start.layer, start.kind),
        ("supervisor", CycleKind::Supervisor)
    );
    assert_eq!(start.request.only.map(|c| c.len()), Some(2));
    core.calls.cycle_due(true);
    assert_eq!(core.next_call(later), None, "a call is in flight");
}

#[test]
fn a_drone_that_took_off_while_the_coordinator_thought_gets_no_implied_take_off() {
    let t0 = Instant::now();
    let gate = gate();
    let mut core = core(Mode::Tacos);
    // Asked with alfa and bravo on the ground; bravo's take-off (of the plan before) has
    // finished by the reply, alfa is still on the ground.
    let mut snap = grounded(t0);
    snap.swarm
        .apply_status(test_status("bravo", DroneMode::Flying), t0);
    let effects = core.step(
        Input::CoordinatorReply {
            instruction: "alfa and bravo, to car_2 and car_3".into(),
            grounded: vec!["alfa".into(), "bravo".into()],
            answer: Ok((
                "Both go.".into(),
                vec![
                    Call::named("T1", "alfa", ActionName::Goto, "car_2"),
                    Call::named("T2", "bravo", ActionName::Goto, "car_3"),
                ],
                None,
            )),
        },
        &snap,
        &gate,
    );
    let plan: Vec<String> = core.book.tasks().map(|t| t.call.to_string()).collect();
    assert_eq!(
        plan,
        [
            "T3 alfa arm_takeoff()",
            "T1 alfa goto(car_2)",
            "T2 bravo goto(car_3)"
        ],
        "{effects:?}"
    );
}

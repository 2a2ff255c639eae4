//! A mission's steps written as the log writes them (`--trace-steps`), read back and fed to a
//! fresh core: the same effects at every step, and every kind of input kept.

use super::cycle_reply_tests::gate;
use super::step_tests::{a_mission, core, drive};
use super::*;
use crate::mission::config::Mode;
use crate::mission::log::{Line, Record};
use crate::mission::replay::{ReplayError, replay};
use crate::mission::report::MissionError;
use crate::swarm::SwarmChange;
use std::time::{Duration, Instant};
use tacos_prompts::{ActionName, Call};
use tacos_shared::DroneId;
use tacos_shared::action::Action;

/// `record` written as a log line and read back.
fn through_the_log(record: Record) -> Record {
    let text = serde_json::to_string(&record).expect("a record is written");
    serde_json::from_str(&text).expect("and read back")
}

#[test]
fn a_traced_mission_read_back_gives_a_fresh_core_the_same_effects_at_every_step() {
    let t0 = Instant::now();
    let gate = gate();
    let mut core = core(Mode::Tacos);
    let Record::TraceBegun { core: began } = through_the_log(Record::TraceBegun {
        core: core.traced(),
    }) else {
        panic!("not a trace's beginning");
    };
    let mut steps = Vec::new();
    for (input, snap) in a_mission(t0, &gate) {
        steps.extend(drive(&mut core, input, &snap, &gate, t0));
    }
    let mut fresh = Core::from_trace(&began);
    // Any base: only the times between steps and the ages at each count.
    let base = Instant::now() + Duration::from_secs(3600);
    let mut sends = 0;
    let mut asks = Vec::new();
    for (i, (traced, effects)) in steps.into_iter().enumerate() {
        let Record::Step(read) = through_the_log(Record::Step(traced)) else {
            panic!("not a step");
        };
        let (input, snap) = read.replayed(&gate, base).expect("a step replays");
        let again = fresh.step(input, &snap, &gate);
        assert_eq!(again, effects, "step {i}: {:?}", read.input);
        sends += effects
            .iter()
            .filter(|e| matches!(e, Effect::Send { .. }))
            .count();
        asks.extend(effects.iter().filter_map(|e| match e {
            Effect::Ask(Ask::Coordinator(ask)) => Some(ask.instruction.clone()),
            Effect::Ask(Ask::Cycle(start)) => Some(start.layer.to_owned()),
            _ => None,
        }));
    }
    // The mission did what it does: the Coordinator asked, a cycle whose take-off was sent,
    // the next cycle after it went, and the replan for the lost drone.
    assert_eq!(sends, 1);
    assert_eq!(
        asks[..3],
        ["alfa and bravo, take off", "supervisor", "supervisor"]
    );
    assert!(
        asks[3].starts_with("(automatic replan) bravo became unavailable"),
        "{asks:?}"
    );
    assert_eq!(asks.len(), 4, "{asks:?}");
    assert_eq!((fresh.book, fresh.history), (core.book, core.history));
}

#[test]
fn every_kind_of_input_is_kept_by_the_log() {
    let t0 = Instant::now();
    let gate = gate();
    let snap = super::step_tests::grounded(t0 + Duration::from_millis(1500));
    let alfa = DroneId::new("alfa").expect("valid");
    let checked = gate
        .check(&snap.swarm, "alfa", &Action::ArmTakeoff, snap.now)
        .expect("alfa may take off");
    let take_off = Call::named("T1", "alfa", ActionName::ArmTakeoff, "");
    let inputs = vec![
        Input::Started,
        Input::Pilot("alfa, take off".into()),
        Input::Membership(SwarmChange::Joined(alfa.clone())),
        Input::MembershipMissed,
        Input::Tick,
        Input::Overridden,
        Input::CoordinatorReply {
            instruction: "alfa, take off".into(),
            grounded: vec!["alfa".into()],
            answer: Err(MissionError::NoDroneAvailable),
        },
        Input::EarlyCall {
            call: take_off.clone(),
            checked: checked.clone(),
            after: Duration::from_millis(700),
        },
        Input::CycleReply(Ok(CycleChoice {
            reasoning: "Alfa first.".into(),
            claim: false,
            all_passed: true,
            accepted: vec![(take_off, checked)],
            later: vec!["T2".into()],
        })),
        Input::Sent(Ok(4)),
        Input::Sent(Err(MissionError::Send {
            drone: "alfa".into(),
            action: "land".into(),
            reason: "the link is down".into(),
        })),
        Input::CallDue,
        Input::Coordinate(Coordination::Replan("bravo was lost".into())),
        Input::CallLost {
            layer: "supervisor",
            reason: "panicked".into(),
        },
        Input::Closed,
    ];
    let base = Instant::now() + Duration::from_secs(3600);
    for input in inputs {
        let traced = trace_step(&input, &snap, t0);
        let Record::Step(read) = through_the_log(Record::Step(traced.clone())) else {
            panic!("not a step");
        };
        assert_eq!(read, traced);
        let (again, again_snap) = read.replayed(&gate, base).expect("a step replays");
        // Errors come back in their words; everything else as it was.
        assert_eq!(trace_step(&again, &again_snap, base), traced, "{input:?}");
    }
}

#[test]
fn an_action_the_gate_refuses_on_the_recorded_state_is_not_replayed() {
    let t0 = Instant::now();
    let gate = gate();
    let snap = super::step_tests::grounded(t0);
    let checked = gate
        .check(&snap.swarm, "alfa", &Action::ArmTakeoff, snap.now)
        .expect("alfa may take off");
    let mut traced = trace_step(
        &Input::EarlyCall {
            call: Call::named("T1", "alfa", ActionName::ArmTakeoff, ""),
            checked,
            after: Duration::ZERO,
        },
        &snap,
        t0,
    );
    // The file says the gate saw alfa with no link to its autopilot: the gate refuses.
    if let TracedInput::EarlyCall { checked, .. } = &mut traced.input {
        checked.seen.autopilot_link = false;
    }
    let refused = traced.replayed(&gate, t0).map(|_| ()).unwrap_err();
    assert!(
        matches!(&refused, TraceError::Refused { drone, .. } if drone == "alfa"),
        "{refused}"
    );
    // Times at the ends of their range (a file written by hand, or broken): a time or an
    // error, never a panic.
    for (at_ns, age_ns) in [(u64::MAX, i64::MAX), (0, i64::MAX), (u64::MAX, i64::MIN)] {
        let mut far = trace_step(&Input::Tick, &snap, t0);
        far.snapshot.at_ns = at_ns;
        far.snapshot.drones[0].status_age_ns = Some(age_ns);
        assert!(matches!(
            far.replayed(&gate, t0).map(|_| ()),
            Ok(()) | Err(TraceError::TimeOutOfReach(_))
        ));
    }
}

/// `a_mission`'s log as `--trace-steps` writes it, with the one send it made as `sent` says.
fn traced_log(sent: Record) -> Vec<Line> {
    let t0 = Instant::now();
    let gate = gate();
    let mut core = core(Mode::Tacos);
    let mut lines = vec![Record::TraceBegun {
        core: core.traced(),
    }];
    for (input, snap) in a_mission(t0, &gate) {
        let went = matches!(input, Input::Sent(Ok(_)));
        for (traced, _) in drive(&mut core, input, &snap, &gate, t0) {
            lines.push(Record::Step(traced));
        }
        if went {
            lines.push(sent.clone());
        }
    }
    (lines.into_iter())
        .map(|record| Line { t: 0.0, record })
        .collect()
}

#[test]
fn a_replay_finds_the_sends_the_log_has_and_names_the_first_that_differs() {
    let gate = gate();
    let snap = super::step_tests::grounded(Instant::now());
    let checked = gate
        .check(&snap.swarm, "alfa", &Action::ArmTakeoff, snap.now)
        .expect("alfa may take off");
    let as_sent = Record::action_sent(&checked, Some("T1".into()), 1);
    let log = traced_log(as_sent);
    let replayed = replay(&log, &gate).expect("the log replays");
    assert_eq!(replayed.first_difference(), None, "{replayed:?}");
    assert_eq!(replayed.replayed.len(), 1);
    // Every traced step was fed.
    let traced = (log.iter())
        .filter(|l| matches!(l.record, Record::Step(_)))
        .count();
    assert_eq!(replayed.steps, traced);

    let other_seq = Record::action_sent(&checked, Some("T1".into()), 2);
    let differs = replay(&traced_log(other_seq), &gate).expect("the log replays");
    let difference = differs.first_difference().expect("a difference");
    assert!(
        difference.starts_with("send 1: the replay sent #1 alfa"),
        "{difference}"
    );

    let untraced: Vec<Line> = traced_log(Record::Pilot { text: "hi".into() })
        .into_iter()
        .filter(|l| !matches!(l.record, Record::TraceBegun { .. }))
        .collect();
    assert_eq!(replay(&untraced, &gate), Err(ReplayError::NoTrace));
}

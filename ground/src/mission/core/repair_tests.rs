//! The repair loop (`core::Repair`) without a model: broken replies repaired, a reply cut off,
//! a repair round failing at the backend, the last attempt's refusals, and the two aids that act
//! here (`compact-repair-echo`, `keep-partial-plan`) on and off.

use super::effect::Effect;
use super::repair::{Checked, Next, Repair, distinct_problems, without_repeated_items};
use crate::mission::aids::{Aid, ModelAids};
use crate::mission::log::{Record, RefusedBy};
use crate::mission::report::{MissionError, MissionUpdate};
use tacos_llm::{ChatMessage, LlmError, Role};
use tacos_prompts::CoordinatorReply;

/// A plan's tasks, as the check lets them through.
type Tasks = Vec<String>;

fn plan(calls: &[(&str, &str)]) -> String {
    let calls: Vec<String> = calls
        .iter()
        .map(|(task, drone)| {
            format!(
                r#"{{"task": "{task}", "drone": "{drone}", "action": "arm_takeoff", "target": "none", "xyz": null}}"#
            )
        })
        .collect();
    format!(r#"{{"reasoning": "r", "plan": [{}]}}"#, calls.join(", "))
}

/// Lets calls to alfa, bravo and echo through; charlie's are refused by the checks, delta's by
/// the safety gate; a plan of echo's calls only is in doubt (echo flies already).
fn check(reply: &CoordinatorReply) -> Checked<Tasks> {
    let mut accepted = Vec::new();
    let mut rejections = Vec::new();
    let mut gate_refusals = Vec::new();
    for call in &reply.plan {
        match call.drone.as_str() {
            "charlie" => rejections.push(format!("{} charlie: unavailable", call.task)),
            "delta" => gate_refusals.push(format!("{} delta: battery too low", call.task)),
            _ => accepted.push(call.task.clone()),
        }
    }
    let doubts = if reply.plan.iter().all(|c| c.drone == "echo") {
        vec!["no call of the plan changes anything (echo is flying already)".to_owned()]
    } else {
        Vec::new()
    };
    Checked {
        nothing_passed: accepted.is_empty(),
        accepted,
        rejections,
        gate_refusals,
        narrowed: None,
        doubts,
    }
}

fn told(effects: &[Effect]) -> Vec<String> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Tell(MissionUpdate::Event { text, .. }) => Some(text.clone()),
            _ => None,
        })
        .collect()
}

fn repair(max_repairs: u32, whole: bool, aids: ModelAids) -> Repair<Tasks> {
    let messages = vec![
        ChatMessage::system("plan"),
        ChatMessage::user("all take off"),
    ];
    let schema = serde_json::json!({"type": "object"});
    Repair::new("coordinator", messages, schema, max_repairs, whole, aids)
}

fn reply(r: &mut Repair<Tasks>, content: &str, effects: &mut Vec<Effect>) -> Next<Tasks> {
    r.replied(content, CoordinatorReply::parse, check, effects)
}

fn done(next: Next<Tasks>) -> Result<Tasks, MissionError> {
    match next {
        Next::Done(answer) => answer,
        Next::Ask => panic!("the loop asks again"),
    }
}

fn aids_fired(effects: &[Effect]) -> Vec<Aid> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Note(Record::AidFired { aid, .. }) => Some(*aid),
            _ => None,
        })
        .collect()
}

fn last(r: &Repair<Tasks>) -> &ChatMessage {
    r.messages().last().expect("a message")
}

#[test]
fn a_broken_reply_is_sent_back_with_its_problem_and_the_repaired_one_is_the_answer() {
    let mut r = repair(2, true, ModelAids::none());
    let mut effects = Vec::new();
    assert_eq!(r.attempt(), 1);
    let next = reply(&mut r, "Sure! Alfa takes off.", &mut effects);
    assert!(matches!(next, Next::Ask));
    assert_eq!(r.attempt(), 2);
    // The broken reply echoed, then the problem in the parser's words.
    let n = r.messages().len();
    assert_eq!(r.messages()[n - 2].role, Role::Assistant);
    assert_eq!(r.messages()[n - 2].content, "Sure! Alfa takes off.");
    assert_eq!(last(&r).role, Role::User);
    assert!(
        last(&r).content.contains("the reply is not JSON"),
        "{}",
        last(&r).content
    );
    // A reply of the right JSON but the wrong shape: its problem too.
    assert!(matches!(
        reply(&mut r, r#"{"reasoning": "r"}"#, &mut effects),
        Next::Ask
    ));
    assert!(last(&r).content.contains("required structure"));
    assert!(effects.is_empty(), "{effects:?}");
    let good = plan(&[("T1", "alfa"), ("T2", "bravo")]);
    assert_eq!(
        done(reply(&mut r, &good, &mut effects)),
        Ok(vec!["T1".into(), "T2".into()])
    );
}

#[test]
fn refusals_are_told_by_whom_sent_back_once_each_and_the_last_attempt_decides() {
    // A plan (whole): after the last attempt a reply with refused calls fails, naming them.
    let mut r = repair(1, true, ModelAids::none());
    let mut effects = Vec::new();
    let bad = plan(&[
        ("T1", "alfa"),
        ("T2", "charlie"),
        ("T3", "charlie"),
        ("T4", "delta"),
    ]);
    assert!(matches!(reply(&mut r, &bad, &mut effects), Next::Ask));
    let told: Vec<(String, RefusedBy)> = effects
        .iter()
        .filter_map(|e| match e {
            Effect::Refused { refusal, by, .. } => Some((refusal.clone(), *by)),
            _ => None,
        })
        .collect();
    assert_eq!(
        told,
        [
            ("T2 charlie: unavailable".to_owned(), RefusedBy::Checks),
            ("T3 charlie: unavailable".to_owned(), RefusedBy::Checks),
            (
                "T4 delta: battery too low".to_owned(),
                RefusedBy::SafetyGate
            ),
        ]
    );
    // The repair request names charlie's refusal once.
    let asked = &last(&r).content;
    assert_eq!(asked.matches("charlie: unavailable").count(), 1, "{asked}");
    assert!(asked.contains("T4 delta: battery too low"), "{asked}");
    let err = done(reply(&mut r, &bad, &mut effects)).expect_err("a plan with refused calls");
    let MissionError::NoValidReply {
        attempts, reason, ..
    } = err
    else {
        panic!("{err:?}")
    };
    assert_eq!(attempts, 2);
    assert_eq!(reason, "T2 charlie: unavailable; T4 delta: battery too low");

    // A cycle's reply (not whole): what passed of the last attempt is the answer.
    let mut r = repair(0, false, ModelAids::none());
    assert_eq!(
        done(reply(&mut r, &bad, &mut Vec::new())),
        Ok(vec!["T1".into()])
    );
}

#[test]
fn keep_partial_plan_keeps_what_passed_only_when_on() {
    let bad = plan(&[("T1", "alfa"), ("T2", "charlie")]);
    let on = ModelAids::none().with(Aid::KeepPartialPlan, true);
    let mut effects = Vec::new();
    let mut r = repair(0, true, on);
    assert_eq!(
        done(reply(&mut r, &bad, &mut effects)),
        Ok(vec!["T1".into()])
    );
    assert_eq!(aids_fired(&effects), [Aid::KeepPartialPlan]);

    let mut effects = Vec::new();
    let mut r = repair(0, true, ModelAids::none());
    assert!(done(reply(&mut r, &bad, &mut effects)).is_err());
    assert!(aids_fired(&effects).is_empty());

    // Nothing passed: nothing to keep, even with the aid.
    let mut r = repair(0, true, on);
    let none_passed = plan(&[("T1", "charlie")]);
    assert!(done(reply(&mut r, &none_passed, &mut Vec::new())).is_err());
}

#[test]
fn a_repair_round_failing_at_the_backend_ends_the_call_or_keeps_what_passed_with_the_aid() {
    let bad = plan(&[("T1", "alfa"), ("T2", "charlie")]);
    let window = || LlmError::Generation("the prompt has 4200 tokens; the window is 4096".into());
    for keep in [false, true] {
        let aids = ModelAids::none().with(Aid::KeepPartialPlan, keep);
        let mut r = repair(2, true, aids);
        let mut effects = Vec::new();
        assert!(matches!(reply(&mut r, &bad, &mut effects), Next::Ask));
        let answer = done(r.failed(window(), &mut effects));
        if keep {
            assert_eq!(answer, Ok(vec!["T1".into()]));
            assert_eq!(aids_fired(&effects), [Aid::KeepPartialPlan]);
        } else {
            let Err(MissionError::Llm { layer, error }) = answer else {
                panic!("{answer:?}")
            };
            assert_eq!((layer, error), ("coordinator", window()));
            assert!(aids_fired(&effects).is_empty());
        }
    }
    // A first attempt failing has nothing to keep.
    let mut r = repair(2, true, ModelAids::small());
    let answer = done(r.failed(LlmError::Connect("refused".into()), &mut Vec::new()));
    assert!(
        matches!(answer, Err(MissionError::Llm { .. })),
        "{answer:?}"
    );
}

#[test]
fn a_doubtful_reply_is_sent_back_once_and_passes_when_it_comes_back() {
    let doubtful = plan(&[("T1", "echo")]);
    let mut r = repair(2, true, ModelAids::none());
    let mut effects = Vec::new();
    assert!(matches!(reply(&mut r, &doubtful, &mut effects), Next::Ask));
    assert!(
        last(&r)
            .content
            .starts_with("Check your reply:\n- no call of the plan changes"),
        "{}",
        last(&r).content
    );
    assert!(
        last(&r)
            .content
            .contains("or the same one if it is what the instruction needs")
    );
    assert_eq!(
        told(&effects),
        [
            "coordinator: reply sent back once: no call of the plan changes anything (echo is \
          flying already)"
        ]
    );
    // The same reply again is the answer: "alfa, land" with alfa on the ground is right.
    assert_eq!(
        done(reply(&mut r, &doubtful, &mut effects)),
        Ok(vec!["T1".into()])
    );
    // A better one is taken instead.
    let mut r = repair(2, true, ModelAids::none());
    assert!(matches!(
        reply(&mut r, &doubtful, &mut Vec::new()),
        Next::Ask
    ));
    let better = plan(&[("T1", "alfa")]);
    assert_eq!(
        done(reply(&mut r, &better, &mut Vec::new())),
        Ok(vec!["T1".into()])
    );
    // Without repairs (max_repairs 0) there is no second look.
    let mut r = repair(0, true, ModelAids::none());
    assert_eq!(
        done(reply(&mut r, &doubtful, &mut Vec::new())),
        Ok(vec!["T1".into()])
    );
}

#[test]
fn a_doubted_reply_stands_when_nothing_after_it_passes() {
    let doubtful = plan(&[("T1", "echo")]);
    // The second look fails at the backend: the first reply stands, with or without aids.
    let mut r = repair(2, true, ModelAids::none());
    let mut effects = Vec::new();
    assert!(matches!(reply(&mut r, &doubtful, &mut effects), Next::Ask));
    let window = LlmError::Generation("the prompt has 4200 tokens; the window is 4096".into());
    assert_eq!(done(r.failed(window, &mut effects)), Ok(vec!["T1".into()]));
    assert!(
        told(&effects).contains(&"coordinator: no better reply came: the first one stands".into()),
        "{effects:?}"
    );
    // The replies after it are refused to the last attempt: the first reply stands.
    let mut r = repair(1, true, ModelAids::none());
    assert!(matches!(
        reply(&mut r, &doubtful, &mut Vec::new()),
        Next::Ask
    ));
    let refused = plan(&[("T1", "charlie")]);
    assert_eq!(
        done(reply(&mut r, &refused, &mut Vec::new())),
        Ok(vec!["T1".into()])
    );
}

#[test]
fn a_reply_cut_off_is_asked_again_shorter_until_the_attempts_run_out() {
    let mut r = repair(1, true, ModelAids::none());
    let mut effects = Vec::new();
    assert!(matches!(
        r.failed(LlmError::Truncated(300), &mut effects),
        Next::Ask
    ));
    assert!(last(&r).content.contains("cut off at 300 tokens"));
    let answer = done(r.failed(LlmError::Truncated(300), &mut effects));
    let Err(MissionError::NoValidReply { reason, .. }) = answer else {
        panic!("{answer:?}")
    };
    assert_eq!(reason, "the reply was cut off at 300 tokens");
}

#[test]
fn the_narrowed_schema_holds_the_next_attempt() {
    let mut r = repair(1, true, ModelAids::none());
    let narrowed = serde_json::json!({"type": "object", "required": ["plan"]});
    let given = narrowed.clone();
    let next = r.replied(
        &plan(&[("T1", "charlie")]),
        CoordinatorReply::parse,
        move |reply| Checked {
            narrowed: Some(given),
            ..check(reply)
        },
        &mut Vec::new(),
    );
    assert!(matches!(next, Next::Ask));
    assert_eq!(r.schema(), &narrowed);
}

#[test]
fn compact_repair_echo_leaves_repeats_out_of_the_echo_only_when_on() {
    let looping = plan(&[("T1", "charlie"), ("T2", "charlie"), ("T3", "charlie")]);
    for on in [false, true] {
        let mut r = repair(1, true, ModelAids::none().with(Aid::CompactRepairEcho, on));
        let mut effects = Vec::new();
        assert!(matches!(reply(&mut r, &looping, &mut effects), Next::Ask));
        let echo = &r.messages()[r.messages().len() - 2].content;
        let echoed = echo.matches("charlie").count();
        if on {
            assert_eq!(echoed, 1, "{echo}");
            assert_eq!(aids_fired(&effects), [Aid::CompactRepairEcho]);
        } else {
            assert_eq!(echo, &looping);
            assert!(aids_fired(&effects).is_empty());
        }
    }
}

#[test]
fn a_repair_echo_leaves_out_repeated_items_and_problems_are_said_once() {
    let reply = r#"{"reasoning": "r", "plan": [
        {"task": "T1", "drone": "alfa", "action": "goto", "target": "car_1", "xyz": null},
        {"task": "T2", "drone": "alfa", "action": "arm_takeoff", "target": "none", "xyz": null},
        {"task": "T3", "drone": "alfa", "action": "arm_takeoff", "target": "none", "xyz": null},
        {"task": "T4", "drone": "alfa", "action": "goto", "target": "car_2", "xyz": null}]}"#;
    let echoed: serde_json::Value =
        serde_json::from_str(&without_repeated_items(reply).0).expect("JSON");
    let tasks: Vec<&str> = echoed["plan"]
        .as_array()
        .expect("plan")
        .iter()
        .filter_map(|c| c["task"].as_str())
        .collect();
    assert_eq!(tasks, ["T1", "T2", "T4"]);
    assert_eq!(echoed["reasoning"], "r");
    assert_eq!(without_repeated_items(reply).1, 1);
    assert_eq!(without_repeated_items("Sure!"), ("Sure!".to_owned(), 0));
    let problems = distinct_problems(vec![
        "T2 alfa start_tracking(car_1): car_1 is not a target".into(),
        "T3 alfa start_tracking(car_1): car_1 is not a target".into(),
        "T4 bravo start_tracking(car_1): car_1 is not a target".into(),
        "the plan is empty".into(),
        "the plan is empty".into(),
    ]);
    assert_eq!(
        problems,
        [
            "T2 alfa start_tracking(car_1): car_1 is not a target",
            "T4 bravo start_tracking(car_1): car_1 is not a target",
            "the plan is empty"
        ]
    );
}

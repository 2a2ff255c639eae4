//! The Coordinator's reply checks (`PlanCheck::judge`), each aid on and off, without a model.

use super::plan_check::{PlanCheck, PlanJudgement};
use crate::mission::aids::{Aid, ModelAids};
use crate::mission::grounding::FollowAsked;
use tacos_prompts::schema::{self, Output};
use tacos_prompts::{ActionName, Call, CoordinatorReply};
use tacos_shared::DroneMode;
use tacos_shared::scenario::Scenario;

fn strings(v: &[&str]) -> Vec<String> {
    v.iter().map(|s| (*s).to_owned()).collect()
}

/// The city with alfa, bravo and charlie, charlie unavailable, alfa and bravo on the ground.
fn check(aids: ModelAids) -> PlanCheck {
    let scenario = Scenario::builtin("city").expect("city");
    let places: Vec<String> = scenario.place_names();
    let available = strings(&["alfa", "bravo"]);
    let schema = schema::build(Output::Coordinator, &available, &places, &strings(&["van"]));
    PlanCheck {
        scenario,
        visible: Vec::new(),
        drones: strings(&["alfa", "bravo", "charlie"]),
        available,
        plan_cap: schema::plan_max_calls(&schema),
        schema,
        places,
        scope: None,
        named_places: Vec::new(),
        aids,
        on_the_ground: strings(&["alfa", "bravo"]),
        modes: vec![
            ("alfa".into(), DroneMode::Idle),
            ("bravo".into(), DroneMode::Idle),
        ],
        follow: Vec::new(),
        followed: Vec::new(),
        whole_swarm: false,
    }
}

fn take_off(task: &str, drone: &str) -> Call {
    Call::named(task, drone, ActionName::ArmTakeoff, "none")
}

fn reply(plan: Vec<Call>) -> CoordinatorReply {
    CoordinatorReply {
        reasoning: "r".into(),
        plan,
        refusal: None,
    }
}

fn passed(j: &PlanJudgement) -> Vec<String> {
    j.plan.iter().map(ToString::to_string).collect()
}

#[test]
fn a_call_for_an_unavailable_drone_is_sent_back_naming_the_available_ones() {
    let j = check(ModelAids::small()).judge(&reply(vec![
        take_off("T1", "alfa"),
        take_off("T2", "charlie"),
    ]));
    assert_eq!(passed(&j), ["T1 alfa arm_takeoff()"]);
    assert_eq!(
        j.rejections,
        ["T2 charlie arm_takeoff(): charlie is unavailable; the drones available are: alfa, bravo"]
    );
}

#[test]
fn an_empty_plan_needs_a_refusal_and_a_refusal_may_not_deny_a_place_the_pilot_named() {
    let mut c = check(ModelAids::none());
    let j = c.judge(&reply(Vec::new()));
    assert_eq!(j.rejections.len(), 1);
    assert!(j.rejections[0].starts_with("the plan is empty"), "{j:?}");
    // A refusal is offered: the grammar stays open for one.
    assert_eq!(j.narrowed, None);
    c.named_places = strings(&["car_3"]);
    let mut declined = reply(Vec::new());
    declined.refusal = Some("car_3 is not on this map".into());
    let j = c.judge(&declined);
    assert_eq!(
        j.rejections,
        ["the refusal: car_3 is a place on this map (the pilot named it), and a goto can reach it"]
    );
    declined.refusal = Some("there is no airport here".into());
    let j = c.judge(&declined);
    assert!(j.rejections.is_empty());
    assert_eq!(j.refusal.as_deref(), Some("there is no airport here"));
}

#[test]
fn an_empty_plan_under_plan_only_is_not_told_of_a_refusal_and_a_whole_swarm_one_hears_the_modes() {
    let mut c = check(ModelAids::small());
    c.schema = schema::without_refusal(&c.schema);
    c.modes[1].1 = DroneMode::Flying;
    c.whole_swarm = true;
    let j = c.judge(&reply(Vec::new()));
    assert_eq!(
        j.rejections,
        [
            "the plan is empty: list the calls the instruction needs, for every drone: alfa (idle), \
          bravo (flying)"
        ]
    );
    c.whole_swarm = false;
    let j = c.judge(&reply(Vec::new()));
    assert_eq!(
        j.rejections,
        ["the plan is empty: list the calls the instruction needs"]
    );
    // With no refusal offered, the repair round's grammar needs a call (`repair-grammar`).
    let min = |j: &PlanJudgement| {
        j.narrowed
            .as_ref()?
            .pointer("/properties/plan/minItems")?
            .as_u64()
    };
    assert_eq!(min(&j), Some(1));
    assert!(
        j.aids_fired.iter().any(|(a, _)| *a == Aid::RepairGrammar),
        "{j:?}"
    );
    c.aids = ModelAids::small().with(Aid::RepairGrammar, false);
    assert_eq!(c.judge(&reply(Vec::new())).narrowed, None);
}

#[test]
fn a_place_off_the_instruction_is_sent_back_only_with_a_scope() {
    let mut c = check(ModelAids::small());
    let plan = vec![
        take_off("T1", "alfa"),
        Call::named("T2", "alfa", ActionName::Goto, "car_5"),
    ];
    assert!(c.judge(&reply(plan.clone())).rejections.is_empty());
    c.scope = Some(strings(&["car_3"]));
    let j = c.judge(&reply(plan));
    assert_eq!(passed(&j), ["T1 alfa arm_takeoff()"]);
    assert!(
        j.rejections[0].contains("the places for this plan are: car_3"),
        "{j:?}"
    );
}

#[test]
fn with_the_whole_swarm_aid_a_plan_for_every_drone_must_leave_none_out() {
    let mut c = check(ModelAids::small());
    // alfa and bravo idle (`check`).
    c.whole_swarm = true;
    let j = c.judge(&reply(vec![take_off("T1", "alfa")]));
    let text = "the instruction is for every drone, but the plan gives bravo (idle) no task: add \
                its part";
    assert_eq!(j.rejections, [text]);
    // The repair round's grammar allows only the plan that takes both off.
    assert_eq!(
        j.aids_fired,
        [
            (Aid::WholeSwarm, text.to_owned()),
            (
                Aid::RepairGrammar,
                "the repair round's grammar allows only the plan alfa arm_takeoff, bravo \
                 arm_takeoff"
                    .to_owned()
            ),
        ]
    );
    let narrowed = j.narrowed.expect("a narrowed grammar");
    let plan = &narrowed["properties"]["plan"];
    assert_eq!(plan["maxItems"], 2);
    let drones: Vec<&serde_json::Value> = (0..2)
        .map(|i| &plan["prefixItems"][i]["properties"]["drone"]["enum"][0])
        .collect();
    assert_eq!(
        drones,
        [&serde_json::json!("alfa"), &serde_json::json!("bravo")]
    );
    // A plan of gotos: each drone's place is the model's to choose, so the text only.
    let goto = Call::named("T2", "alfa", ActionName::Goto, "car_3");
    let j = c.judge(&reply(vec![take_off("T1", "alfa"), goto]));
    assert_eq!(j.rejections.len(), 1);
    assert!(j.narrowed.is_none());
    // Without the repair grammar, the text only.
    let mut plain = c.clone();
    plain.aids = ModelAids::small().with(Aid::RepairGrammar, false);
    assert!(
        plain
            .judge(&reply(vec![take_off("T1", "alfa")]))
            .narrowed
            .is_none()
    );
    let j = c.judge(&reply(vec![
        take_off("T1", "alfa"),
        take_off("T2", "bravo"),
    ]));
    assert!(j.rejections.is_empty() && j.aids_fired.is_empty(), "{j:?}");
    // Off (or not the pilot's words for every drone): the plan is taken as written.
    c.whole_swarm = false;
    assert!(
        c.judge(&reply(vec![take_off("T1", "alfa")]))
            .rejections
            .is_empty()
    );
}

#[test]
fn with_implied_takeoffs_off_a_goto_no_take_off_precedes_is_refused_by_name() {
    let plan = vec![Call::named("T1", "alfa", ActionName::Goto, "car_3")];
    // On: the engine adds the take-off when it adopts the plan (`with_implied_takeoffs`).
    let j = check(ModelAids::small()).judge(&reply(plan.clone()));
    assert_eq!(passed(&j), ["T1 alfa goto(car_3)"]);
    let j = check(ModelAids::none()).judge(&reply(plan));
    assert!(j.plan.is_empty());
    assert_eq!(
        j.rejections,
        [
            "T1 alfa goto(car_3): alfa is on the ground and the plan never takes it off: add `alfa \
          arm_takeoff` before it"
        ]
    );
}

#[test]
fn a_target_asked_to_be_followed_must_be_tracked_and_the_repair_grammar_requires_it() {
    let follow = vec![FollowAsked {
        target: "van".into(),
        drone: Some("bravo".into()),
    }];
    let plan = vec![
        take_off("T1", "bravo"),
        Call::named("T2", "bravo", ActionName::Goto, "car_3"),
    ];
    let mut on = check(ModelAids::small());
    on.follow = follow.clone();
    let j = on.judge(&reply(plan.clone()));
    assert_eq!(
        j.rejections,
        [
            "the instruction asks to follow van, but no call of the plan starts tracking it: add \
          start_tracking with target van for bravo"
        ]
    );
    assert!(j.narrowed.is_some());
    assert_eq!(j.aids_fired.len(), 1);
    assert_eq!(j.aids_fired[0].0, Aid::RepairGrammar);
    let mut off = check(ModelAids::small().with(Aid::RepairGrammar, false));
    off.follow = follow;
    let j = off.judge(&reply(plan.clone()));
    assert_eq!(j.rejections.len(), 1);
    assert!(j.narrowed.is_none() && j.aids_fired.is_empty());
    // Followed already: nothing is missing.
    off.followed = strings(&["van"]);
    assert!(off.judge(&reply(plan)).rejections.is_empty());
}

#[test]
fn a_plan_that_fills_its_cap_is_noted_as_the_cap_firing() {
    let c = check(ModelAids::small());
    let full: Vec<Call> = (0..c.plan_cap)
        .map(|i| take_off(&format!("T{i}"), if i % 2 == 0 { "alfa" } else { "bravo" }))
        .collect();
    let j = c.judge(&reply(full.clone()));
    assert_eq!(j.aids_fired.len(), 1, "{j:?}");
    assert_eq!(j.aids_fired[0].0, Aid::PlanLengthCap);
    let off = check(ModelAids::small().with(Aid::PlanLengthCap, false));
    assert!(off.judge(&reply(full)).aids_fired.is_empty());
}

#[test]
fn a_plan_that_changes_nothing_is_in_doubt_with_why() {
    let mut c = check(ModelAids::small());
    c.modes[0].1 = DroneMode::Flying;
    let land = |task, drone| Call::named(task, drone, ActionName::Land, "none");
    // alfa flies already, bravo rests on the ground already.
    let j = c.judge(&reply(vec![take_off("T1", "alfa"), land("T2", "bravo")]));
    assert!(j.rejections.is_empty(), "{:?}", j.rejections);
    assert_eq!(
        j.doubts,
        [
            "no call of the plan changes anything (T1 alfa arm_takeoff(): alfa is flying already; \
          T2 bravo land(): bravo is idle already): plan what the instruction asks for"
        ]
    );
    // One call that changes something clears the doubt, as does an empty plan (refused).
    let j = c.judge(&reply(vec![
        take_off("T1", "alfa"),
        take_off("T2", "bravo"),
    ]));
    assert!(j.doubts.is_empty(), "{:?}", j.doubts);
    assert!(c.judge(&reply(Vec::new())).doubts.is_empty());
}

#[test]
fn a_goto_that_can_never_be_flown_is_sent_back_with_the_gates_reason() {
    let goto = |task: &str, z: f64| Call {
        task: task.into(),
        drone: "bravo".into(),
        action: ActionName::Goto,
        target: schema::NO_TARGET.into(),
        xyz: Some([0.0, -100.0, z]),
    };
    // On the ground (a goto is not a landing), inside a skyscraper, outside the map: refused
    // when the plan is made, not left waiting for a start the gate would refuse for ever.
    let j = check(ModelAids::small()).judge(&reply(vec![take_off("T1", "bravo"), goto("T2", 0.0)]));
    assert_eq!(
        j.rejections,
        ["T2 bravo goto(0.0, -100.0, 0.0): altitude 0.0 m is too low for a goto: use land"]
    );
    let inside = Call {
        xyz: Some([-18.0, -18.0, 10.0]),
        ..goto("T2", 10.0)
    };
    let outside = Call {
        xyz: Some([0.0, 500.0, 10.0]),
        ..goto("T3", 10.0)
    };
    let j = check(ModelAids::small()).judge(&reply(vec![take_off("T1", "bravo"), inside, outside]));
    assert_eq!(j.rejections.len(), 2, "{:?}", j.rejections);
    // Flyable: passes.
    let j =
        check(ModelAids::small()).judge(&reply(vec![take_off("T1", "bravo"), goto("T2", 10.0)]));
    assert!(j.rejections.is_empty(), "{:?}", j.rejections);
}

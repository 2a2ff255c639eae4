//! JSON schemas of the model outputs, built from the files in `prompts/schemas/` with the enums
//! of this mission filled in (the drones and places that exist), so a server with
//! `response_format: json_schema` or a grammar-constrained model cannot name anything else.
//! A call is one of four shapes (`call.schema.json`): an action without argument, whose target
//! is "none" and xyz null; a goto to a place (xyz null); a goto to a point (target "none"); a
//! start_tracking (a target). Before that split the embedded model filled a take-off's unused
//! target with a landmark, and went on to plan gotos to it that nobody asked for; and while a
//! goto's place and point were one shape, the 1.5B default wrote fifteen gotos to "none" with
//! no point (Task 1), which only the checks after the reply could refuse.

use serde_json::Value;

const CALL: &str = include_str!("../schemas/call.schema.json");
const COORDINATOR: &str = include_str!("../schemas/coordinator.schema.json");
const SUPERVISOR: &str = include_str!("../schemas/supervisor.schema.json");
const MONOLITHIC: &str = include_str!("../schemas/monolithic.schema.json");

/// "none" stands for "no target" in the `target` field.
pub const NO_TARGET: &str = "none";

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Output {
    Coordinator,
    Supervisor,
    Monolithic,
}

impl Output {
    pub fn name(self) -> &'static str {
        match self {
            Output::Coordinator => "coordinator_plan",
            Output::Supervisor => "supervisor_cycle",
            Output::Monolithic => "monolithic_cycle",
        }
    }
}

fn parse(text: &str) -> Value {
    serde_json::from_str::<Value>(text).unwrap_or(Value::Null)
}

/// The call shapes of `call.schema.json` with the names filled in; a shape whose target list
/// comes out empty (no place, nothing trackable) is left out, as no call could take it.
fn shapes(names: &Names) -> Vec<Value> {
    let mut call = parse(CALL);
    fill(&mut call, names, &Value::Null);
    let Value::Object(mut call) = call else {
        return Vec::new();
    };
    let Some(Value::Array(mut shapes)) = call.remove("anyOf") else {
        return Vec::new();
    };
    shapes.retain(|v| {
        v.pointer("/properties/target/enum")
            .and_then(Value::as_array)
            .is_none_or(|e| !e.is_empty())
    });
    shapes
}

/// The call shapes (`call.schema.json`) for a mission with these places and trackable targets
/// (any drone): what [`crate::offer`] narrows to one task and one drone.
pub(crate) fn call_shapes(places: &[String], trackable: &[String]) -> Vec<Value> {
    shapes(&Names {
        drones: &[],
        places,
        trackable,
    })
}

/// True when call shape `shape` (see [`call_shapes`]) is one that `action` takes.
pub(crate) fn shape_takes(shape: &Value, action: &Value) -> bool {
    shape
        .pointer("/properties/action/enum")
        .and_then(Value::as_array)
        .is_some_and(|actions| actions.contains(action))
}

/// The names that fill a schema's placeholders.
struct Names<'a> {
    drones: &'a [String],
    /// What a goto may name (`$PLACES`): landmarks and targets.
    places: &'a [String],
    trackable: &'a [String],
}

fn fill(value: &mut Value, names: &Names, call: &Value) {
    let (drones, places) = (names.drones, names.places);
    match value {
        Value::Array(items) if items.len() == 1 && items[0] == "$DRONES" => {
            *items = drones.iter().map(|d| Value::String(d.clone())).collect();
        }
        Value::Array(items) if items.len() == 1 && items[0] == "$PLACES" => {
            *items = places.iter().cloned().map(Value::String).collect();
        }
        Value::Array(items) if items.len() == 1 && items[0] == "$TRACKABLE" => {
            *items = names.trackable.iter().cloned().map(Value::String).collect();
        }
        Value::String(s) if s == "$CALL" => *value = call.clone(),
        Value::Array(items) => items.iter_mut().for_each(|v| fill(v, names, call)),
        Value::Object(map) => map.values_mut().for_each(|v| fill(v, names, call)),
        _ => {}
    }
}

/// The schema of `output` for a mission with these drone ids, places (landmark and target
/// names: what a goto may name) and trackable targets (what a start_tracking may name: tracking a landmark is
/// refused anyway, and the 135M model, made to track the van, went on to "track" car_1 17
/// times). With nothing trackable, a call cannot be a start_tracking.
pub fn build(output: Output, drones: &[String], places: &[String], trackable: &[String]) -> Value {
    let names = Names {
        drones,
        places,
        trackable,
    };
    let call = serde_json::json!({ "anyOf": shapes(&names) });
    let mut schema = parse(match output {
        Output::Coordinator => COORDINATOR,
        Output::Supervisor => SUPERVISOR,
        Output::Monolithic => MONOLITHIC,
    });
    fill(&mut schema, &names, &call);
    // Bound the lists by the swarm: a small model left unbounded can list calls until it runs out
    // of tokens. A plan gets up to three calls per drone, a cycle one per drone.
    let n = drones.len().max(1);
    if let Some(plan) = schema.pointer_mut("/properties/plan") {
        plan["maxItems"] = Value::from((3 * n).clamp(3, PLAN_MAX_CALLS));
    }
    if let Some(actions) = schema.pointer_mut("/properties/actions") {
        actions["maxItems"] = Value::from(n.min(20));
    }
    schema
}

/// The most calls a plan may hold, whatever the swarm's size: the list must stay bounded for the
/// reply's token budget.
pub const PLAN_MAX_CALLS: usize = 40;

/// The bound on a Coordinator plan's length in `schema` (0 when it has none).
pub fn plan_max_calls(schema: &Value) -> usize {
    schema
        .pointer("/properties/plan/maxItems")
        .and_then(Value::as_u64)
        .map_or(0, |n| n as usize)
}

/// The Coordinator schema `schema` with its plan bounded by [`PLAN_MAX_CALLS`] only, not by three
/// calls per drone (the small-model aid `plan-length-cap` off).
pub fn without_plan_cap(schema: &Value) -> Value {
    let mut out = schema.clone();
    if let Some(plan) = out.pointer_mut("/properties/plan") {
        plan["maxItems"] = Value::from(PLAN_MAX_CALLS);
    }
    out
}

/// The Coordinator schema `schema` without its optional "refusal" (the `plan-only` aid).
pub fn without_refusal(schema: &Value) -> Value {
    let mut out = schema.clone();
    if let Some(properties) = out.get_mut("properties").and_then(Value::as_object_mut) {
        properties.remove("refusal");
    }
    out
}

/// A call that a Coordinator plan must contain: `action` on `target`, by one of `drones`.
#[derive(Debug, Clone, PartialEq)]
pub struct RequiredCall {
    pub drones: Vec<String>,
    pub action: &'static str,
    pub target: String,
}

/// The Coordinator schema `schema` with its plan opening on `required` (`prefixItems`), the
/// rest of the plan as before. For a repair round, when a reply missed a call the instruction
/// asks for in so many words: the 135M model, told "add start_tracking with target van",
/// answered with the same gotos twice; under this grammar it can only open with the call and
/// choose its drone. Used only after a miss, so a server that has trouble with `prefixItems`
/// meets it only when its first answer was wrong already.
pub fn requiring(schema: &Value, required: &[RequiredCall]) -> Value {
    let mut out = schema.clone();
    let Some(plan) = out.pointer_mut("/properties/plan") else {
        return out;
    };
    let prefix: Vec<Value> = required
        .iter()
        .map(|r| {
            serde_json::json!({
                "type": "object",
                "properties": {
                    "task": { "type": "string", "pattern": "^[TA][0-9]{1,3}$" },
                    "drone": { "type": "string", "enum": r.drones },
                    "action": { "type": "string", "enum": [r.action] },
                    "target": { "type": "string", "enum": [r.target] },
                    "xyz": { "type": "null" }
                },
                "required": ["task", "drone", "action", "target", "xyz"],
                "additionalProperties": false
            })
        })
        .collect();
    let n = prefix.len();
    plan["prefixItems"] = Value::Array(prefix);
    let max = plan["maxItems"].as_u64().unwrap_or(0).max(n as u64);
    plan["maxItems"] = Value::from(max);
    plan["minItems"] = Value::from(n);
    out
}

/// The Coordinator schema `schema` with a plan of at least one call. For a repair round after an
/// empty plan where no refusal is offered: the 1.5B default, asked for "all drones take off"
/// with six drones on the ground, answered "All drones are already idle, so no action is
/// needed" with an empty plan, three times in a row, when told the plan was empty.
pub fn non_empty(schema: &Value) -> Value {
    let mut out = schema.clone();
    if let Some(plan) = out.pointer_mut("/properties/plan") {
        let min = plan["minItems"].as_u64().unwrap_or(0).max(1);
        plan["minItems"] = Value::from(min);
    }
    out
}

/// The Coordinator schema `schema` with its plan exactly `calls`, in order: a tuple
/// (`prefixItems` without `items`, `minItems` = `maxItems`). The form llama.cpp's server and
/// llguidance agree on: llama.cpp's grammar converter reads `items` when a schema has both and
/// ignores `prefixItems` then, so [`requiring`]'s open-ended prefix holds only on llguidance.
pub fn exactly(schema: &Value, calls: &[RequiredCall]) -> Value {
    let mut out = requiring(schema, calls);
    if let Some(plan) = out
        .pointer_mut("/properties/plan")
        .and_then(Value::as_object_mut)
    {
        plan.remove("items");
        plan.insert("maxItems".into(), Value::from(calls.len()));
    }
    out
}

/// The most tokens a reply can take under [`build`]'s bounds for `drones` drones: its reasoning
/// at full length (a token is at least one character) and its list full, each call at its
/// longest (a point in "xyz", about 40 tokens). A smaller limit cuts off a well-formed reply of
/// a long plan, as the embedded model's 6-drone take-off plans were at 600.
pub fn token_budget(output: Output, drones: usize) -> u32 {
    let n = drones.max(1) as u32;
    let (reasoning, items) = match output {
        // Its reasoning and an optional refusal (200 characters).
        Output::Coordinator => (300 + 200, (3 * n).clamp(3, PLAN_MAX_CALLS as u32)),
        Output::Supervisor => (200, n.min(20)),
        Output::Monolithic => (400, n.min(20)),
    };
    reasoning + 40 + 40 * items
}

/// The most tokens a Coordinator reply can take with a plan of up to `calls` calls.
pub fn coordinator_token_budget(calls: usize) -> u32 {
    300 + 200 + 40 + 40 * calls as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_required_call_opens_the_plan() {
        let s = build(
            Output::Coordinator,
            &["alfa".into(), "bravo".into()],
            &["car_1".into(), "van".into()],
            &["van".into()],
        );
        let required = RequiredCall {
            drones: vec!["bravo".into()],
            action: "start_tracking",
            target: "van".into(),
        };
        let r = requiring(&s, std::slice::from_ref(&required));
        let plan = &r["properties"]["plan"];
        assert_eq!(plan["minItems"], 1);
        assert_eq!(plan["maxItems"], s["properties"]["plan"]["maxItems"]);
        let first = &plan["prefixItems"][0]["properties"];
        assert_eq!(first["drone"]["enum"], serde_json::json!(["bravo"]));
        assert_eq!(
            first["action"]["enum"],
            serde_json::json!(["start_tracking"])
        );
        assert_eq!(first["target"]["enum"], serde_json::json!(["van"]));
        // The rest of the plan is as before.
        assert_eq!(plan["items"], s["properties"]["plan"]["items"]);
        // `exactly`: that call and nothing else, in the tuple form every server reads.
        let e = exactly(&s, std::slice::from_ref(&required));
        let plan = &e["properties"]["plan"];
        assert_eq!(plan["prefixItems"], r["properties"]["plan"]["prefixItems"]);
        assert!(plan.get("items").is_none());
        assert_eq!(
            (plan["minItems"].as_u64(), plan["maxItems"].as_u64()),
            (Some(1), Some(1))
        );
    }

    #[test]
    fn schema_files_are_valid_json() {
        for text in [CALL, COORDINATOR, SUPERVISOR, MONOLITHIC] {
            serde_json::from_str::<Value>(text).expect("schema file parses");
        }
    }

    #[test]
    fn enums_are_filled_with_the_mission() {
        let s = build(
            Output::Coordinator,
            &["alfa".into(), "bravo".into()],
            &["car_1".into(), "van".into()],
            &["van".into()],
        );
        let variants = s["properties"]["plan"]["items"]["anyOf"]
            .as_array()
            .expect("a call is one of its variants");
        assert_eq!(variants.len(), 4);
        for call in variants {
            assert_eq!(
                call["properties"]["drone"]["enum"],
                serde_json::json!(["alfa", "bravo"])
            );
        }
        let variant = |action: &str| {
            variants
                .iter()
                .find(|v| {
                    v["properties"]["action"]["enum"]
                        .as_array()
                        .is_some_and(|a| a.contains(&action.into()))
                })
                .unwrap_or_else(|| panic!("no variant for {action}"))
        };
        // Only goto and start_tracking take a target, only a trackable one for tracking; only
        // goto a point, and then with no place.
        let gotos: Vec<&Value> = variants
            .iter()
            .filter(|v| v["properties"]["action"]["enum"] == serde_json::json!(["goto"]))
            .collect();
        assert_eq!(
            gotos
                .iter()
                .map(|v| (
                    &v["properties"]["target"]["enum"],
                    &v["properties"]["xyz"]["type"]
                ))
                .collect::<Vec<_>>(),
            [
                (
                    &serde_json::json!(["car_1", "van"]),
                    &serde_json::json!("null")
                ),
                (&serde_json::json!(["none"]), &serde_json::json!("array")),
            ]
        );
        assert_eq!(
            variant("start_tracking")["properties"]["target"]["enum"],
            serde_json::json!(["van"])
        );
        for action in ["arm_takeoff", "land", "hold", "stop_tracking"] {
            assert_eq!(
                variant(action)["properties"]["target"]["enum"],
                serde_json::json!(["none"])
            );
            assert_eq!(variant(action)["properties"]["xyz"]["type"], "null");
        }
        assert_eq!(
            variant("start_tracking")["properties"]["xyz"]["type"],
            "null"
        );
        for placeholder in ["$DRONES", "$PLACES", "$TRACKABLE", "$CALL"] {
            assert!(
                !s.to_string().contains(placeholder),
                "{placeholder} was left: {s}"
            );
        }
        assert_eq!(s["properties"]["plan"]["maxItems"], 6);
        assert_eq!(
            token_budget(Output::Coordinator, 2),
            300 + 200 + 40 + 40 * 6
        );
        assert_eq!(s["properties"]["refusal"]["maxLength"], 200);
        let plan_only = without_refusal(&s);
        assert!(plan_only["properties"].get("refusal").is_none());
        assert_eq!(plan_only["properties"]["plan"], s["properties"]["plan"]);
        // Nothing to track: no call can be a start_tracking.
        let s = build(
            Output::Coordinator,
            &["alfa".into()],
            &["car_1".into()],
            &[],
        );
        let variants = s["properties"]["plan"]["items"]["anyOf"]
            .as_array()
            .expect("a call is one of its variants");
        assert_eq!(variants.len(), 3);
        assert!(!s.to_string().contains("start_tracking"));
        // No place to go to: a goto is a point.
        let s = build(Output::Coordinator, &["alfa".into()], &[], &[]);
        let variants = s["properties"]["plan"]["items"]["anyOf"]
            .as_array()
            .expect("a call is one of its variants");
        assert_eq!(variants.len(), 2);
        assert_eq!(
            variants[1]["properties"]["target"]["enum"],
            serde_json::json!(["none"])
        );
        assert_eq!(variants[1]["properties"]["xyz"]["type"], "array");
        let s = build(Output::Supervisor, &["alfa".into()], &[], &[]);
        assert_eq!(s["properties"]["actions"]["maxItems"], 1);
        assert_eq!(
            s["properties"]["actions"]["items"]["anyOf"][0]["properties"]["drone"]["enum"],
            serde_json::json!(["alfa"])
        );
    }
}

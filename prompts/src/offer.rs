//! Schemas that offer a model only the calls valid now: the Supervisor's startable calls, and
//! each drone's allowed actions for the monolithic model. A constrained model cannot name
//! anything else; it still chooses which, and may choose none.

use crate::schema::{self, Output};
use crate::{ActionName, Call};

/// One drone the monolithic model may give an action to now, under a fresh task id.
pub struct Callable {
    pub task: String,
    pub drone: String,
    pub actions: Vec<ActionName>,
}

/// The monolithic model's output schema for this cycle: each call is one of the calls that are
/// valid now (a ready drone under its fresh task id, an action its mode allows, and an
/// argument of the right kind: no target for take-off, landing, hold and stop-tracking; a place
/// or a point for goto; a target for tracking). The model still chooses which, and may choose
/// none.
pub fn callable_schema(
    callable: &[Callable],
    drones: &[String],
    places: &[String],
    trackable: &[String],
) -> serde_json::Value {
    use serde_json::json;
    let mut schema = schema::build(Output::Monolithic, drones, places, trackable);
    // Each of the drone's actions in every shape `call.schema.json` gives it (a goto: to a place
    // or to a point), narrowed to this drone under its fresh task id.
    let shapes = schema::call_shapes(places, trackable);
    let mut alternatives = Vec::new();
    for c in callable {
        for &action in &c.actions {
            let name = serde_json::to_value(action).unwrap_or_default();
            for shape in shapes.iter().filter(|s| schema::shape_takes(s, &name)) {
                let mut shape = shape.clone();
                shape["properties"]["task"] = json!({ "type": "string", "enum": [c.task] });
                shape["properties"]["drone"] = json!({ "type": "string", "enum": [c.drone] });
                shape["properties"]["action"] = json!({ "type": "string", "enum": [name] });
                alternatives.push(shape);
            }
        }
    }
    if let Some(items) = schema.pointer_mut("/properties/actions/items") {
        *items = json!({ "anyOf": alternatives });
    }
    if let Some(actions) = schema.pointer_mut("/properties/actions") {
        actions["maxItems"] = serde_json::Value::from(callable.len().max(1));
    }
    schema
}

/// The Supervisor's output schema for this cycle: its calls can only name tasks, drones,
/// actions and targets of the calls that could start now, so a constrained model cannot pick
/// anything else (it still chooses which, and may choose none).
/// The reply must start at least one call: a startable call waits for nothing (its drone is
/// free, the tasks before it are done), so an empty choice is a lost cycle. With nothing
/// running it would wait for a change that cannot come; with tasks running, for their outcome
/// (the 1.5B model answered "All drones are already flying" with three of six flying and three
/// take-offs startable, and those three waited a whole take-off).
pub fn startable_schema(startable: &[Call]) -> serde_json::Value {
    let mut drones: Vec<String> = startable.iter().map(|c| c.drone.clone()).collect();
    drones.sort();
    drones.dedup();
    let places: Vec<String> = startable
        .iter()
        .filter_map(|c| c.target_name().map(str::to_owned))
        .collect();
    let mut schema = schema::build(Output::Supervisor, &drones, &places, &[]);
    // Each call is exactly one of the startable calls: task, drone, action and target come as a
    // unit, so a constrained model cannot give one task's id to another drone.
    let alternatives: Vec<serde_json::Value> = startable
        .iter()
        .map(|c| {
            let action = serde_json::to_value(c.action).unwrap_or_default();
            serde_json::json!({
                "type": "object",
                "properties": {
                    "task": { "type": "string", "enum": [c.task] },
                    "drone": { "type": "string", "enum": [c.drone] },
                    "action": { "type": "string", "enum": [action] },
                    "target": { "type": "string", "enum": [c.target] },
                    "xyz": { "type": "null" }
                },
                "required": ["task", "drone", "action", "target", "xyz"],
                "additionalProperties": false
            })
        })
        .collect();
    if let Some(items) = schema.pointer_mut("/properties/actions/items") {
        *items = serde_json::json!({ "anyOf": alternatives });
    }
    if let Some(actions) = schema.pointer_mut("/properties/actions") {
        actions["maxItems"] = serde_json::Value::from(drones.len().max(1));
        if !startable.is_empty() {
            actions["minItems"] = serde_json::Value::from(1);
        }
    }
    schema
}

#[cfg(test)]
mod tests {
    use super::*;

    fn alternatives(
        schema: &serde_json::Value,
    ) -> Vec<(String, String, String, serde_json::Value)> {
        schema
            .pointer("/properties/actions/items/anyOf")
            .and_then(|a| a.as_array())
            .into_iter()
            .flatten()
            .map(|alt| {
                let one = |f: &str| {
                    alt["properties"][f]["enum"][0]
                        .as_str()
                        .unwrap_or("")
                        .to_owned()
                };
                (
                    one("task"),
                    one("drone"),
                    one("action"),
                    alt["properties"]["target"]["enum"].clone(),
                )
            })
            .collect()
    }

    #[test]
    fn the_monolithic_schema_offers_only_the_calls_valid_now() {
        let callable = [
            Callable {
                task: "A4".into(),
                drone: "alfa".into(),
                actions: vec![ActionName::ArmTakeoff],
            },
            Callable {
                task: "A5".into(),
                drone: "bravo".into(),
                actions: vec![
                    ActionName::Goto,
                    ActionName::StartTracking,
                    ActionName::Land,
                ],
            },
        ];
        let drones = ["alfa".to_owned(), "bravo".to_owned(), "charlie".to_owned()];
        let places = ["car_1".to_owned(), "villa_2".to_owned()];
        let schema = callable_schema(&callable, &drones, &places, &["suspect".to_owned()]);
        let alts = alternatives(&schema);
        let none = serde_json::json!(["none"]);
        assert_eq!(
            alts,
            vec![
                (
                    "A4".into(),
                    "alfa".into(),
                    "arm_takeoff".into(),
                    none.clone()
                ),
                (
                    "A5".into(),
                    "bravo".into(),
                    "goto".into(),
                    serde_json::json!(places)
                ),
                ("A5".into(), "bravo".into(), "goto".into(), none.clone()),
                (
                    "A5".into(),
                    "bravo".into(),
                    "start_tracking".into(),
                    serde_json::json!(["suspect"])
                ),
                ("A5".into(), "bravo".into(), "land".into(), none),
            ]
        );
        // Only the goto without a place takes a point.
        let items = &schema["properties"]["actions"]["items"]["anyOf"];
        assert_eq!(items[2]["properties"]["xyz"]["type"], "array");
        assert_eq!(items[1]["properties"]["xyz"]["type"], "null");
        assert_eq!(schema["properties"]["actions"]["maxItems"], 2);
        assert_eq!(
            schema["required"],
            serde_json::json!(["reasoning", "actions", "done"])
        );
    }

    #[test]
    fn a_cycle_with_a_startable_call_must_start_something() {
        let startable = vec![Call {
            task: "T1".into(),
            drone: "alfa".into(),
            action: ActionName::ArmTakeoff,
            target: "none".into(),
            xyz: None,
        }];
        let schema = startable_schema(&startable);
        assert_eq!(
            schema.pointer("/properties/actions/minItems"),
            Some(&serde_json::json!(1))
        );
        assert_eq!(
            schema.pointer("/properties/actions/maxItems"),
            Some(&serde_json::json!(1))
        );
        // Nothing startable: no call can be required.
        assert!(
            startable_schema(&[])
                .pointer("/properties/actions/minItems")
                .is_none()
        );
    }
}

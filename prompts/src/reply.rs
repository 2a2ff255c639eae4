//! Model replies as types, and their parsing. Parsing checks the shape only; whether a call may
//! fly is the safety gate's business (in `tacos-ground`).

use serde::{Deserialize, Serialize};
use std::fmt;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActionName {
    ArmTakeoff,
    Goto,
    StartTracking,
    StopTracking,
    Land,
    Hold,
}

impl ActionName {
    /// Every action, in the API's order.
    pub const ALL: [ActionName; 6] = [
        ActionName::ArmTakeoff,
        ActionName::Goto,
        ActionName::StartTracking,
        ActionName::StopTracking,
        ActionName::Land,
        ActionName::Hold,
    ];

    /// The name models write (the schema's and serde's).
    pub fn as_str(self) -> &'static str {
        match self {
            ActionName::ArmTakeoff => "arm_takeoff",
            ActionName::Goto => "goto",
            ActionName::StartTracking => "start_tracking",
            ActionName::StopTracking => "stop_tracking",
            ActionName::Land => "land",
            ActionName::Hold => "hold",
        }
    }

    /// True for the actions that take no target (take-off, landing, hold, stop-tracking).
    pub fn takes_no_target(self) -> bool {
        !matches!(self, ActionName::Goto | ActionName::StartTracking)
    }
}

/// One atomic API call: a task id, a drone, an action and its argument.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Call {
    pub task: String,
    pub drone: String,
    pub action: ActionName,
    /// A landmark or target name, or "none".
    pub target: String,
    /// A point for goto, metres in the world frame.
    pub xyz: Option<[f64; 3]>,
}

impl Call {
    /// A call whose argument is a name, or "none" for an action without one (no point).
    pub fn named(task: &str, drone: &str, action: ActionName, target: &str) -> Call {
        Call {
            task: task.into(),
            drone: drone.into(),
            action,
            target: target.into(),
            xyz: None,
        }
    }

    /// The target, unless it is "none" or empty.
    pub fn target_name(&self) -> Option<&str> {
        let t = self.target.trim();
        (!t.is_empty() && t != crate::schema::NO_TARGET).then_some(t)
    }
}

impl fmt::Display for Call {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let action = self.action.as_str();
        // Only the argument the action takes: models fill "target" and "xyz" of a take-off or a
        // landing with filler, which is ignored and must not read as part of the call.
        let arg = match (self.action, self.target_name(), self.xyz) {
            (ActionName::Goto | ActionName::StartTracking, Some(t), _) => t.to_owned(),
            (ActionName::Goto, None, Some([x, y, z])) => format!("{x:.1}, {y:.1}, {z:.1}"),
            _ => String::new(),
        };
        write!(f, "{} {} {action}({arg})", self.task, self.drone)
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CoordinatorReply {
    pub reasoning: String,
    pub plan: Vec<Call>,
    /// Said to the pilot when the instruction cannot be carried out (a place or drone that does
    /// not exist, a goal inside an obstacle): why, and what would work. Optional in the schema.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refusal: Option<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SupervisorReply {
    pub reasoning: String,
    pub actions: Vec<Call>,
    pub plan_complete: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonolithicReply {
    pub reasoning: String,
    pub actions: Vec<Call>,
    pub done: bool,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReplyError {
    #[error("the reply is not JSON: {0}")]
    NotJson(String),
    #[error("the reply does not have the required structure: {0}")]
    Shape(String),
}

fn parse<T: for<'de> Deserialize<'de>>(text: &str) -> Result<T, ReplyError> {
    // Models wrap JSON in code fences now and then; accept exactly that and nothing looser.
    let trimmed = text.trim();
    let body = trimmed
        .strip_prefix("```json")
        .or_else(|| trimmed.strip_prefix("```"))
        .and_then(|rest| rest.strip_suffix("```"))
        .unwrap_or(trimmed);
    let value: serde_json::Value =
        serde_json::from_str(body).map_err(|e| ReplyError::NotJson(e.to_string()))?;
    serde_json::from_value(value).map_err(|e| ReplyError::Shape(e.to_string()))
}

impl CoordinatorReply {
    pub fn parse(text: &str) -> Result<Self, ReplyError> {
        parse(text)
    }

    /// The refusal, unless it is absent or blank.
    pub fn refusal_text(&self) -> Option<&str> {
        self.refusal
            .as_deref()
            .map(str::trim)
            .filter(|r| !r.is_empty())
    }
}

impl SupervisorReply {
    pub fn parse(text: &str) -> Result<Self, ReplyError> {
        parse(text)
    }
}

impl MonolithicReply {
    pub fn parse(text: &str) -> Result<Self, ReplyError> {
        parse(text)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_good_replies_and_rejects_broken_ones() {
        let good = r#"{"reasoning":"r","plan":[{"task":"T1","drone":"alfa","action":"goto","target":"car_7","xyz":null}]}"#;
        let reply = CoordinatorReply::parse(good).expect("valid");
        assert_eq!(reply.plan[0].target_name(), Some("car_7"));
        assert_eq!(reply.plan[0].to_string(), "T1 alfa goto(car_7)");
        let takeoff = Call {
            action: ActionName::ArmTakeoff,
            xyz: Some([1.0, 2.0, 3.0]),
            ..reply.plan[0].clone()
        };
        assert_eq!(takeoff.to_string(), "T1 alfa arm_takeoff()");
        for name in ActionName::ALL {
            let serde_name = serde_json::to_value(name).expect("serialises");
            assert_eq!(serde_name.as_str(), Some(name.as_str()));
        }
        assert!(CoordinatorReply::parse(&format!("```json\n{good}\n```")).is_ok());
        assert!(matches!(
            CoordinatorReply::parse("take off!"),
            Err(ReplyError::NotJson(_))
        ));
        assert!(matches!(
            CoordinatorReply::parse(&good[..good.len() - 3]),
            Err(ReplyError::NotJson(_))
        ));
        assert!(matches!(
            CoordinatorReply::parse(r#"{"reasoning":"r"}"#),
            Err(ReplyError::Shape(_))
        ));
        let unknown_action = good.replace("goto", "teleport");
        assert!(matches!(
            CoordinatorReply::parse(&unknown_action),
            Err(ReplyError::Shape(_))
        ));
        assert_eq!(reply.refusal_text(), None);
        let refused = CoordinatorReply::parse(
            r#"{"reasoning":"r","plan":[],"refusal":" There is no airport. "}"#,
        )
        .expect("a refusal is a reply");
        assert_eq!(refused.refusal_text(), Some("There is no airport."));
        let blank = CoordinatorReply::parse(r#"{"reasoning":"r","plan":[],"refusal":"  "}"#);
        assert_eq!(blank.map(|r| r.refusal_text().is_none()), Ok(true));
        let extra = good.replace(r#""reasoning":"r""#, r#""reasoning":"r","mood":"happy""#);
        assert!(matches!(
            CoordinatorReply::parse(&extra),
            Err(ReplyError::Shape(_))
        ));
    }
}

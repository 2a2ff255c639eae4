//! The pilot's approval of a Coordinator plan (`--confirm`): a plan is held, shown call by call,
//! and flies only once approved. The pilot approves it, drops calls from it, or rejects it with
//! a sentence that goes back to the Coordinator. Pure: the engine holds the plan and acts.

use tacos_prompts::reply::Call;

/// What the pilot said about the plan held for approval.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    Approve,
    /// The task ids to drop (as the plan names them, e.g. `T2`).
    Drop(Vec<String>),
    /// Why, in the pilot's words (may be empty).
    Reject(String),
}

/// Reads a pilot line as a verdict on a held plan; anything else is a new instruction.
pub fn parse(text: &str) -> Option<Verdict> {
    let lower = text.trim().to_lowercase();
    let lower = lower.trim_end_matches(['.', '!']);
    let (first, rest) = match lower.split_once(char::is_whitespace) {
        Some((first, rest)) => (first, rest.trim()),
        None => (lower, ""),
    };
    match (first.trim_end_matches([',', ':']), rest) {
        ("approve" | "approved" | "yes" | "ok" | "go", "") => Some(Verdict::Approve),
        ("drop", tasks) if !tasks.is_empty() => {
            let ids: Vec<String> = tasks
                .split(|c: char| c == ',' || c.is_whitespace())
                .filter(|w| !w.is_empty() && *w != "and")
                .map(str::to_uppercase)
                .collect();
            (!ids.is_empty()).then_some(Verdict::Drop(ids))
        }
        ("reject" | "rejected" | "no", _) => {
            // The pilot's own words after the first, not lower-cased.
            let original = text.trim();
            let why = original
                .split_once(char::is_whitespace)
                .map_or("", |(_, rest)| rest)
                .trim()
                .trim_end_matches(['.', '!'])
                .to_owned();
            Some(Verdict::Reject(why))
        }
        _ => None,
    }
}

/// `confirm on` / `confirm off`: the pilot's switch for holding plans, if `text` is one.
pub fn switch(text: &str) -> Option<bool> {
    match text.trim().to_lowercase().trim_end_matches(['.', '!']) {
        "confirm on" => Some(true),
        "confirm off" => Some(false),
        _ => None,
    }
}

/// A Coordinator plan held for the pilot.
#[derive(Debug, Clone, PartialEq)]
pub struct HeldPlan {
    pub instruction: String,
    pub reasoning: String,
    pub calls: Vec<Call>,
}

impl HeldPlan {
    /// Drops the calls with the given task ids; an id the plan lacks is an error naming the
    /// plan's ids, and nothing is dropped.
    pub fn drop_tasks(&mut self, ids: &[String]) -> Result<(), String> {
        let unknown: Vec<&str> = ids
            .iter()
            .filter(|id| !self.calls.iter().any(|c| &c.task == *id))
            .map(String::as_str)
            .collect();
        if !unknown.is_empty() {
            let known: Vec<&str> = self.calls.iter().map(|c| c.task.as_str()).collect();
            return Err(format!(
                "the plan has no task {} (its tasks: {})",
                unknown.join(", "),
                known.join(", ")
            ));
        }
        self.calls.retain(|c| !ids.contains(&c.task));
        Ok(())
    }

    /// The plan as the pilot reads it: each call with what the checks and the gate say of it
    /// now (`verdicts`, one per call: `None` when it could start at once), then what to answer.
    pub fn describe(&self, verdicts: &[Option<String>]) -> String {
        let mut lines = vec![format!(
            "plan for {:?} awaits your approval:",
            self.instruction
        )];
        for (call, verdict) in self.calls.iter().zip(verdicts) {
            lines.push(match verdict {
                None => format!("  {call}: could start now"),
                Some(why) => format!("  {call}: not now ({why})"),
            });
        }
        lines.push(
            "answer `approve`, `drop <task> …`, or `reject <why>` (anything else is a new instruction)"
                .into(),
        );
        lines.join("\n")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn call(task: &str, drone: &str) -> Call {
        Call {
            task: task.into(),
            drone: drone.into(),
            action: tacos_prompts::reply::ActionName::Goto,
            target: "car_11".into(),
            xyz: None,
        }
    }

    #[test]
    fn reads_the_pilot_s_verdicts_and_nothing_else() {
        assert_eq!(parse("approve"), Some(Verdict::Approve));
        assert_eq!(parse("Yes."), Some(Verdict::Approve));
        assert_eq!(
            parse("drop T2, t3"),
            Some(Verdict::Drop(vec!["T2".into(), "T3".into()]))
        );
        assert_eq!(
            parse("reject: Bravo should stay over the villa."),
            Some(Verdict::Reject("Bravo should stay over the villa".into()))
        );
        assert_eq!(parse("no"), Some(Verdict::Reject(String::new())));
        assert_eq!(parse("drop"), None);
        assert_eq!(parse("alfa, go to the villa"), None);
        assert_eq!(parse("yes, and then land"), None);
        assert_eq!(switch("Confirm on."), Some(true));
        assert_eq!(switch("confirm off"), Some(false));
        assert_eq!(parse("confirm on"), None);
    }

    #[test]
    fn drops_named_tasks_and_refuses_unknown_ones() {
        let mut plan = HeldPlan {
            instruction: "inspect the cars".into(),
            reasoning: String::new(),
            calls: vec![call("T1", "alfa"), call("T2", "bravo")],
        };
        let err = plan.drop_tasks(&["T9".into()]);
        assert!(err.is_err_and(|e| e.contains("its tasks: T1, T2")));
        assert_eq!(plan.calls.len(), 2);
        plan.drop_tasks(&["T2".into()]).expect("T2 is in the plan");
        assert_eq!(plan.calls, vec![call("T1", "alfa")]);
        let text = plan.describe(&[Some("alfa is on the ground".into())]);
        assert!(text.contains("not now (alfa is on the ground)"), "{text}");
        assert!(text.contains("`approve`"), "{text}");
    }
}

//! The prompt texts, compiled in so nothing is read from disk at run time.

/// The Coordinator's configuration prompt: the action API, rules, output structure.
pub const COORDINATOR: &str = include_str!("../text/coordinator.md");
/// The Supervisor's configuration prompt.
pub const SUPERVISOR: &str = include_str!("../text/supervisor.md");
/// The single model of the monolithic (`mnl`) ablation.
pub const MONOLITHIC: &str = include_str!("../text/monolithic.md");
/// Appended to [`COORDINATOR`] when a reply may decline (the `plan-only` aid off).
pub const COORDINATOR_REFUSAL: &str = include_str!("../text/coordinator_refusal.md");
/// Few-shot examples for the Coordinator (instruction, context, ideal reasoning and plan); those
/// whose reply declines are shown only when a reply may.
pub const COORDINATOR_EXAMPLES: &str = include_str!("../text/coordinator_examples.json");

/// Few-shot examples for the Supervisor (plan and swarm excerpt, ideal cycle).
pub const SUPERVISOR_EXAMPLES: &str = include_str!("../text/supervisor_examples.json");

/// One Supervisor example: an excerpt of its request and the ideal reply.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CycleExample {
    pub context: String,
    pub reply: serde_json::Value,
}

/// The Supervisor's few-shot examples, parsed.
pub fn supervisor_examples() -> Result<Vec<CycleExample>, serde_json::Error> {
    serde_json::from_str(SUPERVISOR_EXAMPLES)
}

/// One few-shot example.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Example {
    pub context: String,
    pub instruction: String,
    pub reply: serde_json::Value,
}

/// The Coordinator's few-shot examples, parsed.
pub fn coordinator_examples() -> Result<Vec<Example>, serde_json::Error> {
    serde_json::from_str(COORDINATOR_EXAMPLES)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reply::CoordinatorReply;

    #[test]
    fn supervisor_examples_follow_the_reply_shape() {
        let examples = supervisor_examples().expect("examples are valid JSON");
        assert!(examples.len() >= 2);
        for e in examples {
            crate::reply::SupervisorReply::parse(&e.reply.to_string())
                .unwrap_or_else(|err| panic!("{err}"));
        }
    }

    #[test]
    fn examples_parse_and_follow_the_reply_shape() {
        let examples = coordinator_examples().expect("examples are valid JSON");
        assert!(examples.len() >= 3);
        for e in examples {
            let text = e.reply.to_string();
            CoordinatorReply::parse(&text)
                .unwrap_or_else(|err| panic!("example {:?}: {err}", e.instruction));
        }
    }
}

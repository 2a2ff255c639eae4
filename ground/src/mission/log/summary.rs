//! What a mission log says, for people: the closing tally of a run and the timeline that
//! `tacos-ground replay` prints.

use super::{Line, Record, RefusedBy};

/// What a mission did, counted from its records: a run's closing summary, which therefore
/// agrees with the log however the run ended (a model call still in flight included).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Tally {
    /// Requests to a model (repair rounds included).
    pub model_calls: usize,
    pub supervisor_cycles: usize,
    /// Actions sent for a model's plan or cycle (they carry a task).
    pub model_actions: usize,
    /// Actions sent for the pilot's direct commands.
    pub direct_actions: usize,
    /// Calls of the models' replies that the engine's checks refused.
    pub rejections: usize,
    /// … and that the safety gate refused.
    pub gate_refusals: usize,
    /// Times a small-model aid changed what the engine did.
    pub aids_fired: usize,
}

impl Tally {
    pub fn of(lines: &[Line]) -> Tally {
        let mut t = Tally::default();
        for line in lines {
            match &line.record {
                Record::LlmRequest { .. } => t.model_calls += 1,
                Record::SupervisorCycle { .. } => t.supervisor_cycles += 1,
                Record::ActionSent { task: Some(_), .. } => t.model_actions += 1,
                Record::ActionSent { task: None, .. } => t.direct_actions += 1,
                Record::GateRejected {
                    by: RefusedBy::Checks,
                    ..
                } => t.rejections += 1,
                Record::GateRejected {
                    by: RefusedBy::SafetyGate,
                    ..
                } => t.gate_refusals += 1,
                Record::AidFired { .. } => t.aids_fired += 1,
                _ => {}
            }
        }
        t
    }
}

impl std::fmt::Display for Tally {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} model calls, {} supervisor cycles, {} actions sent by the models, {} by direct commands, {} calls refused by the checks and {} by the safety gate, {} small-model aids fired",
            self.model_calls,
            self.supervisor_cycles,
            self.model_actions,
            self.direct_actions,
            self.rejections,
            self.gate_refusals,
            self.aids_fired
        )
    }
}

/// The mission's timeline as text, one line per record (positions left out).
pub fn timeline(lines: &[Line]) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    for l in lines {
        let text = match &l.record {
            Record::MissionStart {
                mode,
                backend,
                scenario,
                drones,
                aids,
                ..
            } => {
                format!(
                    "mission start: mode {mode}, {backend}, map {scenario}, drones {}, aids {aids}",
                    drones.join(", ")
                )
            }
            Record::Pilot { text } => format!("pilot: {text}"),
            Record::Direct { text, outcome } => format!("direct command {text:?}: {outcome}"),
            Record::LlmRequest { layer, attempt, .. } => {
                format!("{layer}: request (attempt {attempt})")
            }
            Record::LlmReply {
                layer,
                latency_ms,
                prompt_tokens,
                completion_tokens,
                ..
            } => {
                format!(
                    "{layer}: reply in {latency_ms} ms ({prompt_tokens} prompt + {completion_tokens} completion tokens)"
                )
            }
            Record::LlmError { layer, error, .. } => format!("{layer}: error: {error}"),
            Record::Plan { reasoning, plan } => format!("plan: {reasoning} {plan}"),
            Record::GateRejected {
                layer,
                call,
                reason,
                by,
            } => {
                let why = if reason.is_empty() {
                    String::new()
                } else {
                    format!(": {reason}")
                };
                format!("{by} refused the {layer}'s {call}{why}")
            }
            Record::ActionSent {
                drone, seq, action, ..
            } => format!("sent #{seq} {action} to {drone}"),
            Record::ActionOutcome {
                drone,
                seq,
                outcome,
                ..
            } => format!("{drone} #{seq}: {outcome}"),
            Record::SupervisorCycle {
                plan_cycle,
                actions,
                plan_complete,
            } => {
                format!(
                    "supervisor cycle {plan_cycle}: [{}]{}",
                    actions.join("; "),
                    if *plan_complete { " plan complete" } else { "" }
                )
            }
            Record::PlanComplete { cycles } => {
                format!("plan complete after {cycles} supervisor cycles")
            }
            Record::Replan { reason } => format!("replan: {reason}"),
            Record::Event { text } => format!("event: {text}"),
            Record::AidFired { aid, detail } => format!("aid {aid}: {detail}"),
            Record::Position { .. } | Record::Step(_) => continue,
            Record::TraceBegun { .. } => "the core's steps traced from here".to_owned(),
            Record::MissionEnd { outcome } => format!("mission end: {outcome}"),
            Record::History { .. } => continue,
            Record::WorldEvent { text } => format!("world event: {text}"),
            Record::PlanAdopted { tasks, .. } => {
                let calls: Vec<String> = tasks.iter().map(|t| t.call.to_string()).collect();
                format!("plan in force: {}", calls.join("; "))
            }
            Record::PlanEnded { how } => format!("plan ended: {how}"),
            Record::Resumed { from, memory } => format!(
                "resumed from {from}: {} history entries, {}",
                memory.history.len(),
                match &memory.plan {
                    Some(plan) => format!("a plan of {} tasks", plan.tasks.len()),
                    None => "no plan in force".to_owned(),
                }
            ),
        };
        let _ = writeln!(out, "[{:>7.1}s] {text}", l.t);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refusals_are_counted_by_who_refused() {
        let line = |t: f64, record: Record| Line { t, record };
        let refused = |by| Record::GateRejected {
            layer: "supervisor".into(),
            call: "T1 alfa goto(car_1): why".into(),
            reason: String::new(),
            by,
        };
        // A record from before `by` was written reads as the checks'.
        let old: Line = serde_json::from_str(
            r#"{"t": 3.0, "kind": "gate_rejected", "layer": "coordinator", "call": "T2 bravo land()", "reason": ""}"#,
        )
        .expect("an old record reads");
        let lines = [
            line(1.0, refused(RefusedBy::Checks)),
            line(2.0, refused(RefusedBy::SafetyGate)),
            old,
        ];
        let tally = Tally::of(&lines);
        assert_eq!((tally.rejections, tally.gate_refusals), (2, 1));
        assert!(timeline(&lines).contains("the safety gate refused the supervisor's T1 alfa"));
    }
}

//! The Coordinator's checked reply taken in: a refusal without a plan is the pilot's answer
//! (nothing is sent, the plan in force stays); a plan has its repeats dropped, its forgotten
//! take-offs added (`implied-takeoffs`), and is held for the pilot (`confirm on`) or adopted.

use super::adopt::{adopt, with_implied_takeoffs, with_pending_kept, without_repeated_work};
use super::effect::Effect;
use super::snapshot::Snapshot;
use super::state::Core;
use super::step::CoordinatorAnswer;
use crate::mission::aids::Aid;
use crate::mission::approval::HeldPlan;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionError, MissionUpdate};
use crate::safety::SafetyGate;
use tacos_prompts::Call;
use tacos_prompts::render::{HistoryEntry, TaskStatus};

impl Core {
    /// The reply to `instruction` (`grounded`: the drones on the ground when it was asked).
    pub(super) fn coordinator_answered(
        &mut self,
        instruction: String,
        grounded: Vec<String>,
        answer: CoordinatorAnswer,
        snap: &Snapshot,
        gate: &SafetyGate,
    ) -> Vec<Effect> {
        let mut effects = Vec::new();
        if let Err(e) = self.take_plan(instruction, grounded, answer, snap, gate, &mut effects) {
            effects.push(Effect::Tell(MissionUpdate::Error(e.to_string())));
        }
        effects
    }

    fn take_plan(
        &mut self,
        instruction: String,
        grounded: Vec<String>,
        answer: CoordinatorAnswer,
        snap: &Snapshot,
        gate: &SafetyGate,
        effects: &mut Vec<Effect>,
    ) -> Result<(), MissionError> {
        let (reasoning, calls, refusal) = answer?;
        if let Some(refusal) = refusal {
            if calls.is_empty() {
                return Err(declined(reasoning, refusal, effects));
            }
            // A plan with a refusal: what it can do flies, and the pilot hears what it cannot.
            let text = format!("the Coordinator says: {refusal}");
            effects.extend(Effect::told(EventTopic::Note, text));
        }
        if calls.is_empty() {
            // Every call of the last attempt was refused: the plan in force (if any) stays, and
            // the refusals are in the log's repair requests.
            return Err(MissionError::NoValidReply {
                layer: "coordinator",
                attempts: self.bounds.max_repairs + 1,
                reason: "no call of its plan passed the checks".into(),
            });
        }
        let (calls, repeats) = without_repeated_work(calls);
        for call in repeats {
            let text = format!("{call}: repeats {}'s previous task: dropped", call.drone);
            effects.extend(Effect::told(EventTopic::Note, text));
        }
        let replan = std::mem::take(&mut self.replan_in_flight);
        let calls = if replan && self.aids.is_on(Aid::ReplanKeepsPending) {
            self.with_pending_kept(calls, snap, gate, effects)
        } else {
            calls
        };
        let calls = if self.aids.is_on(Aid::ImpliedTakeoffs) {
            // On the ground when asked and still now: a drone that has taken off while the
            // model thought (a take-off of the plan before) needs none.
            let now_grounded = snap.grounded_ids();
            let grounded: Vec<String> = (grounded.into_iter())
                .filter(|d| now_grounded.contains(d))
                .collect();
            let (calls, fired) = with_implied_takeoffs(calls, &grounded);
            effects.extend(fired);
            calls
        } else {
            calls
        };
        effects.push(Effect::Note(Record::Plan {
            reasoning: reasoning.clone(),
            plan: serde_json::to_value(&calls).unwrap_or_default(),
        }));
        effects.push(Effect::Tell(MissionUpdate::Plan {
            reasoning: reasoning.clone(),
            calls: calls.iter().map(|c| c.to_string()).collect(),
        }));
        if self.confirm {
            let plan = HeldPlan {
                instruction,
                reasoning,
                calls,
            };
            self.hold_for_approval(plan, snap, gate, effects);
            return Ok(());
        }
        effects.extend(adopt(&mut self.book, reasoning, calls));
        Ok(())
    }
}

impl Core {
    /// An automatic replan's `calls` after the pending tasks of the available drones that it
    /// leaves out (`adopt::with_pending_kept`); the aid's firing names them.
    fn with_pending_kept(
        &self,
        calls: Vec<Call>,
        snap: &Snapshot,
        gate: &SafetyGate,
        effects: &mut Vec<Effect>,
    ) -> Vec<Call> {
        let pending: Vec<Call> = (self.book.plan.iter())
            .flat_map(|p| &p.tasks)
            .filter(|t| matches!(t.status, TaskStatus::NotStarted | TaskStatus::Running))
            .map(|t| t.call.clone())
            .collect();
        let available = snap.available_ids(gate.scenario());
        let (plan, kept) = with_pending_kept(calls, &pending, &available);
        if !kept.is_empty() {
            let kept: Vec<String> = kept.iter().map(Call::to_string).collect();
            let detail = format!(
                "the replan left out pending work of drones still available, kept first: {}",
                kept.join("; ")
            );
            effects.push(Effect::aid_fired(Aid::ReplanKeepsPending, detail));
        }
        plan
    }
}

/// The Coordinator answered the pilot instead of planning: nothing is sent, the plan in force
/// (if any) stays, and the next request's history says what was declined and why.
fn declined(reasoning: String, refusal: String, effects: &mut Vec<Effect>) -> MissionError {
    effects.push(Effect::Note(Record::Event {
        text: format!("instruction declined by the Coordinator: {refusal} ({reasoning})"),
    }));
    effects.push(Effect::Remember(HistoryEntry::Event(format!(
        "the Coordinator declined the instruction: {refusal}"
    ))));
    MissionError::Declined { refusal }
}

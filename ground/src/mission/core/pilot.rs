//! A line from the pilot taken in: a direct command (carried out by the engine, beside the
//! models), the `confirm on|off` switch, an answer to a plan held for approval, or an
//! instruction for the models, refused before any model is asked when it names a drone the
//! swarm lacks.

use super::calls::Coordination;
use super::effect::Effect;
use super::snapshot::Snapshot;
use super::start::Start;
use super::state::Core;
use crate::mission::addressed;
use crate::mission::approval::{self, HeldPlan, Verdict};
use crate::mission::config::Mode;
use crate::mission::directives;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionError, MissionUpdate, Overtaken};
use crate::safety::SafetyGate;
use tacos_prompts::render::{HistoryEntry, TaskStatus};

impl Core {
    pub(super) fn pilot(&mut self, text: &str, snap: &Snapshot, gate: &SafetyGate) -> Vec<Effect> {
        let text = text.trim();
        if text.is_empty() {
            return Vec::new();
        }
        let scenario = gate.scenario();
        let drones = snap.swarm_ids(scenario);
        if let Some(directive) = directives::parse(text, &drones) {
            // The override it raises ends the plan (`Input::Overridden`).
            return vec![Effect::Direct {
                text: text.to_owned(),
                directive,
            }];
        }
        if let Some(on) = approval::switch(text) {
            self.confirm = on;
            let what = if on {
                "on: every plan waits for your approval"
            } else {
                "off: plans fly once checked"
            };
            return Effect::told(EventTopic::Note, format!("confirm {what}")).into();
        }
        let mut effects = Vec::new();
        if self.held.is_some() && self.answer_held(text, snap, gate, &mut effects) {
            return effects;
        }
        effects.push(Effect::Note(Record::Pilot {
            text: text.to_owned(),
        }));
        let unknown =
            addressed::unknown_drones(text, &drones, &scenario.slot_ids(), &scenario.place_names());
        if !unknown.is_empty() {
            let refusal = MissionError::UnknownDrones {
                names: unknown,
                swarm: drones,
            };
            effects.push(Effect::Note(Record::Event {
                text: format!("instruction refused: {refusal}"),
            }));
            effects.push(Effect::Tell(MissionUpdate::Error(refusal.to_string())));
            return effects;
        }
        effects.push(Effect::InstructionBegun(text.to_owned()));
        match self.mode {
            Mode::Mnl => {
                // A cycle in flight was asked without this instruction.
                effects.extend(self.calls.drop_call(Overtaken::NewerWork));
                self.calls.work_replaced();
                let mnl = &mut self.book.mnl;
                mnl.instructions.push(text.to_owned());
                mnl.active = true;
                mnl.cycles = 0;
                mnl.claimed_done = false;
                mnl.tasks.retain(|t| t.status == TaskStatus::Running);
            }
            Mode::Tacos | Mode::Wor => {
                effects.push(Effect::Remember(HistoryEntry::Pilot(text.to_owned())));
                effects.extend(self.calls.want(Coordination::Pilot(text.to_owned())));
            }
        }
        effects
    }

    /// Holds `plan` and shows it to the pilot, call by call with what the checks say now.
    pub(super) fn hold_for_approval(
        &mut self,
        plan: HeldPlan,
        snap: &Snapshot,
        gate: &SafetyGate,
        effects: &mut Vec<Effect>,
    ) {
        let start = Start::new(snap, gate, &self.book);
        let verdicts: Vec<Option<String>> = plan.calls.iter().map(|c| start.blocker(c)).collect();
        effects.extend(Effect::told(EventTopic::Note, plan.describe(&verdicts)));
        self.held = Some(plan);
    }

    /// The pilot's line while a plan is held: true when it was the answer; otherwise the held
    /// plan is dropped and the line is a new instruction.
    fn answer_held(
        &mut self,
        text: &str,
        snap: &Snapshot,
        gate: &SafetyGate,
        effects: &mut Vec<Effect>,
    ) -> bool {
        let Some(mut plan) = self.held.take() else {
            return false;
        };
        let Some(verdict) = approval::parse(text) else {
            let text = format!(
                "the plan for {:?} was not approved: a new instruction came",
                plan.instruction
            );
            effects.extend(Effect::told(EventTopic::Note, text));
            return false;
        };
        effects.push(Effect::Note(Record::Pilot {
            text: text.to_owned(),
        }));
        match verdict {
            Verdict::Approve => {
                let text = format!("plan for {:?} approved", plan.instruction);
                effects.extend(Effect::told(EventTopic::Note, text));
                effects.extend(super::adopt(&mut self.book, plan.reasoning, plan.calls));
            }
            Verdict::Drop(ids) => {
                if let Err(why) = plan.drop_tasks(&ids) {
                    effects.extend(Effect::told(
                        EventTopic::Note,
                        format!("nothing dropped: {why}"),
                    ));
                } else if plan.calls.is_empty() {
                    let text = format!(
                        "every call dropped: the plan for {:?} ends",
                        plan.instruction
                    );
                    effects.extend(Effect::told(EventTopic::Note, text));
                    return true;
                }
                self.hold_for_approval(plan, snap, gate, effects);
            }
            Verdict::Reject(why) => {
                let why = if why.is_empty() {
                    "no reason given".to_owned()
                } else {
                    why
                };
                let text = format!("plan for {:?} rejected: {why}", plan.instruction);
                effects.extend(Effect::told(EventTopic::Note, text));
                let again = format!(
                    "The pilot rejected your plan for \"{}\": {why}. Plan again.",
                    plan.instruction
                );
                // In the history the next request reads, not the log's (as before the move).
                self.history.push(HistoryEntry::Pilot(again.clone()));
                effects.extend(self.calls.want(Coordination::Pilot(again)));
            }
        }
        true
    }
}

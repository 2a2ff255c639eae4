//! `--confirm`: a Coordinator plan held for the pilot, and the pilot's answer to it
//! (`mission::approval`). Direct commands never wait for it; one ends a held plan.

use super::Mission;
use crate::mission::approval::{self, HeldPlan, Verdict};
use crate::mission::core::Coordination;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionError};

/// What a pilot line did to the held plan.
pub(super) enum Answered {
    /// The line was the answer; nothing else is to be done with it.
    Done(Result<(), MissionError>),
    /// Not an answer: the held plan is dropped and the line is a new instruction.
    NewInstruction,
}

impl Mission {
    /// Holds `plan` and shows it to the pilot, call by call with what the checks say now.
    pub(super) fn hold_for_approval(&mut self, plan: HeldPlan) {
        self.show_held(&plan);
        self.held = Some(plan);
    }

    fn show_held(&self, plan: &HeldPlan) {
        let verdicts: Vec<Option<String>> =
            self.with_start(|start| plan.calls.iter().map(|c| start.blocker(c)).collect());
        self.event(EventTopic::Note, plan.describe(&verdicts));
    }

    /// The pilot's line while a plan is held.
    pub(super) async fn answer_held(&mut self, text: &str) -> Answered {
        let Some(mut plan) = self.held.take() else {
            return Answered::NewInstruction;
        };
        let Some(verdict) = approval::parse(text) else {
            self.event(
                EventTopic::Note,
                format!(
                    "the plan for {:?} was not approved: a new instruction came",
                    plan.instruction
                ),
            );
            return Answered::NewInstruction;
        };
        self.log.note(Record::Pilot {
            text: text.to_owned(),
        });
        match verdict {
            Verdict::Approve => {
                self.event(
                    EventTopic::Note,
                    format!("plan for {:?} approved", plan.instruction),
                );
                self.adopt_plan(plan.reasoning, plan.calls);
                Answered::Done(Ok(()))
            }
            Verdict::Drop(ids) => {
                if let Err(why) = plan.drop_tasks(&ids) {
                    self.event(EventTopic::Note, format!("nothing dropped: {why}"));
                } else if plan.calls.is_empty() {
                    self.event(
                        EventTopic::Note,
                        format!(
                            "every call dropped: the plan for {:?} ends",
                            plan.instruction
                        ),
                    );
                    return Answered::Done(Ok(()));
                }
                self.hold_for_approval(plan);
                Answered::Done(Ok(()))
            }
            Verdict::Reject(why) => {
                let why = if why.is_empty() {
                    "no reason given".to_owned()
                } else {
                    why
                };
                self.event(
                    EventTopic::Note,
                    format!("plan for {:?} rejected: {why}", plan.instruction),
                );
                let again = format!(
                    "The pilot rejected your plan for \"{}\": {why}. Plan again.",
                    plan.instruction
                );
                self.history
                    .push(tacos_prompts::render::HistoryEntry::Pilot(again.clone()));
                self.want_coordination(Coordination::Pilot(again));
                Answered::Done(Ok(()))
            }
        }
    }
}

//! The Coordinator layer: the pilot's instruction (or an automatic replan) in, a checked plan out.

use super::Mission;
use super::in_flight::{Answered, CoordinatorAnswer, InFlight};
use crate::mission::aids::Aid;
use crate::mission::approval::HeldPlan;
use crate::mission::core::{
    Checked, Coordination, CoordinatorAsk, CoordinatorContext, Snapshot, adopt, coordinator_ask,
    with_implied_takeoffs, without_repeated_work,
};
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionError, MissionUpdate};
use tacos_prompts::render::HistoryEntry;
use tacos_prompts::schema::Output;
use tacos_prompts::{Call, CoordinatorReply};

/// How long a Coordinator call waits for a drone to be heard again when none is available: a
/// status is stale after a second, and a loaded ground (a model computing on both cores) or a
/// network hiccup can silence the whole swarm for that long without anything being lost.
const SILENCE_GRACE: std::time::Duration = std::time::Duration::from_secs(5);

impl Mission {
    /// A snapshot with a drone available; when none is, the first within [`SILENCE_GRACE`]
    /// that has one, or the last.
    async fn snapshot_after_silence(&self) -> Snapshot {
        let deadline = tokio::time::Instant::now() + SILENCE_GRACE;
        loop {
            let snap = self.snapshot();
            let available = snap.available_ids(self.gate.scenario());
            if !available.is_empty() || tokio::time::Instant::now() >= deadline {
                return snap;
            }
            tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        }
    }

    /// Starts the Coordinator's call for `instruction` beside the engine
    /// ([`Self::coordinator_answered`] takes its reply); its plan will replace the current one
    /// (the pending plan is in its prompt).
    pub(super) async fn coordinate(&mut self, work: &Coordination) -> Result<(), MissionError> {
        // The prompt, the schema and the checks are made from this one snapshot.
        let snap = self.snapshot_after_silence().await;
        let context = CoordinatorContext {
            snap: &snap,
            scenario: self.gate.scenario(),
            book: &self.book,
            history: &self.history,
            events: &self.events,
            aids: self.cfg.aids,
        };
        let mut effects = Vec::new();
        let ask = coordinator_ask(work, &context, &mut effects);
        self.apply(effects);
        let CoordinatorAsk {
            instruction,
            messages,
            schema,
            token_budget,
            check,
            grounded,
        } = ask?;
        let log = self.log.clone();
        self.tell(MissionUpdate::Thinking {
            layer: "coordinator",
        });
        self.stats.update(|s| s.coordinator_calls += 1);
        let caller = self.caller.clone();
        let max_tokens = self.cfg.coordinator_max_tokens.max(token_budget);
        let call = async move {
            let answer = caller
                .ask(
                    "coordinator",
                    messages,
                    Output::Coordinator,
                    schema,
                    max_tokens,
                    CoordinatorReply::parse,
                    true,
                    move |reply: &CoordinatorReply| {
                        let judged = check.judge(reply);
                        for (aid, detail) in judged.aids_fired {
                            log.aid_fired(aid, detail);
                        }
                        Checked {
                            nothing_passed: judged.plan.is_empty() && judged.refusal.is_none(),
                            accepted: (judged.reasoning, judged.plan, judged.refusal),
                            rejections: judged.rejections,
                            // A plan's calls are not actions yet: the gate judges them when sent.
                            gate_refusals: Vec::new(),
                            narrowed: judged.narrowed,
                        }
                    },
                )
                .await;
            Answered::Coordinator {
                instruction,
                grounded,
                answer,
            }
        };
        self.in_flight = Some(InFlight::spawn("coordinator", call));
        self.calls.started("coordinator");
        Ok(())
    }

    /// The Coordinator's checked reply to `instruction` (`grounded`: the drones on the ground
    /// when it was asked): its plan is held for the pilot or adopted.
    pub(super) fn coordinator_answered(
        &mut self,
        instruction: String,
        grounded: Vec<String>,
        answer: CoordinatorAnswer,
    ) -> Result<(), MissionError> {
        let (reasoning, calls, refusal) = answer?;
        if let Some(refusal) = refusal {
            if calls.is_empty() {
                return Err(self.declined(reasoning, refusal));
            }
            // A plan with a refusal: what it can do flies, and the pilot hears what it cannot.
            self.event(EventTopic::Note, format!("the Coordinator says: {refusal}"));
        }
        if calls.is_empty() {
            // Every call of the last attempt was refused: the plan in force (if any) stays, and
            // the refusals are in the log's repair requests.
            return Err(MissionError::NoValidReply {
                layer: "coordinator",
                attempts: self.caller.max_repairs + 1,
                reason: "no call of its plan passed the checks".into(),
            });
        }
        let (calls, repeats) = without_repeated_work(calls);
        for call in repeats {
            let text = format!("{call}: repeats {}'s previous task: dropped", call.drone);
            self.event(EventTopic::Note, text);
        }
        let calls = if self.cfg.aids.is_on(Aid::ImpliedTakeoffs) {
            let (calls, effects) = with_implied_takeoffs(calls, &grounded);
            self.apply(effects);
            calls
        } else {
            calls
        };
        self.log.note(Record::Plan {
            reasoning: reasoning.clone(),
            plan: serde_json::to_value(&calls).unwrap_or_default(),
        });
        self.tell(MissionUpdate::Plan {
            reasoning: reasoning.clone(),
            calls: calls.iter().map(|c| c.to_string()).collect(),
        });
        if self.cfg.confirm {
            self.hold_for_approval(HeldPlan {
                instruction,
                reasoning,
                calls,
            });
            return Ok(());
        }
        self.adopt_plan(reasoning, calls);
        Ok(())
    }

    /// The Coordinator answered the pilot instead of planning: nothing is sent, the plan in force
    /// (if any) stays, and the next request's history says what was declined and why.
    fn declined(&mut self, reasoning: String, refusal: String) -> MissionError {
        self.log.note(Record::Event {
            text: format!("instruction declined by the Coordinator: {refusal} ({reasoning})"),
        });
        self.remember(HistoryEntry::Event(format!(
            "the Coordinator declined the instruction: {refusal}"
        )));
        MissionError::Declined { refusal }
    }

    /// Makes `calls` the plan in force (`core::adopt`).
    pub(super) fn adopt_plan(&mut self, reasoning: String, calls: Vec<Call>) {
        let effects = adopt(&mut self.book, reasoning, calls);
        self.apply(effects);
    }
}

//! The Coordinator layer: the pilot's instruction (or an automatic replan) in, a checked plan out.

use super::Mission;
use super::in_flight::{Answered, Coordination, CoordinatorAnswer, InFlight};
use crate::mission::aids::Aid;
use crate::mission::approval::HeldPlan;
use crate::mission::core::Checked;
use crate::mission::core::{PlanCheck, adopt, with_implied_takeoffs, without_repeated_work};
use crate::mission::grounding;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionError, MissionUpdate};
use crate::mission::whole_swarm;
use tacos_llm::ChatMessage;
use tacos_prompts::render::{self, HistoryEntry, TaskStatus};
use tacos_prompts::schema::{self, Output};
use tacos_prompts::{Call, CoordinatorReply, texts};
use tacos_shared::{DroneId, DroneMode};

/// How long a Coordinator call waits for a drone to be heard again when none is available: a
/// status is stale after a second, and a loaded ground (a model computing on both cores) or a
/// network hiccup can silence the whole swarm for that long without anything being lost.
const SILENCE_GRACE: std::time::Duration = std::time::Duration::from_secs(5);

impl Mission {
    /// The available drones; when there are none, those heard again within [`SILENCE_GRACE`].
    async fn available_after_silence(&self) -> Vec<String> {
        let deadline = tokio::time::Instant::now() + SILENCE_GRACE;
        loop {
            let available = self.available_ids();
            if !available.is_empty() || tokio::time::Instant::now() >= deadline {
                return available;
            }
            tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        }
    }

    /// Starts the Coordinator's call for `instruction` beside the engine
    /// ([`Self::coordinator_answered`] takes its reply); its plan will replace the current one
    /// (the pending plan is in its prompt).
    pub(super) async fn coordinate(&mut self, work: &Coordination) -> Result<(), MissionError> {
        let (instruction, from_pilot) = match work {
            Coordination::Pilot(text) => (text.as_str(), true),
            Coordination::Replan(text) => (text.as_str(), false),
        };
        let pending: Vec<(Call, TaskStatus)> = self
            .plan_lines()
            .into_iter()
            .filter(|(_, s)| *s != TaskStatus::Done)
            .collect();
        let (drones, places) = self.enums();
        let names: Vec<String> = drones.iter().chain(&places).cloned().collect();
        let named = render::named_in(instruction, &names);
        let named_places: Vec<String> = named
            .iter()
            .filter(|n| places.contains(n))
            .cloned()
            .collect();
        let pending_places: Vec<String> = pending
            .iter()
            .filter_map(|(c, _)| c.target_name().map(str::to_owned))
            .collect();
        let aids = self.cfg.aids;
        let scope = grounding::places_in_scope(&places, &named, &pending_places)
            .filter(|_| aids.is_on(Aid::PlaceScope));
        if let Some(scope) = scope.as_ref().filter(|s| s.len() < places.len()) {
            self.log.aid_fired(
                Aid::PlaceScope,
                format!(
                    "the plan may name {} of the map's {} places: {}",
                    scope.len(),
                    places.len(),
                    scope.join(", ")
                ),
            );
        }
        // A plan for a drone that cannot fly it would wait for ever: the grammar offers only the
        // available drones, and the reply check holds a server that ignores the schema to them.
        let available = self.available_after_silence().await;
        if available.is_empty() {
            return Err(MissionError::NoDroneAvailable);
        }
        // A target the instruction asks to be followed must be tracked by the plan (or be
        // followed already); a drone named beside it is suggested only if it can fly.
        let follow: Vec<grounding::FollowAsked> = if aids.is_on(Aid::FollowWords) {
            grounding::follow_asked(instruction, &drones, &self.trackable())
                .into_iter()
                .map(|a| grounding::FollowAsked {
                    drone: a.drone.filter(|d| available.contains(d)),
                    ..a
                })
                .collect()
        } else {
            Vec::new()
        };
        if !follow.is_empty() {
            let targets: Vec<&str> = follow.iter().map(|a| a.target.as_str()).collect();
            self.log.aid_fired(
                Aid::FollowWords,
                format!(
                    "the instruction asks that {} be followed: the plan must track it",
                    targets.join(", ")
                ),
            );
        }
        // The pilot's instruction for the whole swarm: the available drones and their modes,
        // for the reply check (`whole_swarm`; a replan's own words are not the pilot's).
        let whole_swarm: Option<Vec<(String, DroneMode)>> = (from_pilot
            && aids.is_on(Aid::WholeSwarm)
            && whole_swarm::addresses_whole_swarm(instruction))
        .then(|| {
            let snap = self.snapshot();
            available
                .iter()
                .filter_map(|d| {
                    let entry = DroneId::new(d).ok().and_then(|id| snap.swarm.get(&id))?;
                    Some((d.clone(), entry.effective_mode(snap.now)))
                })
                .collect()
        });
        let grounded = self.grounded_ids();
        let followed = self.followed_targets();
        let user = render::coordinator_request(
            &render::swarm(&self.drone_lines()),
            &self.world_text(),
            &render::plan(&pending),
            &render::history(&self.history),
            instruction,
            &named,
        );
        let offer_refusal = !aids.is_on(Aid::PlanOnly);
        let messages = coordinator_messages(user, offer_refusal);
        let in_scope = |name: &String| scope.as_ref().is_none_or(|s| s.contains(name));
        let trackable: Vec<String> = self.trackable().into_iter().filter(in_scope).collect();
        let mut schema = schema::build(
            Output::Coordinator,
            &available,
            scope.as_ref().unwrap_or(&places),
            &trackable,
        );
        if !offer_refusal {
            schema = schema::without_refusal(&schema);
        }
        let plan_cap = schema::plan_max_calls(&schema);
        let token_budget = if aids.is_on(Aid::PlanLengthCap) {
            schema::token_budget(Output::Coordinator, drones.len())
        } else {
            schema = schema::without_plan_cap(&schema);
            schema::coordinator_token_budget(schema::PLAN_MAX_CALLS)
        };
        let check = PlanCheck {
            scenario: self.gate.scenario().clone(),
            visible: self.visible_targets(),
            drones: drones.clone(),
            available: available.clone(),
            places,
            scope,
            named_places,
            aids,
            plan_cap,
            schema: schema.clone(),
            on_the_ground: grounded.clone(),
            follow,
            followed,
            whole_swarm,
        };
        let log = self.log.clone();
        self.tell(MissionUpdate::Thinking {
            layer: "coordinator",
        });
        self.stats.update(|s| s.coordinator_calls += 1);
        let caller = self.caller.clone();
        let max_tokens = self.cfg.coordinator_max_tokens.max(token_budget);
        let instruction = instruction.to_owned();
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

/// The Coordinator's messages: its configuration prompt, the few-shot examples as turns, then
/// the request. `offer_refusal`: a reply may decline (the `plan-only` aid off).
pub fn coordinator_messages(user: String, offer_refusal: bool) -> Vec<ChatMessage> {
    let mut messages = coordinator_fixed_messages(offer_refusal);
    messages.push(ChatMessage::user(user));
    messages
}

/// The beginning every Coordinator request shares: its configuration prompt and the few-shot
/// turns.
pub fn coordinator_fixed_messages(offer_refusal: bool) -> Vec<ChatMessage> {
    let system = if offer_refusal {
        format!("{}{}", texts::COORDINATOR, texts::COORDINATOR_REFUSAL)
    } else {
        texts::COORDINATOR.to_owned()
    };
    let mut messages = vec![ChatMessage::system(system)];
    for example in texts::coordinator_examples().unwrap_or_default() {
        if !offer_refusal && example.reply.get("refusal").is_some() {
            continue;
        }
        // "Named in the instruction" as a real request shows it: the example plan's drones and
        // places that its instruction names.
        let names: Vec<String> = CoordinatorReply::parse(&example.reply.to_string())
            .map(|r| {
                r.plan
                    .iter()
                    .flat_map(|c| [Some(c.drone.clone()), c.target_name().map(str::to_owned)])
                    .flatten()
                    .collect()
            })
            .unwrap_or_default();
        let named = render::named_section(&render::named_in(&example.instruction, &names));
        messages.push(ChatMessage::user(format!(
            "## Context\n{}\n## Instruction\n{}\n{named}",
            example.context, example.instruction
        )));
        messages.push(ChatMessage::assistant(example.reply.to_string()));
    }
    messages
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refusal_is_offered_only_with_the_plan_only_aid_off() {
        let text = |messages: &[ChatMessage]| {
            messages
                .iter()
                .map(|m| m.content.clone())
                .collect::<String>()
        };
        let plan_only = text(&coordinator_fixed_messages(false));
        let may_decline = text(&coordinator_fixed_messages(true));
        assert!(!plan_only.contains("refusal"), "{plan_only}");
        assert!(may_decline.contains("## Declining"));
        assert!(may_decline.contains(r#""refusal":"airport is not a place on this map"#));
    }
}

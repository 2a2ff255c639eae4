//! The Coordinator's request for one piece of work (a pilot's instruction or a replan), built
//! from one snapshot: its messages, its schema, its token budget, and the checks its reply is
//! held to (`PlanCheck`). The aids that act on the request (`place-scope`, `follow-words`,
//! `plan-only`, `plan-length-cap`, `whole-swarm`) say when they fire.

use super::book::PlanBook;
use super::calls::Coordination;
use super::effect::Effect;
use super::plan_check::PlanCheck;
use super::prompt_view::{plan_lines, trackable};
use super::snapshot::Snapshot;
use crate::mission::aids::{Aid, ModelAids};
use crate::mission::grounding;
use crate::mission::report::MissionError;
use crate::mission::whole_swarm;
use tacos_llm::ChatMessage;
use tacos_prompts::render::{self, HistoryEntry, TaskStatus};
use tacos_prompts::schema::{self, Output};
use tacos_prompts::{Call, CoordinatorReply, texts};
use tacos_shared::DroneMode;
use tacos_shared::scenario::Scenario;

/// What the Coordinator is asked.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct CoordinatorAsk {
    pub(crate) instruction: String,
    pub(crate) messages: Vec<ChatMessage>,
    pub(crate) schema: serde_json::Value,
    /// The completion tokens the reply may need (the engine takes the larger of this and its
    /// configured limit).
    pub(crate) token_budget: u32,
    /// What the reply is held to.
    pub(crate) check: PlanCheck,
    /// The drones on the ground when it was asked (for the take-offs a plan forgets).
    pub(crate) grounded: Vec<String>,
}

/// What the request is made from.
pub(crate) struct CoordinatorContext<'a> {
    pub(crate) snap: &'a Snapshot,
    pub(crate) scenario: &'a Scenario,
    pub(crate) book: &'a PlanBook,
    pub(crate) history: &'a [HistoryEntry],
    /// The world events taken in, as the prompts show them.
    pub(crate) events: &'a [String],
    pub(crate) aids: ModelAids,
}

/// The Coordinator's request for `work`; the aids that fired go to `effects`. No drone
/// available: a plan would wait for ever, so nothing is asked.
pub(crate) fn coordinator_ask(
    work: &Coordination,
    cx: &CoordinatorContext<'_>,
    effects: &mut Vec<Effect>,
) -> Result<CoordinatorAsk, MissionError> {
    let (instruction, from_pilot) = match work {
        Coordination::Pilot(text) => (text.as_str(), true),
        Coordination::Replan(text) => (text.as_str(), false),
    };
    let (snap, scenario, aids) = (cx.snap, cx.scenario, cx.aids);
    // The grammar offers only the available drones, and the reply check holds a server that
    // ignores the schema to them.
    let available = snap.available_ids(scenario);
    if available.is_empty() {
        return Err(MissionError::NoDroneAvailable);
    }
    let pending: Vec<(Call, TaskStatus)> = plan_lines(cx.book)
        .into_iter()
        .filter(|(_, s)| *s != TaskStatus::Done)
        .collect();
    let (drones, places) = snap.enums(scenario);
    let names: Vec<String> = drones.iter().chain(&places).cloned().collect();
    let kinds = render::landmark_kinds(&scenario.world);
    let named = render::named_with_kinds(instruction, &names, &kinds);
    let named_places: Vec<String> = named
        .iter()
        .filter(|n| places.contains(n))
        .cloned()
        .collect();
    let pending_places: Vec<String> = pending
        .iter()
        .filter_map(|(c, _)| c.target_name().map(str::to_owned))
        .collect();
    let scope = grounding::places_in_scope(&places, &named, &pending_places)
        .filter(|_| aids.is_on(Aid::PlaceScope));
    if let Some(scope) = scope.as_ref().filter(|s| s.len() < places.len()) {
        let detail = format!(
            "the plan may name {} of the map's {} places: {}",
            scope.len(),
            places.len(),
            scope.join(", ")
        );
        effects.push(Effect::aid_fired(Aid::PlaceScope, detail));
    }
    // A target the instruction asks to be followed must be tracked by the plan (or be
    // followed already); a drone named beside it is suggested only if it can fly.
    let follow: Vec<grounding::FollowAsked> = if aids.is_on(Aid::FollowWords) {
        grounding::follow_asked(instruction, &drones, &trackable(scenario))
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
        let detail = format!(
            "the instruction asks that {} be followed: the plan must track it",
            targets.join(", ")
        );
        effects.push(Effect::aid_fired(Aid::FollowWords, detail));
    }
    // The available drones and their modes, for the reply check; the pilot's instruction may be
    // for all of them (`whole_swarm`; a replan's own words are not the pilot's).
    let modes: Vec<(String, DroneMode)> = (available.iter())
        .filter_map(|d| Some((d.clone(), snap.mode_of(d)?)))
        .collect();
    let whole_swarm = from_pilot
        && aids.is_on(Aid::WholeSwarm)
        && whole_swarm::addresses_whole_swarm(instruction);
    let grounded = snap.grounded_ids();
    let user = render::coordinator_request(
        &render::swarm(&snap.drone_lines(scenario)),
        &snap.world_text(scenario, cx.events),
        &render::plan(&pending),
        &render::history(cx.history),
        instruction,
        &named,
    );
    let offer_refusal = !aids.is_on(Aid::PlanOnly);
    let messages = coordinator_messages(user, offer_refusal);
    let in_scope = |name: &String| scope.as_ref().is_none_or(|s| s.contains(name));
    let trackable: Vec<String> = trackable(scenario).into_iter().filter(in_scope).collect();
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
        scenario: scenario.clone(),
        visible: snap.targets.clone(),
        drones,
        available,
        places,
        scope,
        named_places,
        aids,
        plan_cap,
        schema: schema.clone(),
        on_the_ground: grounded.clone(),
        modes,
        follow,
        followed: snap.followed_targets(),
        whole_swarm,
    };
    Ok(CoordinatorAsk {
        instruction: instruction.to_owned(),
        messages,
        schema,
        token_budget,
        check,
        grounded,
    })
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
        // places that its instruction names, by name or by kind (an example's landmarks are
        // named `<kind>_<n>`).
        let names: Vec<String> = CoordinatorReply::parse(&example.reply.to_string())
            .map(|r| {
                r.plan
                    .iter()
                    .flat_map(|c| [Some(c.drone.clone()), c.target_name().map(str::to_owned)])
                    .flatten()
                    .collect()
            })
            .unwrap_or_default();
        let kinds: Vec<(String, String)> = (names.iter())
            .filter_map(|n| Some((n.clone(), n.rsplit_once('_')?.0.to_owned())))
            .collect();
        let named = render::named_with_kinds(&example.instruction, &names, &kinds);
        let named = render::named_section(&named);
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

//! The checks of a Coordinator's reply: each call names an available drone and something real
//! in the places the instruction allows; an empty plan comes with a refusal that does not deny a
//! place the pilot named; the aids' own rules (whole swarm, follow-words, the take-off a goto
//! needs when `implied-takeoffs` is off). Fixed when the call is asked, so every repair round is
//! judged against the same facts.

use super::checks::check_static;
use super::outcomes::effect_holds;
use crate::mission::aids::{Aid, ModelAids};
use crate::mission::grounding::{self, FollowAsked};
use crate::mission::whole_swarm;
use tacos_prompts::render;
use tacos_prompts::schema;
use tacos_prompts::{ActionName, Call, CoordinatorReply};
use tacos_shared::DroneMode;
use tacos_shared::messages::TargetObservation;
use tacos_shared::scenario::Scenario;

/// What a Coordinator reply is checked against.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PlanCheck {
    pub(crate) scenario: Scenario,
    /// The targets seen when the call was asked.
    pub(crate) visible: Vec<TargetObservation>,
    /// The swarm's drones, and those of them a plan may use.
    pub(crate) drones: Vec<String>,
    pub(crate) available: Vec<String>,
    /// The map's places, the ones the plan may name (`place-scope`), and those the pilot named.
    pub(crate) places: Vec<String>,
    pub(crate) scope: Option<Vec<String>>,
    pub(crate) named_places: Vec<String>,
    pub(crate) aids: ModelAids,
    /// The schema's bound on the plan's length, and the schema itself (a repair round's grammar
    /// is narrowed from it).
    pub(crate) plan_cap: usize,
    pub(crate) schema: serde_json::Value,
    /// The drones on the ground when the call was asked, and the available drones' modes.
    pub(crate) on_the_ground: Vec<String>,
    pub(crate) modes: Vec<(String, DroneMode)>,
    /// What the instruction asks to be followed (`follow-words`), and what is followed already.
    pub(crate) follow: Vec<FollowAsked>,
    pub(crate) followed: Vec<String>,
    /// The pilot's instruction is for every drone (`whole-swarm`): every one of `modes`.
    pub(crate) whole_swarm: bool,
}

/// A Coordinator reply as judged.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PlanJudgement {
    pub(crate) reasoning: String,
    /// The calls that passed.
    pub(crate) plan: Vec<Call>,
    pub(crate) refusal: Option<String>,
    /// Why the rest did not, for the repair round.
    pub(crate) rejections: Vec<String>,
    /// The repair round's schema when the reply missed what a grammar can require.
    pub(crate) narrowed: Option<serde_json::Value>,
    /// The aids that changed what happens, with what they did (`Record::AidFired`).
    pub(crate) aids_fired: Vec<(Aid, String)>,
    /// Why the reply earns a second look though nothing in it is refused (`Checked::doubts`).
    pub(crate) doubts: Vec<String>,
}

impl PlanCheck {
    pub(crate) fn judge(&self, reply: &CoordinatorReply) -> PlanJudgement {
        let mut rejections = Vec::new();
        let mut aids_fired = Vec::new();
        let mut plan = Vec::new();
        for call in &reply.plan {
            match self.check_call(call) {
                Ok(()) => plan.push(call.clone()),
                Err(why) => rejections.push(format!("{call}: {why}")),
            }
        }
        // An empty plan is a reply only with a refusal for the pilot, and not one about a
        // place the pilot named that the map has: the 1.5B model declined "charlie, search
        // the business_district" on the lab map, which has it.
        match reply.refusal_text() {
            None if reply.plan.is_empty() => rejections.push(self.empty_plan_text()),
            Some(refusal) if reply.plan.is_empty() => {
                for place in render::named_in(refusal, &self.named_places) {
                    rejections.push(format!(
                        "the refusal: {place} is a place on this map (the pilot named it), and a \
                         goto can reach it"
                    ));
                }
            }
            _ => {}
        }
        if self.aids.is_on(Aid::PlanLengthCap)
            && self.plan_cap < schema::PLAN_MAX_CALLS
            && reply.plan.len() >= self.plan_cap
        {
            aids_fired.push((
                Aid::PlanLengthCap,
                format!(
                    "the plan filled its cap of {} calls (three per drone)",
                    self.plan_cap
                ),
            ));
        }
        // The whole plan the repair round's grammar allows (`repair-grammar`), for a plan of
        // one action for the whole swarm that left drones out.
        let mut whole: Option<Vec<schema::RequiredCall>> = None;
        if let Some(available) = self.whole_swarm.then_some(&self.modes) {
            let left = whole_swarm::left_out(&reply.plan, available);
            if !left.is_empty() {
                let text = whole_swarm::left_out_text(&left);
                aids_fired.push((Aid::WholeSwarm, text.clone()));
                rejections.push(text);
                // The 1.5B default sent the same three take-offs back three times when told:
                // a plan of one action without a target is then the whole plan's grammar, that
                // action for each drone whose state it would change.
                whole = whole_swarm::one_action_without_target(&reply.plan).map(|action| {
                    whole_swarm::needing(action, available)
                        .into_iter()
                        .map(|drone| schema::RequiredCall {
                            drones: vec![drone],
                            action: action.as_str(),
                            target: schema::NO_TARGET.to_owned(),
                        })
                        .collect()
                });
            }
        }
        if !self.aids.is_on(Aid::ImpliedTakeoffs) {
            // The rule the aid stands in for: a drone on the ground cannot fly a goto or a
            // chase that no take-off precedes.
            for i in missing_takeoffs(&plan, &self.on_the_ground)
                .into_iter()
                .rev()
            {
                let call = plan.remove(i);
                rejections.push(format!(
                    "{call}: {} is on the ground and the plan never takes it off: add `{} \
                     arm_takeoff` before it",
                    call.drone, call.drone
                ));
            }
        }
        let missing = grounding::untracked(&self.follow, &plan, &self.followed);
        // The repair round's grammar opens the plan with the missing tracking.
        let required: Vec<schema::RequiredCall> = missing
            .iter()
            .map(|a| schema::RequiredCall {
                drones: a
                    .drone
                    .clone()
                    .map_or_else(|| self.available.clone(), |d| vec![d]),
                action: "start_tracking",
                target: a.target.clone(),
            })
            .collect();
        let narrowed = match (whole, required.is_empty()) {
            _ if !self.aids.is_on(Aid::RepairGrammar) => None,
            (Some(whole), _) => {
                let calls: Vec<String> = whole
                    .iter()
                    .map(|r| format!("{} {}", r.drones.join("|"), r.action))
                    .collect();
                aids_fired.push((
                    Aid::RepairGrammar,
                    format!(
                        "the repair round's grammar allows only the plan {}",
                        calls.join(", ")
                    ),
                ));
                Some(schema::exactly(&self.schema, &whole))
            }
            (None, false) => {
                let targets: Vec<&str> = required.iter().map(|r| r.target.as_str()).collect();
                aids_fired.push((
                    Aid::RepairGrammar,
                    format!(
                        "the repair round's grammar opens the plan with start_tracking of {}",
                        targets.join(", ")
                    ),
                ));
                Some(schema::requiring(&self.schema, &required))
            }
            // An empty plan where no refusal is offered: the repair round's grammar needs a
            // call (`schema::non_empty`).
            (None, true)
                if reply.plan.is_empty()
                    && self.schema.pointer("/properties/refusal").is_none() =>
            {
                aids_fired.push((
                    Aid::RepairGrammar,
                    "the repair round's grammar needs at least one call".to_owned(),
                ));
                Some(schema::non_empty(&self.schema))
            }
            (None, true) => None,
        };
        rejections.extend(missing.iter().map(FollowAsked::missing_text));
        let doubts = self.changes_nothing(&reply.plan).into_iter().collect();
        PlanJudgement {
            reasoning: reply.reasoning.clone(),
            plan,
            refusal: reply.refusal_text().map(str::to_owned),
            rejections,
            narrowed,
            aids_fired,
            doubts,
        }
    }

    /// A plan none of whose calls would change its drone's state, said with why: a take-off of
    /// a drone in the air, a landing or hold of a drone on the ground, a stop_tracking of a
    /// drone not tracking. Adopted, it completes at once and the instruction is not carried out
    /// (the 1.5B default answered "find the suspect" with six take-offs of flying drones).
    fn changes_nothing(&self, plan: &[Call]) -> Option<String> {
        let mut said = Vec::new();
        for call in plan {
            let (_, mode) = self.modes.iter().find(|(d, _)| *d == call.drone)?;
            if !effect_holds(call.action, *mode) {
                return None;
            }
            said.push(format!("{call}: {} is {mode} already", call.drone));
        }
        (!said.is_empty()).then(|| {
            format!(
                "no call of the plan changes anything ({}): plan what the instruction asks for",
                said.join("; ")
            )
        })
    }

    /// What an empty plan without a refusal is told. A refusal is mentioned only where the
    /// schema offers one (not under `plan-only`: the 1.5B default, told to "say why in
    /// \"refusal\"" with no such field, sent the same empty plan back twice), and an instruction
    /// for the whole swarm names its drones with their modes: that reply's reason was "All
    /// drones are already flying" with all six on the ground.
    fn empty_plan_text(&self) -> String {
        let mut text = String::from("the plan is empty: list the calls the instruction needs");
        if let Some(available) = self.whole_swarm.then_some(&self.modes) {
            text.push_str(&format!(
                ", for every drone: {}",
                whole_swarm::with_modes(available)
            ));
        }
        if self.schema.pointer("/properties/refusal").is_some() {
            text.push_str(", or, if it cannot be carried out, say why in \"refusal\"");
        }
        text
    }

    /// One call: within the places allowed, for an available drone, naming real things.
    fn check_call(&self, call: &Call) -> Result<(), String> {
        if let Some(why) = self
            .scope
            .as_ref()
            .and_then(|s| grounding::off_scope(call, &self.places, s))
        {
            return Err(why);
        }
        if self.drones.contains(&call.drone) && !self.available.contains(&call.drone) {
            return Err(format!(
                "{} is unavailable; the drones available are: {}",
                call.drone,
                self.available.join(", ")
            ));
        }
        check_static(call, &self.scenario, &self.visible)
    }
}

/// The positions in `calls` of the first goto or start_tracking of each drone in `grounded`
/// whose plan has no take-off anywhere: such a call could never start.
pub(crate) fn missing_takeoffs(calls: &[Call], grounded: &[String]) -> Vec<usize> {
    let mut out: Vec<usize> = Vec::new();
    for (i, call) in calls.iter().enumerate() {
        let needs_air = matches!(call.action, ActionName::Goto | ActionName::StartTracking);
        let takes_off = |c: &Call| c.drone == call.drone && c.action == ActionName::ArmTakeoff;
        let first = !out.iter().any(|&j| calls[j].drone == call.drone);
        if needs_air && first && grounded.contains(&call.drone) && !calls.iter().any(takes_off) {
            out.push(i);
        }
    }
    out
}

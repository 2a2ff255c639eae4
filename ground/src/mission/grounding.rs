//! Which places a Coordinator plan may send drones to for one instruction.
//!
//! When the pilot names places ("find the dog in small_park"), the plan is about those: a goto
//! or start_tracking may name a place the instruction names, or one a pending task is still
//! headed for (the pilot's "everyone else keep searching" keeps them). Any other place is off
//! the instruction; the embedded 135M model sends drones to whatever its history mentions
//! (villa, again and again) unless its grammar forbids it. When the instruction names no place
//! ("find the dog, start from the most likely areas", "all drones take off"), nothing is limited
//! and choosing is the model's job. A point (`xyz`) is always allowed: "north of the
//! villa" names no landmark to go to.
//!
//! The scope fills the Coordinator's `target` enum, so a grammar-constrained model cannot leave
//! it, and the same rule checks each reply, so a server that ignores the schema gets the
//! rejection and a repair round.
//!
//! The same holds for following: when the pilot asks for a target to be followed ("bravo,
//! follow the van"), or a replan hands on a lost drone's `start_tracking(van)`, a plan that
//! tracks nothing is not about the instruction. The 135M model planned `goto(car_1)` and
//! `goto(van)` for "bravo, follow the van", and the tracking step waited for ever.
//! [`untracked`] names what is missing, and the reply goes back for a repair round.

use tacos_prompts::reply::{ActionName, Call};

/// The places a plan for this instruction may name, when the instruction limits them: `named`
/// (the places among `places` that the instruction names) plus `pending` (the places
/// unfinished tasks are headed for), in the order of `places`. `None` when the instruction
/// names no place: then nothing is limited here (the schema and the static checks still hold
/// the plan to real places).
pub fn places_in_scope(
    places: &[String],
    named: &[String],
    pending: &[String],
) -> Option<Vec<String>> {
    if !named.iter().any(|n| places.contains(n)) {
        return None;
    }
    Some(
        places
            .iter()
            .filter(|p| named.contains(p) || pending.contains(p))
            .cloned()
            .collect(),
    )
}

/// Why `call` leaves `scope`, if it does: only a goto or start_tracking's target among `places`
/// counts. Other actions ignore the field, which models fill with anything; a name that is no
/// place (a hidden target, a typo) is the static checks' business.
pub fn off_scope(call: &Call, places: &[String], scope: &[String]) -> Option<String> {
    if !matches!(call.action, ActionName::Goto | ActionName::StartTracking) {
        return None;
    }
    let target = call.target_name()?;
    let is_place = places.iter().any(|p| p == target);
    (is_place && !scope.iter().any(|p| p == target)).then(|| {
        format!(
            "{target} is neither named in the instruction nor in the pending plan; the places for this plan are: {}",
            scope.join(", ")
        )
    })
}

/// Word forms that ask for a target to be followed ("start_tracking" splits into "start" and
/// "tracking").
const FOLLOW_WORDS: &[&str] = &[
    "follow",
    "follows",
    "following",
    "track",
    "tracks",
    "tracking",
    "chase",
    "chases",
    "chasing",
    "pursue",
    "pursues",
    "pursuing",
    "tail",
    "tailing",
];

/// Words that turn a clause's following into its end ("stop following the van",
/// "stop_tracking(van)", "don't chase it").
const ENDING_WORDS: &[&str] = &[
    "stop", "stops", "stopping", "cease", "quit", "abandon", "release", "not", "don", "dont", "no",
    "never",
];

/// A target the instruction asks to be followed, and the drone named beside it, if one is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FollowAsked {
    pub target: String,
    pub drone: Option<String>,
}

/// The targets among `targets` that `instruction` asks to be followed: per clause (split at
/// `;`, `.`, `!`, `?` and line breaks), a follow word and a target's name, and no word that
/// ends following. The drone is the one among `drones` that the same clause names, when exactly
/// one is named.
pub fn follow_asked(instruction: &str, drones: &[String], targets: &[String]) -> Vec<FollowAsked> {
    let mut out: Vec<FollowAsked> = Vec::new();
    for clause in instruction.split([';', '.', '!', '?', '\n']) {
        // Letters only: "start_tracking(van)" gives "start", "tracking", "van".
        let words: Vec<String> = clause
            .split(|c: char| !c.is_alphabetic())
            .filter(|w| !w.is_empty())
            .map(str::to_lowercase)
            .collect();
        let has = |list: &[&str]| words.iter().any(|w| list.contains(&w.as_str()));
        if !has(FOLLOW_WORDS) || has(ENDING_WORDS) {
            continue;
        }
        let named_drones = tacos_prompts::render::named_in(clause, drones);
        let drone = match named_drones.as_slice() {
            [one] => Some(one.clone()),
            _ => None,
        };
        for target in tacos_prompts::render::named_in(clause, targets) {
            if !out.iter().any(|a| a.target == target) {
                out.push(FollowAsked {
                    target,
                    drone: drone.clone(),
                });
            }
        }
    }
    out
}

/// What a plan misses of `asked`: the asked targets that no call of `plan` starts tracking and
/// no drone follows already (`followed`).
pub fn untracked(asked: &[FollowAsked], plan: &[Call], followed: &[String]) -> Vec<FollowAsked> {
    asked
        .iter()
        .filter(|a| !followed.contains(&a.target))
        .filter(|a| {
            !plan.iter().any(|c| {
                c.action == ActionName::StartTracking && c.target_name() == Some(&a.target)
            })
        })
        .cloned()
        .collect()
}

impl FollowAsked {
    /// What a plan that misses this is told.
    pub fn missing_text(&self) -> String {
        let by = self.drone.as_deref().unwrap_or("one drone");
        format!(
            "the instruction asks to follow {t}, but no call of the plan starts tracking it: add start_tracking with target {t} for {by}",
            t = self.target
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn strings(v: &[&str]) -> Vec<String> {
        v.iter().map(|s| (*s).to_owned()).collect()
    }

    fn call(action: ActionName, target: &str) -> Call {
        Call {
            task: "T1".into(),
            drone: "alfa".into(),
            action,
            target: target.into(),
            xyz: None,
        }
    }

    #[test]
    fn named_places_and_pending_ones_make_the_scope() {
        let places = strings(&["villa", "small_park", "car_1", "van"]);
        // Drones are named too; they are not places.
        let named = strings(&["bravo", "van"]);
        assert_eq!(
            places_in_scope(&places, &named, &strings(&["car_1"])),
            Some(strings(&["car_1", "van"]))
        );
        assert_eq!(
            places_in_scope(&places, &strings(&["small_park"]), &[]),
            Some(strings(&["small_park"]))
        );
    }

    #[test]
    fn an_instruction_naming_no_place_limits_nothing() {
        let places = strings(&["villa", "small_park"]);
        assert_eq!(
            places_in_scope(&places, &strings(&["alfa"]), &strings(&["villa"])),
            None
        );
        assert_eq!(places_in_scope(&places, &[], &[]), None);
    }

    #[test]
    fn only_a_goto_or_tracking_target_can_leave_the_scope() {
        let places = strings(&["villa", "small_park", "van"]);
        let scope = strings(&["small_park"]);
        let off = |action, target| off_scope(&call(action, target), &places, &scope);
        let why = off(ActionName::Goto, "villa").expect("villa is off");
        assert!(why.contains("villa") && why.contains("small_park"), "{why}");
        assert!(off(ActionName::StartTracking, "van").is_some());
        assert_eq!(off(ActionName::Goto, "small_park"), None);
        assert_eq!(off(ActionName::Goto, "none"), None);
        assert_eq!(off(ActionName::ArmTakeoff, "villa"), None);
        assert_eq!(off(ActionName::Land, "villa"), None);
        // Not a place: a hidden target's name is for the static checks to judge.
        assert_eq!(off(ActionName::StartTracking, "suspect"), None);
    }

    #[test]
    fn a_clause_with_a_follow_word_and_a_target_asks_for_following() {
        let drones = strings(&["alfa", "bravo", "charlie"]);
        let targets = strings(&["van", "dog"]);
        let asked = |text| follow_asked(text, &drones, &targets);
        assert_eq!(
            asked("bravo, follow the van; everyone else keep searching"),
            vec![FollowAsked {
                target: "van".into(),
                drone: Some("bravo".into()),
            }]
        );
        // A replan naming a lost drone's tracking: the drone named is the lost one, kept as
        // named (the caller offers only available drones).
        assert_eq!(
            asked(
                "(automatic replan) bravo became unavailable: reassign its unfinished subtasks (T1 bravo start_tracking(van)) and keep the mission going"
            ),
            vec![FollowAsked {
                target: "van".into(),
                drone: Some("bravo".into()),
            }]
        );
        assert_eq!(
            asked("Chase the VAN with alfa or charlie"),
            vec![FollowAsked {
                target: "van".into(),
                drone: None,
            }]
        );
        // No follow word, an ending word, or no target: nothing asked.
        assert!(asked("alfa, go to the van").is_empty());
        assert!(asked("stop following the van").is_empty());
        assert!(asked("T2 alfa stop_tracking(van)").is_empty());
        assert!(asked("don't chase the van").is_empty());
        assert!(asked("follow me").is_empty());
        // Clauses are judged apart: the second one's "stop" does not cancel the first.
        assert_eq!(asked("alfa, track the dog. bravo, stop").len(), 1);
    }

    #[test]
    fn a_plan_that_tracks_nothing_asked_is_named() {
        let asked = vec![FollowAsked {
            target: "van".into(),
            drone: Some("bravo".into()),
        }];
        let goto = call(ActionName::Goto, "van");
        let track = call(ActionName::StartTracking, "van");
        let missing = untracked(&asked, std::slice::from_ref(&goto), &[]);
        assert_eq!(missing, asked);
        let text = missing[0].missing_text();
        assert!(
            text.contains("start_tracking") && text.contains("for bravo"),
            "{text}"
        );
        assert!(untracked(&asked, &[goto.clone(), track], &[]).is_empty());
        // A drone following the van already: nothing is missing.
        assert!(untracked(&asked, &[goto], &strings(&["van"])).is_empty());
    }
}

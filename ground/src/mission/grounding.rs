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
}

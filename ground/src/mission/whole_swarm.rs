//! An instruction for the whole swarm ("all drones take off", "everyone land", "split the
//! swarm …") is carried out by every available drone. The 1.5B default, asked "All drones take
//! off." with six drones on the ground, copied its three-drone example and planned three
//! take-offs, and the plan completed with three drones on the ground (issue 15). With the
//! `whole-swarm` aid on, such a plan goes back for a repair round naming the drones it leaves
//! out. English words decide what addresses the whole swarm, so this is an aid, not a rule.

use tacos_prompts::reply::{ActionName, Call};
use tacos_shared::DroneMode;

/// Words after which an instruction for the swarm leaves some drones out ("all drones except
/// alfa", "everyone but bravo"): the check is not made then.
const EXCEPTING_WORDS: &[&str] = &["except", "excluding", "but", "besides", "apart", "save"];

/// True when `instruction` addresses every drone: "all drones", "all the drones", "all of you",
/// "every drone", "each drone", "everyone", "everybody", or the swarm itself, with no word that
/// excepts some.
pub fn addresses_whole_swarm(instruction: &str) -> bool {
    let words: Vec<String> = instruction
        .split(|c: char| !c.is_alphabetic())
        .filter(|w| !w.is_empty())
        .map(str::to_lowercase)
        .collect();
    let has = |w: &str| words.iter().any(|x| x == w);
    if EXCEPTING_WORDS.iter().any(|w| has(w)) || instruction.to_lowercase().contains("other than") {
        return false;
    }
    let after = |i: usize| words.get(i + 1).map(String::as_str);
    let after_the = |i: usize| match after(i) {
        Some("the") => words.get(i + 2).map(String::as_str),
        other => other,
    };
    words.iter().enumerate().any(|(i, w)| match w.as_str() {
        "everyone" | "everybody" | "swarm" => true,
        "all" => matches!(after_the(i), Some("drones" | "of" | "you")),
        "every" | "each" => after(i) == Some("drone"),
        _ => false,
    })
}

/// The drones among `available` (with their mode when the plan was asked for) that a plan for
/// the whole swarm leaves out: no call of `plan` names them, and some action of the plan would
/// change their state (a drone already flying needs no take-off, one on the ground no landing).
pub fn left_out(plan: &[Call], available: &[(String, DroneMode)]) -> Vec<(String, DroneMode)> {
    if plan.is_empty() {
        return Vec::new();
    }
    available
        .iter()
        .filter(|(drone, _)| !plan.iter().any(|c| &c.drone == drone))
        .filter(|(_, mode)| {
            plan.iter()
                .any(|c| !crate::mission::core::effect_holds(c.action, *mode))
        })
        .cloned()
        .collect()
}

/// The one action of `plan` when every call is the same action without a target (a take-off
/// for all, a landing for all): what a drone left out is to do, too.
pub fn one_action_without_target(plan: &[Call]) -> Option<ActionName> {
    let first = plan.first()?.action;
    (first.takes_no_target() && plan.iter().all(|c| c.action == first)).then_some(first)
}

/// The drones among `available` whose state `action` would change: those a plan of that action
/// for the whole swarm must name.
pub fn needing(action: ActionName, available: &[(String, DroneMode)]) -> Vec<String> {
    available
        .iter()
        .filter(|(_, mode)| !crate::mission::core::effect_holds(action, *mode))
        .map(|(drone, _)| drone.clone())
        .collect()
}

/// Drones with their modes, as a repair round names them: "alfa (idle), bravo (flying)".
pub fn with_modes(drones: &[(String, DroneMode)]) -> String {
    let named: Vec<String> = drones
        .iter()
        .map(|(drone, mode)| format!("{drone} ({mode})"))
        .collect();
    named.join(", ")
}

/// What a plan that leaves `left` out is told.
pub fn left_out_text(left: &[(String, DroneMode)]) -> String {
    format!(
        "the instruction is for every drone, but the plan gives {} no task: add {} part",
        with_modes(left),
        if left.len() == 1 { "its" } else { "each one's" }
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn take_off(drone: &str) -> Call {
        Call {
            task: "T1".into(),
            drone: drone.into(),
            action: ActionName::ArmTakeoff,
            target: "none".into(),
            xyz: None,
        }
    }

    #[test]
    fn the_words_that_address_every_drone() {
        for yes in [
            "All drones take off.",
            "all the drones, land now",
            "all of you go to car_3",
            "every drone hold",
            "Everyone up!",
            "split the swarm, send one group north and have the other surround the van",
        ] {
            assert!(addresses_whole_swarm(yes), "{yes}");
        }
        for no in [
            "alfa, take off",
            "check all the cars",
            "all drones except alfa take off",
            "everyone but bravo land",
            "every car is a suspect",
            "all drones other than charlie hold",
        ] {
            assert!(!addresses_whole_swarm(no), "{no}");
        }
    }

    #[test]
    fn a_plan_for_every_drone_leaves_out_only_those_whose_state_it_would_not_change() {
        let available = vec![
            ("alfa".to_owned(), DroneMode::Idle),
            ("bravo".to_owned(), DroneMode::Flying),
            ("charlie".to_owned(), DroneMode::Idle),
            ("delta".to_owned(), DroneMode::Idle),
        ];
        // The 1.5B model's copy of its three-drone example.
        let plan = vec![take_off("alfa"), take_off("bravo"), take_off("charlie")];
        assert_eq!(
            left_out(&plan, &available),
            [("delta".into(), DroneMode::Idle)]
        );
        // bravo is flying: a take-off plan need not name it.
        let plan = vec![take_off("alfa"), take_off("charlie"), take_off("delta")];
        assert!(left_out(&plan, &available).is_empty());
        assert!(left_out(&[], &available).is_empty());
        let left = vec![
            ("delta".to_owned(), DroneMode::Idle),
            ("echo".to_owned(), DroneMode::Idle),
        ];
        assert_eq!(
            left_out_text(&left),
            "the instruction is for every drone, but the plan gives delta (idle), echo (idle) no \
             task: add each one's part"
        );
    }
}

//! The aids that carry a small model, as named switches.
//!
//! The engine grew rules that exist because a small model needs them; a capable model can be
//! hurt by them (a plan narrowed to the places the pilot named, a take-off the engine adds on its
//! own). Each is a switch here; the mission log's start record says which were on, and every time
//! one changes what the engine does it writes an [`Record::AidFired`](super::log::Record) naming
//! it. Where an aid stands in for a principled rule, the rule is what runs when it is off (an
//! implied take-off off: the Coordinator's plan is refused, naming the missing take-off).
//!
//! The first four, `whole-swarm` and `replan-keeps-pending` act on the Coordinator only, so `mnl` never meets them; compare the modes with
//! the same preset and say which.

use serde::{Deserialize, Serialize};
use std::fmt;

/// One aid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Aid {
    /// The Coordinator's grammar offers only the places the instruction or the pending plan
    /// names, and its plan may name no other (`grounding::places_in_scope`).
    PlaceScope,
    /// English follow-words ("follow", "track", "chase" …) next to a target's name make the
    /// plan track that target (`grounding::follow_asked`).
    FollowWords,
    /// A repair round after a missed follow-up opens the plan's grammar with the missing
    /// start_tracking (`prefixItems`, `schema::requiring`; llama.cpp's server ignores that
    /// prefix, see `schema::exactly`); after a plan of one action for the whole swarm that left
    /// drones out (`whole-swarm`), the grammar is that action for each drone it would change;
    /// after an empty plan where no refusal is offered, it needs a call (`schema::non_empty`).
    RepairGrammar,
    /// A take-off is added before the first goto or start_tracking of a grounded drone whose
    /// plan never takes it off. Off: that call is refused, naming the missing take-off.
    ImpliedTakeoffs,
    /// A plan holds at most three calls per drone (the grammar's `maxItems`). Off: up to the
    /// grammar's overall bound of 40 calls.
    PlanLengthCap,
    /// The rejected reply is echoed back in a repair round without its repeated items. Off:
    /// echoed as the model wrote it.
    CompactRepairEcho,
    /// A repair round that the backend cannot answer leaves in force what passed the checks in
    /// the round before. Off: the call fails with the backend's error.
    KeepPartialPlan,
    /// The Coordinator is offered no refusal: its schema has no "refusal" and its prompt no rule
    /// or example for one. The 1.5B default, offered one, declined "all drones take off" with
    /// every drone on the ground, and "charlie, search the business_district" on a map that has
    /// it. Off: a reply may decline with a reason for the pilot instead of planning.
    PlanOnly,
    /// An instruction for the whole swarm (English words: "all drones", "everyone", "the
    /// swarm" …) needs a task for every available drone whose state the plan would change; a
    /// plan that leaves some out goes back naming them (`whole_swarm`). Off: the plan is taken
    /// as the model wrote it.
    WholeSwarm,
    /// An automatic replan (a drone lost or joined) keeps the pending tasks of the drones still
    /// available that its plan leaves out, before the plan's own calls
    /// (`adopt::with_pending_kept`): nobody cancelled them, and the 1.5B default, asked to hand
    /// on a lost drone's searches, planned those alone and dropped the other drones' (the two
    /// failures of ten Task 1 runs once the cars were named). Off: the plan is taken as the
    /// model wrote it.
    ReplanKeepsPending,
}

impl Aid {
    pub const ALL: [Aid; 10] = [
        Aid::PlaceScope,
        Aid::FollowWords,
        Aid::RepairGrammar,
        Aid::ImpliedTakeoffs,
        Aid::PlanLengthCap,
        Aid::CompactRepairEcho,
        Aid::KeepPartialPlan,
        Aid::PlanOnly,
        Aid::WholeSwarm,
        Aid::ReplanKeepsPending,
    ];

    /// The name on the command line and in the log.
    pub fn name(self) -> &'static str {
        match self {
            Aid::PlaceScope => "place-scope",
            Aid::FollowWords => "follow-words",
            Aid::RepairGrammar => "repair-grammar",
            Aid::ImpliedTakeoffs => "implied-takeoffs",
            Aid::PlanLengthCap => "plan-length-cap",
            Aid::CompactRepairEcho => "compact-repair-echo",
            Aid::KeepPartialPlan => "keep-partial-plan",
            Aid::PlanOnly => "plan-only",
            Aid::WholeSwarm => "whole-swarm",
            Aid::ReplanKeepsPending => "replan-keeps-pending",
        }
    }

    const fn bit(self) -> u16 {
        1 << (self as u16)
    }
}

impl fmt::Display for Aid {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Which aids are on. `small` (all on) is the preset the 135M embedded model was measured with
/// and the default; `none` turns them all off.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct ModelAids {
    on: u16,
}

impl ModelAids {
    /// Every aid on: what the 135M embedded model needs.
    pub const fn small() -> ModelAids {
        let mut on = 0;
        let mut i = 0;
        while i < Aid::ALL.len() {
            on |= Aid::ALL[i].bit();
            i += 1;
        }
        ModelAids { on }
    }

    /// No aid: the principled rules only.
    pub const fn none() -> ModelAids {
        ModelAids { on: 0 }
    }

    pub fn is_on(self, aid: Aid) -> bool {
        self.on & aid.bit() != 0
    }

    pub fn with(self, aid: Aid, on: bool) -> ModelAids {
        ModelAids {
            on: if on {
                self.on | aid.bit()
            } else {
                self.on & !aid.bit()
            },
        }
    }

    /// The aids that are on, in [`Aid::ALL`]'s order.
    pub fn enabled(self) -> Vec<Aid> {
        Aid::ALL.into_iter().filter(|a| self.is_on(*a)).collect()
    }

    /// The preset's name when this is one, else the aids that are on.
    pub fn describe(self) -> String {
        if self == ModelAids::small() {
            "small".into()
        } else if self == ModelAids::none() {
            "none".into()
        } else {
            let names: Vec<&str> = self.enabled().into_iter().map(Aid::name).collect();
            names.join(",")
        }
    }
}

impl Default for ModelAids {
    fn default() -> Self {
        ModelAids::small()
    }
}

impl fmt::Debug for ModelAids {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ModelAids({})", self.describe())
    }
}

impl fmt::Display for ModelAids {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.describe())
    }
}

/// `small`, `none`, or a comma-separated list of aid names: those on, the rest off; a name
/// prefixed with `-` after a preset turns that one off (`small,-implied-takeoffs`).
impl std::str::FromStr for ModelAids {
    type Err = String;

    fn from_str(text: &str) -> Result<ModelAids, String> {
        let mut aids = ModelAids::none();
        for word in text.split(',').map(str::trim).filter(|w| !w.is_empty()) {
            let (on, name) = match word.strip_prefix('-') {
                Some(name) => (false, name),
                None => (true, word),
            };
            aids = match name {
                "small" if on => ModelAids::small(),
                "none" if on => ModelAids::none(),
                _ => {
                    let aid = Aid::ALL
                        .into_iter()
                        .find(|a| a.name() == name)
                        .ok_or_else(|| {
                            let names: Vec<&str> = Aid::ALL.into_iter().map(Aid::name).collect();
                            format!(
                                "unknown aid {name:?}: give small, none, or aids among {}",
                                names.join(", ")
                            )
                        })?;
                    aids.with(aid, on)
                }
            };
        }
        Ok(aids)
    }
}

/// In the log: the aids that are on, by name, so a reader needs no bit layout.
impl Serialize for ModelAids {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        self.enabled().serialize(s)
    }
}

impl<'de> Deserialize<'de> for ModelAids {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let on = Vec::<Aid>::deserialize(d)?;
        Ok(on
            .into_iter()
            .fold(ModelAids::none(), |aids, aid| aids.with(aid, true)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_and_lists_parse_and_describe_themselves() {
        assert_eq!("small".parse(), Ok(ModelAids::small()));
        assert_eq!("none".parse(), Ok(ModelAids::none()));
        let some: ModelAids = "implied-takeoffs, keep-partial-plan"
            .parse()
            .expect("parses");
        assert_eq!(some.enabled(), [Aid::ImpliedTakeoffs, Aid::KeepPartialPlan]);
        assert_eq!(some.describe(), "implied-takeoffs,keep-partial-plan");
        let all_but: ModelAids = "small,-place-scope".parse().expect("parses");
        assert!(!all_but.is_on(Aid::PlaceScope));
        assert_eq!(all_but.enabled().len(), Aid::ALL.len() - 1);
        assert_eq!(ModelAids::small().enabled(), Aid::ALL);
        assert!(ModelAids::none().enabled().is_empty());
        let err = "small,scope".parse::<ModelAids>().expect_err("unknown");
        assert!(err.contains("place-scope"), "{err}");
        assert!("-small".parse::<ModelAids>().is_err());
    }

    #[test]
    fn the_log_names_the_aids_that_were_on() {
        let some = ModelAids::none().with(Aid::FollowWords, true);
        let json = serde_json::to_string(&some).expect("serialises");
        assert_eq!(json, r#"["follow-words"]"#);
        assert_eq!(serde_json::from_str::<ModelAids>(&json).ok(), Some(some));
        let small = serde_json::to_string(&ModelAids::small()).expect("serialises");
        assert_eq!(
            serde_json::from_str::<ModelAids>(&small).ok(),
            Some(ModelAids::small())
        );
    }
}

//! The driver's shell around the core (`mission::core`): it takes one
//! snapshot of the swarm per step, hands it to the core, and carries out the effects.

use super::{Awaited, Mission};
use crate::link::GroundLink;
use crate::mission::core::{Ask, Effect, Snapshot};
use crate::mission::log::Record;
use crate::mission::untrusted;
use tacos_shared::messages::TargetObservation;

/// The link's view of the world now, with the targets seen (`Mission::visible_targets`).
pub(super) fn snapshot_of(link: &GroundLink, targets: Vec<TargetObservation>) -> Snapshot {
    let swarm = link.view().clone();
    Snapshot {
        swarm,
        targets,
        now: link.clock().instant(),
        ground: link.epoch(),
    }
}

impl Mission {
    /// The step's view of the world: the swarm, the targets seen, the time, this ground's epoch.
    pub(super) fn snapshot(&self) -> Snapshot {
        snapshot_of(&self.link, self.visible_targets())
    }

    /// The targets seen now that the scenario has: a name from the network reaches a prompt
    /// only when it is one of the map's (`untrusted`).
    pub(super) fn visible_targets(&self) -> Vec<TargetObservation> {
        let seen = self.targets.borrow();
        let known = untrusted::known_targets(&seen, self.gate.scenario());
        let unknown = seen.len() - known.len();
        if unknown > 0 {
            tracing::debug!(
                unknown,
                "observations of targets the map does not have left out"
            );
        }
        known
    }

    /// Carries out the core's effects, in order, once the core kept its own (`Core::absorb`).
    pub(super) fn apply(&mut self, effects: Vec<Effect>) {
        for effect in self.core.absorb(effects) {
            match effect {
                Effect::Note(Record::AidFired { aid, detail }) => self.log.aid_fired(aid, detail),
                Effect::Note(record) => self.log.note(record),
                Effect::Tell(update) => self.tell(update),
                Effect::Refused { layer, refusal, by } => super::caller::refused(
                    &self.log,
                    &self.updates,
                    &self.stats,
                    layer,
                    refusal,
                    by,
                ),
                Effect::DropCall { layer, by } => self.abort_call(layer, by),
                Effect::PlanCycles(cycles) => self.stats.update(|s| s.cycles_per_plan.push(cycles)),
                Effect::Direct { text, directive } => {
                    self.awaited.push_back(Awaited::Direct { text, directive })
                }
                Effect::InstructionBegun(text) => self.commands.begin_instruction(&text),
                Effect::Send { checked, task } => {
                    self.awaited.push_back(Awaited::Send { checked, task })
                }
                Effect::Ask(Ask::Coordinator(ask)) => self.start_coordinator_call(*ask),
                Effect::Ask(Ask::Cycle(start)) => self.start_cycle_call(start),
                Effect::Coordinate(work) => self.awaited.push_back(Awaited::Coordinate(work)),
                Effect::CycleCounted => self.stats.update(|s| s.cycles_total += 1),
                // Kept by the core in `absorb`: they never come out of it.
                Effect::Remember(_) | Effect::WorkReplaced | Effect::Replan(_) => {}
            }
        }
    }
}

//! The engine's shell around the core's plan bookkeeping (`mission::core`): it takes one
//! snapshot of the swarm per step, hands it to the core, and carries out the effects.

use super::Mission;
use crate::link::GroundLink;
use crate::mission::core::{self, Coordination, Effect, Rules, Snapshot, Start};
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

    /// Carries out the core's effects, in order.
    pub(super) fn apply(&mut self, effects: Vec<Effect>) {
        for effect in effects {
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
                Effect::Remember(entry) => self.remember(entry),
                Effect::WorkReplaced => self.calls.work_replaced(),
                Effect::DropCall { layer, by } => self.abort_call(layer, by),
                Effect::PlanCycles(cycles) => self.stats.update(|s| s.cycles_per_plan.push(cycles)),
                Effect::Replan(instruction) => {
                    self.want_coordination(Coordination::Replan(instruction))
                }
            }
        }
    }

    /// Looks for finished actions; true when any task changed state.
    pub(super) fn poll_outcomes(&mut self) -> bool {
        let snap = self.snapshot();
        let rules = Rules {
            gate: &self.gate,
            mode: self.cfg.mode,
            max_task_failures: self.cfg.max_task_failures,
        };
        let (effects, changed) = core::poll(&mut self.book, &snap, &rules);
        self.apply(effects);
        changed
    }

    /// Runs `f` with the checks of whether a call can start, on one snapshot of the swarm.
    pub(super) fn with_start<R>(&self, f: impl FnOnce(&Start<'_>) -> R) -> R {
        let snap = self.snapshot();
        f(&Start::new(&snap, &self.gate, &self.book))
    }

    /// Gives the plan up when it has been stuck too long (`core::give_up_if_stuck`).
    pub(super) fn give_up_if_stuck(&mut self) {
        let snap = self.snapshot();
        let effects = core::give_up_if_stuck(&mut self.book, &snap, &self.gate);
        self.apply(effects);
    }

    /// Ends `plan` `how` ("complete", or why not).
    pub(super) fn finish_plan(&mut self, plan: core::ActivePlan, how: &str) {
        self.apply(core::plan_ended(plan, how));
    }

    /// The monolithic model's work is complete when its claim stands and nothing it issued runs.
    pub(super) fn judge_monolithic(&mut self) {
        let effects = core::judge_monolithic(&mut self.book.mnl);
        self.apply(effects);
    }
}

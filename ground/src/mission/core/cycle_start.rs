//! Starting a Supervisor (or monolithic) cycle that is due: within the cycles a plan may take,
//! and only with a decision to make. The request is built on the step's one snapshot
//! (`cycle_ask`); when nothing of the plan can start, a plan stuck too long is given up
//! (`outcomes::give_up_if_stuck`). A cycle that starts is the calls' and the cycle's state at
//! once (`CallQueue::started`, `Core::cycle_started`): the driver runs its call.

use super::cycle_ask::{CycleRequest, monolithic_ask, supervisor_ask};
use super::cycle_reply::CycleKind;
use super::effect::Effect;
use super::outcomes::{give_up_if_stuck, plan_ended};
use super::snapshot::Snapshot;
use super::state::Core;
use crate::mission::config::Mode;
use crate::mission::log::Record;
use crate::mission::report::MissionUpdate;
use crate::safety::SafetyGate;

/// A cycle to ask its model for: which layer and kind, and the request.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct CycleStart {
    pub(crate) layer: &'static str,
    pub(crate) kind: CycleKind,
    pub(crate) request: CycleRequest,
}

impl Core {
    /// The cycle to start now, if there is a decision to make; its call counts as started.
    pub(crate) fn start_cycle(
        &mut self,
        snap: &Snapshot,
        gate: &SafetyGate,
    ) -> (Option<CycleStart>, Vec<Effect>) {
        let mut effects = Vec::new();
        if !self.cycle_allowed(&mut effects) {
            return (None, effects);
        }
        let start = match self.mode {
            Mode::Tacos | Mode::Wor => {
                match supervisor_ask(&self.book, snap, gate, &self.events, self.mode) {
                    Some(request) => {
                        if let Some(plan) = self.book.plan.as_mut() {
                            plan.stuck_since = None;
                        }
                        CycleStart {
                            layer: "supervisor",
                            kind: CycleKind::Supervisor,
                            request,
                        }
                    }
                    None => {
                        // Nothing can start: wait for the swarm (an outcome, a membership change
                        // or the cycle timeout wakes us again), unless stuck too long.
                        effects.extend(give_up_if_stuck(&mut self.book, snap, gate));
                        return (None, effects);
                    }
                }
            }
            Mode::Mnl => {
                // As for the Supervisor: when no drone can take an action, there is nothing
                // to decide.
                let asked = monolithic_ask(&self.book, snap, gate.scenario(), &self.events);
                let Some((request, offered)) = asked else {
                    return (None, effects);
                };
                CycleStart {
                    layer: "monolithic",
                    kind: CycleKind::Monolithic { offered },
                    request,
                }
            }
        };
        self.calls.started(start.layer);
        self.cycle_started(start.kind);
        (Some(start), effects)
    }

    /// Whether a cycle may be asked for: not when the monolithic model claimed its work done
    /// (its outcomes are awaited), nor past the cycles a plan may take, which ends the work
    /// with an error for the pilot.
    pub(crate) fn cycle_allowed(&mut self, effects: &mut Vec<Effect>) -> bool {
        let max = self.bounds.max_cycles_per_plan;
        match self.mode {
            Mode::Tacos | Mode::Wor => {
                let Some(plan) = self.book.plan.as_ref() else {
                    return false;
                };
                if plan.cycles < max {
                    return true;
                }
                if let Some(plan) = self.book.plan.take() {
                    effects.extend(plan_ended(plan, "abandoned after too many cycles"));
                    effects.push(Effect::Tell(MissionUpdate::Error(format!(
                        "the plan was not complete after {max} Supervisor cycles"
                    ))));
                }
                false
            }
            Mode::Mnl => {
                let mnl = &mut self.book.mnl;
                if mnl.claimed_done {
                    return false;
                }
                if mnl.cycles < max {
                    return true;
                }
                mnl.active = false;
                let text = format!(
                    "the monolithic model did not carry out the instructions in {} cycles",
                    mnl.cycles
                );
                effects.push(Effect::Note(Record::Event { text: text.clone() }));
                effects.push(Effect::Tell(MissionUpdate::Error(text)));
                false
            }
        }
    }
}

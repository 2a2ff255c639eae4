//! Which model call runs next and which one a newer event overtakes. One call is in flight at a
//! time; work for the Coordinator that comes meanwhile (a newer instruction, an automatic
//! replan) waits in order, and drops a Supervisor (or monolithic) call in flight, whose reply
//! would act on the plan before it. A direct command drops the call in flight and everything
//! waiting. A cycle's reply is used only if the models' work has not been replaced since it was
//! asked (the work epoch). The engine runs the calls (`driver::in_flight`); this decides.

use super::effect::Effect;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, Overtaken};
use std::collections::VecDeque;

/// Work waiting for the Coordinator, in the order it came.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Coordination {
    /// The pilot's instruction (in the history already).
    Pilot(String),
    /// An automatic replan after a membership change, as its instruction.
    Replan(String),
}

/// The next call to start.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum NextCall {
    Coordinate(Coordination),
    /// A Supervisor (or monolithic) cycle.
    Cycle,
}

/// The calls' schedule: the layer whose call is in flight, the Coordinator's queue, whether a
/// cycle is due, and the work epoch.
#[derive(Debug, Default, Clone, PartialEq)]
pub(crate) struct CallQueue {
    in_flight: Option<&'static str>,
    queued: VecDeque<Coordination>,
    cycle_due: bool,
    /// Bumped whenever the models' work is replaced or ends (a plan adopted or finished, a
    /// direct command, a monolithic instruction): a cycle's reply from before is not used.
    epoch: u64,
}

impl CallQueue {
    /// The work epoch now (a cycle call carries the one it was asked in).
    pub(crate) fn epoch(&self) -> u64 {
        self.epoch
    }

    /// Whether a reply asked in `epoch` is still for the work in force.
    pub(crate) fn is_current(&self, epoch: u64) -> bool {
        epoch == self.epoch
    }

    /// The models' work was replaced or ended.
    pub(crate) fn work_replaced(&mut self) {
        self.epoch += 1;
    }

    /// A cycle is due once no call is in flight (when `due`).
    pub(crate) fn cycle_due(&mut self, due: bool) {
        self.cycle_due |= due;
    }

    /// A cycle is due, or not, whatever was due before (a new plan: its first cycle at once).
    pub(crate) fn set_cycle_due(&mut self, due: bool) {
        self.cycle_due = due;
    }

    /// The layer whose call is in flight, if one is (the tests' driver asks).
    #[cfg(test)]
    pub(crate) fn in_flight(&self) -> Option<&'static str> {
        self.in_flight
    }

    /// The call of `layer` was started.
    pub(crate) fn started(&mut self, layer: &'static str) {
        self.in_flight = Some(layer);
    }

    /// The call in flight answered (or ended): its layer.
    pub(crate) fn answered(&mut self) -> Option<&'static str> {
        self.in_flight.take()
    }

    /// Work for the Coordinator, queued behind what waits already; a cycle call in flight is
    /// for the plan this work will change, and is dropped.
    pub(crate) fn want(&mut self, work: Coordination) -> Vec<Effect> {
        let effects = match self.in_flight {
            Some(layer) if layer != "coordinator" => self.drop_call(Overtaken::NewerWork),
            _ => Vec::new(),
        };
        self.queued.push_back(work);
        effects
    }

    /// Drops the call in flight, if any: the engine aborts it and never uses its reply.
    pub(crate) fn drop_call(&mut self, by: Overtaken) -> Vec<Effect> {
        let Some(layer) = self.in_flight.take() else {
            return Vec::new();
        };
        vec![
            Effect::Note(Record::Event {
                text: format!("the {layer}'s call in flight was dropped, overtaken by {by}"),
            }),
            Effect::DropCall { layer, by },
        ]
    }

    /// A direct command came: the call in flight is dropped, and whatever waited for the
    /// Coordinator was typed (or raised) before the command, which overrides it: an instruction
    /// queued behind `land all` must not take the drones up again. No cycle is due and the
    /// work is replaced.
    pub(crate) fn overridden(&mut self) -> Vec<Effect> {
        let mut effects = self.drop_call(Overtaken::DirectCommand);
        for work in std::mem::take(&mut self.queued) {
            let text = match work {
                Coordination::Pilot(line) => {
                    format!("instruction {line:?} dropped: a direct command came after it")
                }
                Coordination::Replan(why) => {
                    format!("replan dropped ({why}): a direct command ended the plan")
                }
            };
            effects.extend(Effect::told(EventTopic::PlanEnded, text));
        }
        self.epoch += 1;
        self.cycle_due = false;
        effects
    }

    /// Whether a call would start now (`next` hands one out).
    pub(crate) fn has_next(&self, busy: bool) -> bool {
        self.in_flight.is_none() && (!self.queued.is_empty() || (self.cycle_due && busy))
    }

    /// The call to start now, if any: with none in flight, the Coordinator's next work, or else
    /// a cycle when one is due and the models have work (`busy`).
    pub(crate) fn next(&mut self, busy: bool) -> Option<NextCall> {
        if !self.has_next(busy) {
            return None;
        }
        if let Some(work) = self.queued.pop_front() {
            return Some(NextCall::Coordinate(work));
        }
        self.cycle_due = false;
        Some(NextCall::Cycle)
    }
}

//! Starting the next model call, as two inputs: `Input::CallDue` (no call is in flight: the
//! next work waiting for the Coordinator, or a cycle when one is due — `CallQueue::next`) and
//! `Input::Coordinate` (the Coordinator's request built on a snapshot the driver took once a
//! drone was heard). Each hands back the call to run as `Effect::Ask`; the call counts as
//! started here, and its reply (or its abnormal end, `Input::CallLost`) ends it.

use super::calls::{Coordination, NextCall};
use super::coordinator::{CoordinatorAsk, CoordinatorContext, coordinator_ask};
use super::cycle_start::CycleStart;
use super::effect::Effect;
use super::snapshot::Snapshot;
use super::state::Core;
use crate::mission::report::MissionUpdate;
use crate::safety::SafetyGate;

/// A model call for the driver to run beside the mission; its reply comes back as
/// `Input::CoordinatorReply` or `Input::CycleReply`.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Ask {
    /// Boxed: the request with its checks is several times the size of a cycle's.
    Coordinator(Box<CoordinatorAsk>),
    Cycle(CycleStart),
}

impl Core {
    /// No call is in flight: a cycle that is due starts on this step's snapshot; work for the
    /// Coordinator waits for a snapshot with a drone heard (`Effect::Coordinate`).
    pub(super) fn call_due(&mut self, snap: &Snapshot, gate: &SafetyGate) -> Vec<Effect> {
        match self.next_call(snap.now) {
            None => Vec::new(),
            Some(NextCall::Coordinate(work)) => vec![Effect::Coordinate(work)],
            Some(NextCall::Cycle) => {
                let (start, mut effects) = self.start_cycle(snap, gate);
                effects.extend(start.map(|start| Effect::Ask(Ask::Cycle(start))));
                effects
            }
        }
    }

    /// The Coordinator's request for `work` on `snap`; when none can be made (no drone is
    /// available) the pilot is told why, and the next work is due.
    pub(super) fn coordinate(
        &mut self,
        work: &Coordination,
        snap: &Snapshot,
        gate: &SafetyGate,
    ) -> Vec<Effect> {
        let context = CoordinatorContext {
            snap,
            scenario: gate.scenario(),
            book: &self.book,
            history: &self.history,
            events: &self.events,
            aids: self.aids,
        };
        let mut effects = Vec::new();
        match coordinator_ask(work, &context, &mut effects) {
            Ok(ask) => {
                self.calls.started("coordinator");
                self.replan_in_flight = matches!(work, Coordination::Replan(_));
                effects.push(Effect::Ask(Ask::Coordinator(Box::new(ask))));
            }
            Err(e) => effects.push(Effect::Tell(MissionUpdate::Error(e.to_string()))),
        }
        effects
    }

    /// The call in flight of `layer` ended without a reply (its task failed): told, and the
    /// next call may start.
    pub(super) fn call_lost(&mut self, layer: &str, reason: &str) -> Vec<Effect> {
        self.calls.answered();
        vec![Effect::Tell(MissionUpdate::Error(format!(
            "the {layer}'s call ended abnormally: {reason}"
        )))]
    }
}

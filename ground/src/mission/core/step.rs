//! The core fed one input at a time, each with the step's one `Snapshot`: what the engine hears
//! (a pilot line, a membership change, a world event, a tick, a direct command carried out, a
//! Coordinator's checked reply, a cycle's calls and reply, a send's result, the session's end)
//! goes in, and the effects come back with the ones that only change the core already absorbed.

use super::calls::Coordination;
use super::cycle_reply::CycleAnswer;
use super::effect::Effect;
use super::membership::membership_changed;
use super::outcomes::{Rules, plan_ended, poll};
use super::snapshot::Snapshot;
use super::state::Core;
use super::world::world_event;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionError, Overtaken};
use crate::safety::{CheckedAction, SafetyGate};
use crate::swarm::{SwarmChange, membership_diff};
use std::time::Duration;
use tacos_prompts::Call;
use tacos_shared::messages::WorldEvent;

/// The Coordinator's checked reply: its reasoning, the calls that passed, and its refusal.
pub(crate) type CoordinatorAnswer = Result<(String, Vec<Call>, Option<String>), MissionError>;

/// What the engine hands the core.
#[derive(Debug)]
pub(crate) enum Input {
    /// The mission starts: the snapshot's drones are the ones present.
    Started,
    /// A line from the pilot: a direct command, an answer to a held plan, or an instruction.
    Pilot(String),
    Membership(SwarmChange),
    /// Membership changes went by unseen (a lagging channel): the snapshot says where they led.
    MembershipMissed,
    World(WorldEvent),
    /// Time passed: outcomes are looked for, and a cycle is due after the cycle timeout.
    Tick,
    /// A direct command was carried out: the models' work ends.
    Overridden,
    /// The Coordinator answered the call for `instruction`, asked with `grounded` on the ground.
    CoordinatorReply {
        instruction: String,
        grounded: Vec<String>,
        answer: CoordinatorAnswer,
    },
    /// A call of the cycle in flight passed while its reply is still being written.
    EarlyCall {
        call: Call,
        checked: CheckedAction,
        /// How long after the call started it was complete.
        after: Duration,
    },
    /// The cycle call in flight answered.
    CycleReply(CycleAnswer),
    /// The send the core asked for last (`Effect::Send`) went, with its sequence number, or
    /// failed.
    Sent(Result<u64, MissionError>),
    /// No model call is in flight: the next one starts if one is due (`Effect::Ask`).
    CallDue,
    /// The Coordinator's request for this work, on this step's snapshot.
    Coordinate(Coordination),
    /// The model call in flight of `layer` ended without a reply (its task failed).
    CallLost {
        layer: &'static str,
        reason: String,
    },
    /// The pilot closed the session.
    Closed,
}

impl Core {
    /// Takes `input` in, seen on `snap`; the effects are for the engine to carry out in order.
    pub(crate) fn step(&mut self, input: Input, snap: &Snapshot, gate: &SafetyGate) -> Vec<Effect> {
        let effects = match input {
            Input::Started => {
                self.present = snap.swarm.present_ids();
                self.last_cycle = Some(snap.now);
                Vec::new()
            }
            Input::Pilot(text) => {
                let effects = self.pilot(&text, snap, gate);
                self.calls.cycle_due(self.busy());
                effects
            }
            Input::Membership(change) => {
                let effects = self.membership(change, snap);
                self.calls.cycle_due(self.busy());
                effects
            }
            Input::MembershipMissed => {
                let now_present = snap.swarm.present_ids();
                let mut effects = Vec::new();
                for change in membership_diff(&self.present, &now_present) {
                    effects.extend(self.membership(change, snap));
                }
                self.calls.cycle_due(self.busy());
                effects
            }
            Input::World(event) => {
                let (taken, effects) = world_event(
                    event,
                    gate.scenario(),
                    self.mode,
                    &mut self.book,
                    &mut self.events,
                );
                self.calls.cycle_due(taken && self.busy());
                effects
            }
            Input::Tick => self.tick(snap, gate),
            Input::Overridden => self.overridden(),
            Input::CoordinatorReply {
                instruction,
                grounded,
                answer,
            } => {
                self.calls.answered();
                let effects = self.coordinator_answered(instruction, grounded, answer, snap, gate);
                // A new plan: its first cycle at once.
                self.calls.set_cycle_due(self.busy());
                effects
            }
            Input::EarlyCall {
                call,
                checked,
                after,
            } => self.early_call(call, &checked, after, snap, gate),
            Input::CycleReply(answer) => {
                self.calls.answered();
                self.cycle_answered(answer, snap, gate)
            }
            Input::Sent(result) => self.sent(result, snap, gate),
            Input::CallDue => self.call_due(snap, gate),
            Input::Coordinate(work) => self.coordinate(&work, snap, gate),
            Input::CallLost { layer, reason } => self.call_lost(layer, &reason),
            Input::Closed => {
                let mut effects = self.calls.drop_call(Overtaken::SessionClosed);
                effects.push(Effect::Note(Record::MissionEnd {
                    outcome: "pilot closed the session".into(),
                }));
                effects
            }
        };
        self.absorb(effects)
    }

    fn membership(&mut self, change: SwarmChange, snap: &Snapshot) -> Vec<Effect> {
        match &change {
            SwarmChange::Joined(d) => self.present.insert(d.clone()),
            SwarmChange::Left(d) => self.present.remove(d),
            SwarmChange::Status(_) => false,
        };
        let effects = membership_changed(&mut self.book, snap, self.mode, &change);
        self.absorb(effects)
    }

    /// Outcomes looked for; a cycle is due when a task changed or the cycle timeout passed.
    fn tick(&mut self, snap: &Snapshot, gate: &SafetyGate) -> Vec<Effect> {
        let rules = Rules {
            gate,
            mode: self.mode,
            max_task_failures: self.bounds.max_task_failures,
        };
        let (effects, changed) = poll(&mut self.book, snap, &rules);
        let last = *self.last_cycle.get_or_insert(snap.now);
        let timed_out = self.busy() && snap.now.duration_since(last) >= self.bounds.cycle_timeout;
        self.calls.cycle_due(changed || timed_out);
        effects
    }

    /// A direct command was carried out: the call in flight and the work waiting are dropped,
    /// the plan in force ends, and so does a plan held for approval and the monolithic work.
    fn overridden(&mut self) -> Vec<Effect> {
        let mut effects = self.calls.overridden();
        if let Some(plan) = self.book.plan.take() {
            effects.extend(plan_ended(plan, "interrupted by a direct command"));
        }
        if let Some(held) = self.held.take() {
            let text = format!(
                "the plan for {:?} awaiting approval ended: interrupted by a direct command",
                held.instruction
            );
            effects.extend(Effect::told(EventTopic::PlanEnded, text));
        }
        self.book.mnl.active = false;
        effects
    }
}

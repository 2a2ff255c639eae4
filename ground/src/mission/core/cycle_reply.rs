//! A Supervisor's (or the monolithic model's) reply taken in, and its calls sent one at a time:
//! each is checked by the gate again on the step's snapshot (the swarm may have moved on since
//! the reply was judged) and handed to the engine as `Effect::Send`; the send's result comes
//! back as `Input::Sent` and books the call, then the next goes. Calls that passed while the
//! reply was still being written (`driver::early`) come as `Input::EarlyCall` and go the same
//! way; the whole reply leaves their drones out. When the last call is sent the cycle is
//! counted and logged; a failed send ends it there, told to the pilot.

use super::effect::Effect;
use super::outcomes::judge_monolithic;
use super::snapshot::Snapshot;
use super::state::Core;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionError, MissionUpdate};
use crate::safety::{CheckedAction, SafetyGate};
use std::collections::VecDeque;
use std::time::Duration;
use tacos_prompts::Call;
use tacos_shared::DroneId;

/// Which cycle a call is for, and what its answer completes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum CycleKind {
    Supervisor,
    /// `offered`: the numbered callables offered, whose ids the next cycle does not reuse.
    Monolithic {
        offered: u32,
    },
}

/// A cycle's reply as checked: the calls that passed, and what the pilot is told.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct CycleChoice {
    pub(crate) reasoning: String,
    /// The model claimed the work complete.
    pub(crate) claim: bool,
    /// Every call of the reply passed the checks (none was a later step).
    pub(crate) all_passed: bool,
    pub(crate) accepted: Vec<(Call, CheckedAction)>,
    pub(crate) later: Vec<String>,
}

/// A cycle's checked reply, or why there is none.
pub(crate) type CycleAnswer = Result<CycleChoice, MissionError>;

/// The cycle whose call is in flight or whose calls are being sent.
#[derive(Debug, Clone)]
pub(crate) struct CycleSends {
    kind: CycleKind,
    /// `CallQueue::epoch` when the call started: a reply from before a plan was adopted or
    /// ended is for other work.
    epoch: u64,
    /// Calls sent while the reply was being written, and how many were refused when they were
    /// to go.
    served: Vec<Call>,
    refused: usize,
    /// Once the whole reply is in: the cycle's record and the calls still to send.
    reply: Option<WholeReply>,
    /// The call whose send the core waits for.
    sending: Option<Sending>,
}

#[derive(Debug, Clone)]
struct Sending {
    call: Call,
    drone: DroneId,
    /// For an early call: how long after the call started it was complete.
    early: Option<Duration>,
}

#[derive(Debug, Clone)]
struct WholeReply {
    reasoning: String,
    claim: bool,
    all_passed: bool,
    sent: Vec<String>,
    queue: VecDeque<(Call, CheckedAction)>,
}

impl Core {
    /// A cycle call of `kind` was started in the work epoch now.
    pub(crate) fn cycle_started(&mut self, kind: CycleKind) {
        self.cycle = Some(CycleSends {
            kind,
            epoch: self.calls.epoch(),
            served: Vec::new(),
            refused: 0,
            reply: None,
            sending: None,
        });
    }

    /// A call that passed while its reply is still being written (`after` the call started).
    pub(super) fn early_call(
        &mut self,
        call: Call,
        checked: &CheckedAction,
        after: Duration,
        snap: &Snapshot,
        gate: &SafetyGate,
    ) -> Vec<Effect> {
        let current = self.cycle.as_ref().is_some_and(|c| {
            c.reply.is_none() && c.sending.is_none() && self.calls.is_current(c.epoch)
        });
        if !current {
            return Vec::new();
        }
        let mut effects = Vec::new();
        match recheck(&call, checked, snap, gate, &mut effects) {
            Some(checked) => {
                let sending = sending(call, &checked, Some(after));
                effects.push(send(&sending.call, checked));
                if let Some(cycle) = self.cycle.as_mut() {
                    cycle.sending = Some(sending);
                }
            }
            None => {
                if let Some(cycle) = self.cycle.as_mut() {
                    cycle.refused += 1;
                }
            }
        }
        effects
    }

    /// The cycle call's checked reply: its calls sent but for the drones served while it was
    /// written. A reply for work that has since ended or been replaced is dropped, and nothing
    /// of it is sent.
    pub(super) fn cycle_answered(
        &mut self,
        answer: CycleAnswer,
        snap: &Snapshot,
        gate: &SafetyGate,
    ) -> Vec<Effect> {
        let choice = match answer {
            Ok(choice) => choice,
            Err(e) => {
                self.cycle = None;
                return vec![Effect::Tell(MissionUpdate::Error(e.to_string()))];
            }
        };
        let Some(mut cycle) = self.cycle.take() else {
            return Vec::new();
        };
        let mut effects = Vec::new();
        if !self.calls.is_current(cycle.epoch) {
            let calls: Vec<String> = choice.accepted.iter().map(|(c, _)| c.to_string()).collect();
            let text = format!(
                "a reply for work that ended meanwhile was dropped, nothing of it sent: [{}]",
                calls.join("; ")
            );
            effects.extend(Effect::told(EventTopic::Note, text));
            return effects;
        }
        if !choice.later.is_empty() {
            let text = format!(
                "later steps in the same reply, left for a later cycle: {}",
                choice.later.join("; ")
            );
            effects.extend(Effect::told(EventTopic::Note, text));
        }
        let served = &cycle.served;
        let queue = choice
            .accepted
            .into_iter()
            .filter(|(call, _)| !served.iter().any(|c| c.drone == call.drone))
            .collect();
        cycle.reply = Some(WholeReply {
            reasoning: choice.reasoning,
            claim: choice.claim,
            all_passed: choice.all_passed && cycle.refused == 0,
            sent: cycle.served.iter().map(ToString::to_string).collect(),
            queue,
        });
        self.cycle = Some(cycle);
        effects.extend(self.send_next(snap, gate));
        effects
    }

    /// The send the core waited for: the call booked as issued (or the error told), then the
    /// next call of the reply.
    pub(super) fn sent(
        &mut self,
        result: Result<u64, MissionError>,
        snap: &Snapshot,
        gate: &SafetyGate,
    ) -> Vec<Effect> {
        let Some(Sending { call, drone, early }) =
            self.cycle.as_mut().and_then(|c| c.sending.take())
        else {
            return Vec::new();
        };
        let seq = match result {
            Ok(seq) => seq,
            Err(e) => {
                if early.is_none() {
                    // The rest of the reply is not sent, and the cycle not counted.
                    self.cycle = None;
                }
                return vec![Effect::Tell(MissionUpdate::Error(e.to_string()))];
            }
        };
        let mut effects = Vec::new();
        self.issued(call.clone(), drone, seq);
        if let Some(cycle) = self.cycle.as_mut() {
            match (early, cycle.reply.as_mut()) {
                (Some(after), _) => {
                    let text = format!(
                        "{call}: sent {:.1} s into the call, while the reply was still being \
                         written",
                        after.as_secs_f64()
                    );
                    effects.extend(Effect::told(EventTopic::Note, text));
                    cycle.served.push(call);
                }
                (None, Some(reply)) => reply.sent.push(call.to_string()),
                (None, None) => {}
            }
        }
        if self.cycle.as_ref().is_some_and(|c| c.reply.is_some()) {
            effects.extend(self.send_next(snap, gate));
        }
        effects
    }

    /// Sends the reply's next call that the gate still passes; with none left, the cycle ends.
    fn send_next(&mut self, snap: &Snapshot, gate: &SafetyGate) -> Vec<Effect> {
        let mut effects = Vec::new();
        let Some(cycle) = self.cycle.as_mut() else {
            return effects;
        };
        let Some(reply) = cycle.reply.as_mut() else {
            return effects;
        };
        while let Some((call, checked)) = reply.queue.pop_front() {
            if let Some(checked) = recheck(&call, &checked, snap, gate, &mut effects) {
                let sending = sending(call, &checked, None);
                effects.push(send(&sending.call, checked));
                cycle.sending = Some(sending);
                return effects;
            }
            reply.all_passed = false;
        }
        if let Some(CycleSends {
            kind,
            reply: Some(reply),
            ..
        }) = self.cycle.take()
        {
            effects.extend(self.cycle_done(kind, reply));
        }
        effects
    }

    /// Books a sent call on the plan (or the monolithic model's work).
    fn issued(&mut self, call: Call, drone: DroneId, seq: u64) {
        let Some(kind) = self.cycle.as_ref().map(|c| c.kind) else {
            return;
        };
        match kind {
            CycleKind::Supervisor => {
                if let Some(plan) = self.book.plan.as_mut() {
                    plan.issued(call, drone, seq);
                }
            }
            CycleKind::Monolithic { .. } => self.book.mnl.issued(call, drone, seq),
        }
    }

    /// Counts the cycle and logs it with the model's claim, which is never trusted: a plan is
    /// complete when its tasks are done (`Input::Tick`), the monolithic work when its claim
    /// stands (every call of the reply passed and was sent) and nothing it issued runs.
    fn cycle_done(&mut self, kind: CycleKind, reply: WholeReply) -> Vec<Effect> {
        let plan_cycle = match kind {
            CycleKind::Supervisor => {
                let Some(plan) = self.book.plan.as_mut() else {
                    return Vec::new();
                };
                plan.cycles += 1;
                plan.cycles
            }
            CycleKind::Monolithic { offered } => {
                let mnl = &mut self.book.mnl;
                mnl.next_task += offered;
                mnl.cycles += 1;
                mnl.claimed_done = reply.claim && reply.all_passed;
                mnl.cycles
            }
        };
        let mut effects = vec![
            Effect::CycleCounted,
            Effect::Note(Record::SupervisorCycle {
                plan_cycle,
                actions: reply.sent.clone(),
                plan_complete: reply.claim,
            }),
            Effect::Tell(MissionUpdate::Cycle {
                plan_cycle,
                reasoning: reply.reasoning,
                actions: reply.sent,
            }),
        ];
        if matches!(kind, CycleKind::Monolithic { .. }) {
            effects.extend(judge_monolithic(&mut self.book.mnl));
        }
        effects
    }
}

/// The gate's check of `checked` again on the step's snapshot; a refusal is told as a note.
fn recheck(
    call: &Call,
    checked: &CheckedAction,
    snap: &Snapshot,
    gate: &SafetyGate,
    effects: &mut Vec<Effect>,
) -> Option<CheckedAction> {
    let drone = checked.drone().as_str();
    match gate.check(&snap.swarm, drone, checked.action(), snap.now) {
        Ok(checked) => Some(checked),
        Err(why) => {
            effects.extend(Effect::told(
                EventTopic::Note,
                format!("{call}: not sent: {why}"),
            ));
            None
        }
    }
}

fn sending(call: Call, checked: &CheckedAction, early: Option<Duration>) -> Sending {
    Sending {
        call,
        drone: checked.drone().clone(),
        early,
    }
}

fn send(call: &Call, checked: CheckedAction) -> Effect {
    Effect::Send {
        checked,
        task: call.task.clone(),
    }
}

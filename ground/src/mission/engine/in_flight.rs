//! Model calls run beside the engine. A call (with its repair rounds) is a task of its own, so
//! that while a model thinks — minutes with a small CPU model — the engine goes on taking in
//! outcomes, lost drones, detections and pilot lines. One call is in flight at a time; work for
//! the Coordinator that comes meanwhile (a newer instruction, an automatic replan) waits in
//! order, and only a direct command, which overrides what came before it, drops it. A reply is
//! used only if nothing overtook it: a direct command drops
//! any call in flight, newer work for the Coordinator drops a Supervisor (or monolithic) call,
//! and a cycle's reply for a plan that has since ended is dropped when it comes
//! (`Mission::work_epoch`). Whatever is dropped is logged and told.

use super::Mission;
use super::cycle_call::{CycleChoice, CycleWork};
use super::early::{EarlyCall, EarlyCalls};
use crate::mission::log::Record;
use crate::mission::report::{MissionError, MissionUpdate, Overtaken};
use crate::task_guard::AbortOnDrop;
use std::future::Future;
use tacos_prompts::Call;

/// The Coordinator's checked reply: its reasoning, the calls that passed, and its refusal.
pub(super) type CoordinatorAnswer = Result<(String, Vec<Call>, Option<String>), MissionError>;
/// A Supervisor's or monolithic model's checked reply.
pub(super) type CycleAnswer = Result<CycleChoice, MissionError>;

/// A call's reply with what it was asked for, as its task hands it back.
pub(super) enum Answered {
    Coordinator {
        instruction: String,
        /// The drones on the ground when the call was made.
        grounded: Vec<String>,
        answer: CoordinatorAnswer,
    },
    Cycle {
        work: CycleWork,
        answer: CycleAnswer,
    },
}

/// What a call in flight tells the engine.
pub(super) enum Heard {
    /// A call of a cycle's reply that passed while the reply is still being written.
    Early(EarlyCall),
    Answer(Result<Answered, tokio::task::JoinError>),
}

/// The model call in flight.
pub(super) struct InFlight {
    pub(super) layer: &'static str,
    task: AbortOnDrop<Answered>,
    /// A cycle call's calls that pass while its reply is still being written (`early`).
    pub(super) early: Option<EarlyCalls>,
}

impl InFlight {
    pub(super) fn spawn(
        layer: &'static str,
        call: impl Future<Output = Answered> + Send + 'static,
    ) -> Self {
        InFlight {
            layer,
            task: AbortOnDrop(tokio::spawn(call)),
            early: None,
        }
    }

    /// A Supervisor or monolithic call (not the Coordinator's).
    pub(super) fn is_cycle(&self) -> bool {
        self.layer != "coordinator"
    }

    /// The next thing heard from the call: a call of its reply sent early, or its answer.
    pub(super) async fn heard(&mut self) -> Heard {
        let early = async {
            match self.early.as_mut() {
                Some(calls) => calls.next().await,
                None => None,
            }
        };
        tokio::select! {
            biased;
            Some(call) = early => Heard::Early(call),
            answer = &mut self.task.0 => Heard::Answer(answer),
        }
    }
}

/// Work waiting for the Coordinator, in the order it came.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Coordination {
    /// The pilot's instruction (in the history already).
    Pilot(String),
    /// An automatic replan after a membership change, as its instruction.
    Replan(String),
}

impl Mission {
    /// Queues work for the Coordinator; a Supervisor (or monolithic) call in flight is for the
    /// plan this work will change, and is dropped.
    pub(super) fn want_coordination(&mut self, work: Coordination) {
        if self.in_flight.as_ref().is_some_and(InFlight::is_cycle) {
            self.drop_call(Overtaken::NewerWork);
        }
        self.queued.push_back(work);
    }

    /// Drops the call in flight, if any: its task is aborted and its reply never used.
    pub(super) fn drop_call(&mut self, by: Overtaken) {
        let Some(flight) = self.in_flight.take() else {
            return;
        };
        let layer = flight.layer;
        drop(flight);
        self.log.note(Record::Event {
            text: format!("the {layer}'s call in flight was dropped, overtaken by {by}"),
        });
        self.tell(MissionUpdate::CallDropped { layer, by });
    }

    /// With no call in flight: the next work waiting for the Coordinator, or else a cycle when
    /// one is due. Errors are told to the pilot.
    pub(super) async fn start_next_call(&mut self) {
        while self.in_flight.is_none() {
            let Some(work) = self.queued.pop_front() else {
                break;
            };
            if let Err(e) = self.coordinate(&work).await {
                self.tell(MissionUpdate::Error(e.to_string()));
            }
        }
        if self.in_flight.is_none() && self.cycle_due && self.busy() {
            self.cycle_due = false;
            self.last_cycle = self.link.clock().instant();
            if let Err(e) = self.cycle() {
                self.tell(MissionUpdate::Error(e.to_string()));
            }
        }
    }

    /// The call in flight answered: its reply is taken in.
    pub(super) async fn answered(&mut self, joined: Result<Answered, tokio::task::JoinError>) {
        let Some(flight) = self.in_flight.take() else {
            return;
        };
        let result = match joined {
            Err(e) => Err(format!("the {}'s call ended abnormally: {e}", flight.layer)),
            Ok(Answered::Coordinator {
                instruction,
                grounded,
                answer,
            }) => {
                let result = self.coordinator_answered(instruction, grounded, answer);
                // A new plan: its first cycle at once.
                self.cycle_due = self.busy();
                result.map_err(|e| e.to_string())
            }
            Ok(Answered::Cycle { work, answer }) => {
                let served = flight.early.map(EarlyCalls::served).unwrap_or_default();
                self.cycle_answered(work, answer, served)
                    .await
                    .map_err(|e| e.to_string())
            }
        };
        if let Err(e) = result {
            self.tell(MissionUpdate::Error(e));
        }
    }
}

//! Model calls run beside the engine. A call (with its repair rounds) is a task of its own, so
//! that while a model thinks — minutes with a small CPU model — the engine goes on taking in
//! outcomes, lost drones, detections and pilot lines. Which call runs next and which one is
//! overtaken is decided by `core::CallQueue`; this runs them, aborts the dropped ones and takes
//! the replies in.

use super::Mission;
use super::early::{EarlyCall, EarlyCalls};
use crate::mission::core::{CoordinatorAnswer, CycleAnswer, Input};
use crate::mission::report::{MissionUpdate, Overtaken};
use crate::task_guard::AbortOnDrop;
use std::future::Future;

/// A call's reply with what it was asked for, as its task hands it back.
pub(super) enum Answered {
    Coordinator {
        instruction: String,
        /// The drones on the ground when the call was made.
        grounded: Vec<String>,
        answer: CoordinatorAnswer,
    },
    /// A Supervisor's or monolithic model's checked reply.
    Cycle(CycleAnswer),
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

impl Mission {
    /// Aborts the call in flight (`Effect::DropCall`): its reply is never used.
    pub(super) fn abort_call(&mut self, layer: &'static str, by: Overtaken) {
        drop(self.in_flight.take());
        self.tell(MissionUpdate::CallDropped { layer, by });
    }

    /// With no call in flight: the next work waiting for the Coordinator, or else a cycle when
    /// one is due (`Input::CallDue`); work whose request could not be made (told to the
    /// pilot) makes way for the next.
    pub(super) async fn start_next_call(&mut self) {
        while self.in_flight.is_none() && self.core.has_call_due() {
            self.step(Input::CallDue);
            if self.awaited.is_empty() {
                break;
            }
            self.carry_out_queued().await;
        }
    }

    /// The call in flight answered: its reply is taken in.
    pub(super) fn answered(&mut self, joined: Result<Answered, tokio::task::JoinError>) {
        let Some(flight) = self.in_flight.take() else {
            return;
        };
        let input = match joined {
            Err(e) => Input::CallLost {
                layer: flight.layer,
                reason: e.to_string(),
            },
            Ok(Answered::Coordinator {
                instruction,
                grounded,
                answer,
            }) => Input::CoordinatorReply {
                instruction,
                grounded,
                answer,
            },
            Ok(Answered::Cycle(answer)) => Input::CycleReply(answer),
        };
        self.step(input);
    }
}

//! The Coordinator layer: the pilot's instruction (or an automatic replan) in, a checked plan out.

use super::Mission;
use super::in_flight::{Answered, InFlight};
use crate::mission::core::{Checked, Coordination, CoordinatorAsk, Input, Snapshot};
use crate::mission::report::MissionUpdate;
use tacos_prompts::CoordinatorReply;
use tacos_prompts::schema::Output;

/// How long a Coordinator call waits for a drone to be heard again when none is available: a
/// status is stale after a second, and a loaded ground (a model computing on both cores) or a
/// network hiccup can silence the whole swarm for that long without anything being lost.
const SILENCE_GRACE: std::time::Duration = std::time::Duration::from_secs(5);

impl Mission {
    /// A snapshot with a drone available; when none is, the first within [`SILENCE_GRACE`]
    /// that has one, or the last.
    async fn snapshot_after_silence(&self) -> Snapshot {
        let deadline = tokio::time::Instant::now() + SILENCE_GRACE;
        loop {
            let snap = self.snapshot();
            let available = snap.available_ids(self.gate.scenario());
            if !available.is_empty() || tokio::time::Instant::now() >= deadline {
                return snap;
            }
            tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        }
    }

    /// Feeds the Coordinator's work to the core (`Input::Coordinate`) on a snapshot with a
    /// drone heard, if one is within the grace.
    pub(super) async fn coordinate(&mut self, work: Coordination) {
        let snap = self.snapshot_after_silence().await;
        self.step_on(Input::Coordinate(work), snap);
    }

    /// Starts the Coordinator's call for the request the core made (`Ask::Coordinator`) beside
    /// the mission; the core takes its reply in (`Input::CoordinatorReply`).
    pub(super) fn start_coordinator_call(&mut self, ask: CoordinatorAsk) {
        let CoordinatorAsk {
            instruction,
            messages,
            schema,
            token_budget,
            check,
            grounded,
        } = ask;
        let log = self.log.clone();
        self.tell(MissionUpdate::Thinking {
            layer: "coordinator",
        });
        self.stats.update(|s| s.coordinator_calls += 1);
        let caller = self.caller.clone();
        let max_tokens = self.cfg.coordinator_max_tokens.max(token_budget);
        let call = async move {
            let answer = caller
                .ask(
                    "coordinator",
                    messages,
                    Output::Coordinator,
                    schema,
                    max_tokens,
                    CoordinatorReply::parse,
                    true,
                    move |reply: &CoordinatorReply| {
                        let judged = check.judge(reply);
                        for (aid, detail) in judged.aids_fired {
                            log.aid_fired(aid, detail);
                        }
                        Checked {
                            nothing_passed: judged.plan.is_empty() && judged.refusal.is_none(),
                            accepted: (judged.reasoning, judged.plan, judged.refusal),
                            rejections: judged.rejections,
                            // A plan's calls are not actions yet: the gate judges them when sent.
                            gate_refusals: Vec::new(),
                            narrowed: judged.narrowed,
                            doubts: judged.doubts,
                        }
                    },
                )
                .await;
            Answered::Coordinator {
                instruction,
                grounded,
                answer,
            }
        };
        self.in_flight = Some(InFlight::spawn("coordinator", call));
    }
}

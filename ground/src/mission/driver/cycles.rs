//! The Supervisor's and the monolithic model's cycles: the model's call for the cycle the core
//! starts (`core::cycle_start`), with its choice judged by the live checks as it comes (its
//! reply and its sends are the core's: `core::cycle_reply`).

use super::Mission;
use super::cycle_call::{CycleAsk, CycleReply};
use super::early::early_calls;
use super::in_flight::{Answered, InFlight};
use crate::mission::core::{
    Checked, CycleChoice, CycleJudgement, CycleKind, CycleRequest, CycleStart, check_live,
    judge_cycle, match_startable,
};
use crate::mission::report::MissionUpdate;
use tacos_prompts::schema::{self, Output};
use tacos_prompts::{Call, MonolithicReply, SupervisorReply};

impl Mission {
    /// The common part of a Supervisor and a monolithic cycle: starts the model's call (with the
    /// repair loop) beside the engine, keeping the calls that are among `only` (when given) and
    /// pass `check_live` and the safety gate as the reply comes; the core takes the calls that
    /// pass early (`Input::EarlyCall`) and the reply (`Input::CycleReply`) and sends them.
    pub(super) fn start_cycle_call(&mut self, start: CycleStart) {
        let ask = match start.kind {
            CycleKind::Supervisor => CycleAsk {
                layer: start.layer,
                output: Output::Supervisor,
                parse: |text| SupervisorReply::parse(text).map(CycleReply::from),
                request: start.request,
            },
            CycleKind::Monolithic { .. } => CycleAsk {
                layer: start.layer,
                output: Output::Monolithic,
                parse: |text| MonolithicReply::parse(text).map(CycleReply::from),
                request: start.request,
            },
        };
        self.tell(MissionUpdate::Thinking { layer: ask.layer });
        self.stats.update(|s| s.supervisor_calls += 1);
        let max_tokens = self
            .cfg
            .supervisor_max_tokens
            .max(schema::token_budget(ask.output, ask.request.drones));
        let (gate, link) = (self.gate.clone(), self.link.clone());
        let visible = self.visible_targets();
        let judge = {
            let (only, tasks) = (ask.request.only.clone(), ask.request.tasks.clone());
            let (gate, link, visible) = (gate.clone(), link.clone(), visible.clone());
            move |calls: &[Call]| {
                let calls = match &only {
                    Some(startable) => match_startable(calls, startable).0,
                    None => calls.to_vec(),
                };
                let snap = super::snapshot_of(&link, visible.clone());
                check_live(&calls, &gate, &snap, &tasks).0
            }
        };
        let (on_written, seen, early) = early_calls(judge);
        let mut caller = self.caller.clone();
        caller.on_written = Some(on_written);
        let layer = ask.layer;
        let call = async move {
            let CycleAsk {
                layer,
                output,
                parse,
                request:
                    CycleRequest {
                        messages,
                        schema,
                        only,
                        tasks,
                        drones: _,
                    },
            } = ask;
            let answer = caller
                .ask(
                    layer,
                    messages,
                    output,
                    schema,
                    max_tokens,
                    parse,
                    false,
                    move |reply: &CycleReply| {
                        // The drones whose call went while the reply was written are served.
                        let snap = super::snapshot_of(&link, visible.clone());
                        let CycleJudgement {
                            accepted,
                            later,
                            rejections,
                            gate_refusals,
                        } = judge_cycle(
                            &reply.actions,
                            only.as_deref(),
                            &seen.handed_on(),
                            &snap,
                            &gate,
                            &tasks,
                        );
                        Checked {
                            nothing_passed: accepted.is_empty(),
                            accepted: CycleChoice {
                                reasoning: reply.reasoning.clone(),
                                claim: reply.claim,
                                all_passed: rejections.is_empty()
                                    && gate_refusals.is_empty()
                                    && later.is_empty(),
                                accepted,
                                later,
                            },
                            rejections,
                            gate_refusals,
                            narrowed: None,
                            doubts: Vec::new(),
                        }
                    },
                )
                .await;
            Answered::Cycle(answer)
        };
        let mut flight = InFlight::spawn(layer, call);
        flight.early = Some(early);
        self.in_flight = Some(flight);
    }
}

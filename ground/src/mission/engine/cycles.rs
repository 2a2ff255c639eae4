//! The Supervisor's and the monolithic model's cycles: what may start now, the model's choice,
//! the live checks, and the sends.

use super::Mission;
use super::cycle_call::{CycleAsk, CycleChoice, CycleKind, CycleOutcome, CycleReply, CycleWork};
use super::early::{Served, early_calls};
use super::in_flight::{Answered, CycleAnswer, InFlight};
use crate::mission::config::Mode;
use crate::mission::core::{
    Checked, CycleJudgement, CycleRequest, check_live, judge_cycle, match_startable,
    monolithic_ask, supervisor_ask,
};
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionError, MissionUpdate};
use crate::safety::CheckedAction;
use tacos_prompts::schema::{self, Output};
use tacos_prompts::{Call, MonolithicReply, SupervisorReply};
use tacos_shared::DroneId;

impl Mission {
    /// Starts one Supervisor (or monolithic) cycle, when there is a decision to make.
    pub(super) fn cycle(&mut self) -> Result<(), MissionError> {
        match self.cfg.mode {
            Mode::Mnl => self.monolithic_cycle(),
            Mode::Tacos | Mode::Wor => self.supervisor_cycle(),
        }
    }

    pub(super) fn supervisor_cycle(&mut self) -> Result<(), MissionError> {
        let Some(plan) = self.book.plan.as_ref() else {
            return Ok(());
        };
        if plan.cycles >= self.cfg.max_cycles_per_plan {
            if let Some(plan) = self.book.plan.take() {
                self.finish_plan(plan, "abandoned after too many cycles");
                self.tell(MissionUpdate::Error(format!(
                    "the plan was not complete after {} Supervisor cycles",
                    self.cfg.max_cycles_per_plan
                )));
            }
            return Ok(());
        }
        // One snapshot for the decision and the prompt: every line of it sees the same swarm.
        let snap = self.snapshot();
        let mode = self.cfg.mode;
        let Some(request) = supervisor_ask(&self.book, &snap, &self.gate, &self.events, mode)
        else {
            // Nothing can start: wait for the swarm (an outcome, a membership change or the
            // cycle timeout wakes us again).
            self.give_up_if_stuck();
            return Ok(());
        };
        if let Some(plan) = self.book.plan.as_mut() {
            plan.stuck_since = None;
        }
        let ask = CycleAsk {
            layer: "supervisor",
            output: Output::Supervisor,
            parse: |text| SupervisorReply::parse(text).map(CycleReply::from),
            request,
        };
        self.start_cycle_call(ask, CycleKind::Supervisor, |mission, call, drone, seq| {
            if let Some(plan) = mission.book.plan.as_mut() {
                plan.issued(call, drone, seq);
            }
        });
        Ok(())
    }

    pub(super) fn monolithic_cycle(&mut self) -> Result<(), MissionError> {
        if self.book.mnl.claimed_done {
            // The model said its actions carry out the instructions: wait for their outcomes.
            return Ok(());
        }
        if self.book.mnl.cycles >= self.cfg.max_cycles_per_plan {
            self.book.mnl.active = false;
            let text = format!(
                "the monolithic model did not carry out the instructions in {} cycles",
                self.book.mnl.cycles
            );
            self.log.note(Record::Event { text: text.clone() });
            self.tell(MissionUpdate::Error(text));
            return Ok(());
        }
        // As for the Supervisor: when no drone can take an action, there is nothing to decide.
        let snap = self.snapshot();
        let scenario = self.gate.scenario();
        let Some((request, offered)) = monolithic_ask(&self.book, &snap, scenario, &self.events)
        else {
            return Ok(());
        };
        let ask = CycleAsk {
            layer: "monolithic",
            output: Output::Monolithic,
            parse: |text| MonolithicReply::parse(text).map(CycleReply::from),
            request,
        };
        self.start_cycle_call(
            ask,
            CycleKind::Monolithic { offered },
            |mission, call, drone, seq| mission.book.mnl.issued(call, drone, seq),
        );
        Ok(())
    }

    /// The common part of a Supervisor and a monolithic cycle: starts the model's call (with the
    /// repair loop) beside the engine, keeping the calls that are among `only` (when given) and
    /// pass `check_live` and the safety gate as the reply comes. [`Self::cycle_answered`] sends
    /// them and hands each sent call to `issued` for the caller's bookkeeping.
    pub(super) fn start_cycle_call(
        &mut self,
        ask: CycleAsk,
        kind: CycleKind,
        issued: fn(&mut Mission, Call, DroneId, u64),
    ) {
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
        let (on_written, seen, early) = early_calls(judge, issued, self.calls.epoch());
        let mut caller = self.caller.clone();
        caller.on_written = Some(on_written);
        let work = CycleWork {
            kind,
            issued,
            epoch: self.calls.epoch(),
        };
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
                        }
                    },
                )
                .await;
            Answered::Cycle { work, answer }
        };
        let mut flight = InFlight::spawn(layer, call);
        flight.early = Some(early);
        self.in_flight = Some(flight);
        self.calls.started(layer);
    }

    /// A cycle's checked reply: its calls sent (each checked by the gate again, against the
    /// swarm as it is now) but for the drones `served` while it was written, the cycle counted.
    /// A reply for work that has since ended or been replaced is dropped, and nothing of it is
    /// sent.
    pub(super) async fn cycle_answered(
        &mut self,
        work: CycleWork,
        answer: CycleAnswer,
        served: Served,
    ) -> Result<(), MissionError> {
        let choice = answer?;
        if !self.calls.is_current(work.epoch) {
            let calls: Vec<String> = choice.accepted.iter().map(|(c, _)| c.to_string()).collect();
            self.event(
                EventTopic::Note,
                format!(
                    "a reply for work that ended meanwhile was dropped, nothing of it sent: [{}]",
                    calls.join("; ")
                ),
            );
            return Ok(());
        }
        if !choice.later.is_empty() {
            let text = format!(
                "later steps in the same reply, left for a later cycle: {}",
                choice.later.join("; ")
            );
            self.event(EventTopic::Note, text);
        }
        let mut sent: Vec<String> = served.sent.iter().map(ToString::to_string).collect();
        let mut all_passed = choice.all_passed && served.refused == 0;
        for (call, checked) in choice.accepted {
            if served.sent.iter().any(|c| c.drone == call.drone) {
                continue;
            }
            let text = call.to_string();
            if self.send_cycle_call(call, &checked, work.issued).await? {
                sent.push(text);
            } else {
                all_passed = false;
            }
        }
        let cycle = CycleOutcome {
            reasoning: choice.reasoning,
            claim: choice.claim,
            all_passed,
            sent,
        };
        match work.kind {
            CycleKind::Supervisor => {
                // The Supervisor's claim that the plan is complete is logged only: the plan is
                // complete when its tasks are done (`poll_outcomes`).
                if let Some(plan) = self.book.plan.as_mut() {
                    plan.cycles += 1;
                    let n = plan.cycles;
                    self.note_cycle(n, cycle);
                }
            }
            CycleKind::Monolithic { offered } => {
                self.book.mnl.next_task += offered;
                self.book.mnl.cycles += 1;
                self.book.mnl.claimed_done = cycle.claim_stands();
                self.note_cycle(self.book.mnl.cycles, cycle);
                self.judge_monolithic();
            }
        }
        Ok(())
    }

    /// Sends one call a cycle's reply chose, checked by the gate again (it was checked when
    /// the reply came; the swarm may have moved on since), and hands it to `issued`. False
    /// when the gate now refuses it (told as a note).
    pub(super) async fn send_cycle_call(
        &mut self,
        call: Call,
        checked: &CheckedAction,
        issued: fn(&mut Mission, Call, DroneId, u64),
    ) -> Result<bool, MissionError> {
        let now = self.link.clock().instant();
        let checked = {
            let view = self.link.view();
            self.gate
                .check(&view, checked.drone().as_str(), checked.action(), now)
        };
        let checked = match checked {
            Ok(checked) => checked,
            Err(why) => {
                self.event(EventTopic::Note, format!("{call}: not sent: {why}"));
                return Ok(false);
            }
        };
        let seq = self.send(&checked, Some(call.task.clone())).await?;
        issued(self, call, checked.drone().clone(), seq);
        Ok(true)
    }

    /// Counts a cycle, logs it with the model's claim, and reports it.
    pub(super) fn note_cycle(&mut self, plan_cycle: u32, cycle: CycleOutcome) {
        self.stats.update(|s| s.cycles_total += 1);
        self.log.note(Record::SupervisorCycle {
            plan_cycle,
            actions: cycle.sent.clone(),
            plan_complete: cycle.claim,
        });
        self.tell(MissionUpdate::Cycle {
            plan_cycle,
            reasoning: cycle.reasoning,
            actions: cycle.sent,
        });
    }
}

//! The mission core's state: the plan book, the calls' schedule, the two memories (the
//! Coordinator's history and the world's events), the plan held for the pilot, and what the
//! core knows of the swarm's membership and the last cycle's time. [`Core::step`] (`step`)
//! takes the engine's inputs in; [`Core::absorb`] keeps the effects that only change this
//! state, so what reaches the engine is what it must do outside.

use super::book::{ActivePlan, PlanBook};
use super::calls::{CallQueue, Coordination, NextCall};
use super::cycle_reply::CycleSends;
use super::effect::Effect;
use crate::mission::aids::ModelAids;
use crate::mission::approval::HeldPlan;
use crate::mission::config::{MissionConfig, Mode};
use crate::mission::log::Record;
use crate::mission::resume::MissionMemory;
use std::collections::BTreeSet;
use std::time::{Duration, Instant};
use tacos_prompts::render::{HistoryEntry, TaskStatus};
use tacos_shared::DroneId;

/// The engine's bounds the core decides by (from `MissionConfig`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Bounds {
    /// A cycle is due at the latest this long after the last one while the models have work.
    pub(crate) cycle_timeout: Duration,
    pub(crate) max_cycles_per_plan: u32,
    pub(crate) max_task_failures: u32,
    /// Repair rounds per model call (named in the error when none passed).
    pub(crate) max_repairs: u32,
}

/// Everything the mission decides by, but the swarm (which each step's `Snapshot` brings).
#[derive(Debug, Clone)]
pub(crate) struct Core {
    pub(crate) mode: Mode,
    pub(crate) aids: ModelAids,
    /// Every Coordinator plan waits for the pilot's approval (`confirm on`).
    pub(crate) confirm: bool,
    pub(crate) bounds: Bounds,
    /// The plan in force and the monolithic model's work.
    pub(crate) book: PlanBook,
    /// Which model call runs next, what waits for the Coordinator, and the work epoch.
    pub(crate) calls: CallQueue,
    /// The Coordinator's memory of the mission.
    pub(crate) history: Vec<HistoryEntry>,
    /// The world's events as the prompts show them.
    pub(crate) events: Vec<String>,
    /// A Coordinator plan held for the pilot's approval.
    pub(crate) held: Option<HeldPlan>,
    /// The drones present as the membership changes taken in say (after changes were missed,
    /// the difference to the snapshot's view is taken in instead).
    pub(super) present: BTreeSet<DroneId>,
    /// When the last cycle started (the first tick's time until one has).
    pub(super) last_cycle: Option<Instant>,
    /// The cycle whose call is in flight or whose calls are being sent (`cycle_reply`).
    pub(super) cycle: Option<CycleSends>,
    /// The Coordinator's call in flight is an automatic replan (`replan-keeps-pending`).
    pub(super) replan_in_flight: bool,
}

impl Core {
    pub(crate) fn new(cfg: &MissionConfig) -> Core {
        Core {
            mode: cfg.mode,
            aids: cfg.aids,
            confirm: cfg.confirm,
            bounds: Bounds {
                cycle_timeout: cfg.cycle_timeout,
                max_cycles_per_plan: cfg.max_cycles_per_plan,
                max_task_failures: cfg.max_task_failures,
                max_repairs: cfg.max_repairs,
            },
            book: PlanBook::default(),
            calls: CallQueue::default(),
            history: Vec::new(),
            events: Vec::new(),
            held: None,
            present: BTreeSet::new(),
            last_cycle: None,
            cycle: None,
            replan_in_flight: false,
        }
    }

    /// True while a plan (or the monolithic model's work) is under way.
    pub(crate) fn busy(&self) -> bool {
        match self.mode {
            Mode::Mnl => self.book.mnl.active,
            Mode::Tacos | Mode::Wor => self.book.plan.is_some(),
        }
    }

    /// Carries out the effects that change only the core (remembering, replacing the work,
    /// queueing a replan) and hands back the rest, in order.
    pub(crate) fn absorb(&mut self, effects: Vec<Effect>) -> Vec<Effect> {
        let mut out = Vec::with_capacity(effects.len());
        for effect in effects {
            match effect {
                Effect::Remember(entry) => {
                    out.push(Effect::Note(Record::History {
                        entry: entry.clone(),
                    }));
                    self.history.push(entry);
                }
                Effect::WorkReplaced => self.calls.work_replaced(),
                Effect::Replan(instruction) => {
                    let dropped = self.calls.want(Coordination::Replan(instruction));
                    out.extend(dropped);
                }
                other => out.push(other),
            }
        }
        out
    }

    /// Whether a model call would start now: the driver feeds `Input::CallDue` only then, so
    /// an idle loop turn costs no snapshot and no traced step.
    pub(crate) fn has_call_due(&self) -> bool {
        self.calls.has_next(self.busy())
    }

    /// The model call to start now, if any (`CallQueue::next`); a cycle's start is its time.
    pub(crate) fn next_call(&mut self, now: Instant) -> Option<NextCall> {
        let next = self.calls.next(self.busy());
        if next == Some(NextCall::Cycle) {
            self.last_cycle = Some(now);
        }
        next
    }

    /// Goes on with a mission from its log (`mission::resume`): its history, world events and
    /// plan in force, with what each task was sent as so the outcomes the drones report now are
    /// matched to them; the first cycle is due at once. Returns what the pilot is told.
    pub(crate) fn resume(&mut self, memory: MissionMemory) -> String {
        let MissionMemory {
            history,
            world_events,
            plan,
        } = memory;
        let told = format!(
            "{} history entries, {}",
            history.len(),
            match &plan {
                Some(plan) => {
                    let open = plan
                        .tasks
                        .iter()
                        .filter(|t| t.status != TaskStatus::Done)
                        .count();
                    format!("a plan of {} tasks, {open} not done", plan.tasks.len())
                }
                None => "no plan in force".to_owned(),
            }
        );
        self.history = history;
        self.events = world_events;
        self.book.plan = plan.map(ActivePlan::resumed);
        self.calls.set_cycle_due(self.book.plan.is_some());
        told
    }
}

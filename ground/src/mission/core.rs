//! The mission's pure core: the plan's bookkeeping (`book`), the outcomes the drones report and
//! when a plan is complete, given up or stuck (`outcomes`), and whether a call can start now
//! (`start`), what a cycle's reply and a Coordinator's plan come to (`cycle`,
//! `checks`, `plan_check`), each decided from one [`Snapshot`] of the swarm, the targets and the time, handing
//! back [`Effect`]s for the driver (the async shell in `driver`) to carry out. Nothing here does
//! I/O or reads a clock, so the same book and snapshot give the same effects, and the rules are
//! tested without a process (`core::tests`; `core::purity` fails if a file here names tokio,
//! zenoh, the link, the log writer, the model backend or a clock).
//!
//! The repair loop of a model call is here too (`repair`): the engine's `Caller` only asks the
//! model and carries out its effects; and which model call runs next and which one a newer
//! event overtakes (`calls`).
//!
//! The swarm as the prompts show it is read from the snapshot (`prompt_view`), and the layers'
//! requests are built here (`coordinator`, `cycle_ask`).
//!
//! [`Core`] (`state`) holds all of it with the memories and the plan held for the pilot, and is
//! fed the engine's [`Input`]s one step at a time (`step`): pilot lines (`pilot`), membership
//! changes, world events (`world`), ticks, direct commands carried out, the Coordinator's
//! checked reply (`plan_reply`), a cycle's calls and reply with the results of their sends
//! (`cycle_reply`: one `Effect::Send` at a time, each checked by the gate on its step's
//! snapshot) and the session's end.

mod adopt;
mod book;
mod call_start;
mod calls;
mod checks;
mod coordinator;
mod cycle;
mod cycle_ask;
mod cycle_reply;
mod cycle_start;
mod effect;
mod membership;
mod outcomes;
mod pilot;
mod plan_check;
mod plan_reply;
mod prompt_view;
mod repair;
mod snapshot;
mod start;
mod state;
mod step;
mod trace;
mod world;

#[cfg(test)]
mod calls_tests;
#[cfg(test)]
mod coordinator_tests;
#[cfg(test)]
mod cycle_ask_tests;
#[cfg(test)]
mod cycle_reply_tests;
#[cfg(test)]
mod cycles_tests;
#[cfg(test)]
mod plan_tests;
#[cfg(test)]
mod prompt_view_tests;
#[cfg(test)]
mod properties;
#[cfg(test)]
mod purity;
#[cfg(test)]
mod repair_tests;
#[cfg(test)]
mod replan_tests;
#[cfg(test)]
mod step_tests;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod trace_tests;
#[cfg(test)]
mod world_tests;

pub(crate) use adopt::adopt;
pub(crate) use call_start::Ask;
pub(crate) use calls::Coordination;
pub(crate) use checks::check_live;
pub(crate) use coordinator::CoordinatorAsk;
pub use coordinator::{coordinator_fixed_messages, coordinator_messages};
pub(crate) use cycle::{CycleJudgement, first_call_per_drone, judge_cycle, match_startable};
pub(crate) use cycle_ask::CycleRequest;
pub use cycle_ask::{monolithic_fixed_messages, supervisor_fixed_messages, supervisor_messages};
pub(crate) use cycle_reply::{CycleAnswer, CycleChoice, CycleKind};
pub(crate) use cycle_start::CycleStart;
pub(crate) use effect::Effect;
pub(crate) use outcomes::effect_holds;
pub(crate) use repair::{Checked, Next, Repair};
pub(crate) use snapshot::Snapshot;
pub(crate) use state::Core;
pub(crate) use step::{CoordinatorAnswer, Input};
pub use trace::{TraceError, TracedCore, TracedStep};
pub(crate) use trace::{TracedInput, trace_step};

// What the core's tests reach through `super::*`.
#[cfg(test)]
use book::{ActivePlan, PlanBook};
#[cfg(test)]
use calls::{CallQueue, NextCall};
#[cfg(test)]
use coordinator::{CoordinatorContext, coordinator_ask};
#[cfg(test)]
use membership::membership_changed;
#[cfg(test)]
use outcomes::{Rules, give_up_if_stuck, plan_ended, poll};
#[cfg(test)]
use start::Start;

//! A drone joining or leaving the swarm: the pilot is told, a lost drone's running tasks fail
//! (and its done start_tracking while it still followed the target), and an automatic replan is
//! asked for when there is work the change may affect, naming what the lost drone leaves undone.

use super::book::PlanBook;
use super::effect::Effect;
use super::outcomes::following_of;
use super::snapshot::Snapshot;
use crate::mission::config::Mode;
use crate::mission::log::Record;
use crate::mission::report::EventTopic;
use crate::swarm::SwarmChange;
use tacos_prompts::render::HistoryEntry;
use tacos_shared::DroneId;

/// Takes in a membership change seen on `snap` (the view after it).
pub(crate) fn membership_changed(
    book: &mut PlanBook,
    snap: &Snapshot,
    mode: Mode,
    change: &SwarmChange,
) -> Vec<Effect> {
    let (topic, text) = match change {
        SwarmChange::Joined(d) => (EventTopic::Joined, format!("{d} joined the swarm")),
        SwarmChange::Left(d) => (EventTopic::Failure, left_text(snap, d)),
        SwarmChange::Status(_) => return Vec::new(),
    };
    let mut effects = Effect::told(topic, text.clone()).to_vec();
    // What the lost drone leaves undone, named in the replan's instruction so the Coordinator
    // hands exactly that on (a done start_tracking is still work while the drone follows:
    // without this, the chase would end with its tracker).
    let lost_work = match change {
        SwarmChange::Left(d) => {
            let following = following_of(snap, d);
            book.fail_tasks_of(d, following.as_deref(), "drone lost");
            book.unfinished_work_of(d, following)
        }
        _ => Vec::new(),
    };
    match mode {
        Mode::Mnl => {
            book.mnl.executed.push(format!("event: {text}"));
            book.mnl.claimed_done = false;
        }
        Mode::Tacos | Mode::Wor => {
            effects.push(Effect::Remember(HistoryEntry::Event(text.clone())));
            // Replan only when there is work that the change may affect.
            if book.plan.is_some() || !lost_work.is_empty() {
                effects.push(Effect::Note(Record::Replan {
                    reason: text.clone(),
                }));
                let subtasks = if lost_work.is_empty() {
                    String::new()
                } else {
                    format!(" ({})", lost_work.join(", "))
                };
                effects.push(Effect::Replan(format!(
                    "(automatic replan) {text}: reassign its unfinished subtasks{subtasks} and \
                     keep the mission going"
                )));
            }
        }
    }
    effects
}

/// Why `drone` left, when its status says: PX4 flies it (it is back once PX4 is in offboard
/// again or it is on the ground; a hold or land takes it back).
fn left_text(snap: &Snapshot, drone: &DroneId) -> String {
    let took_over = snap
        .swarm
        .get(drone)
        .filter(|e| e.alive)
        .and_then(|e| e.status.as_ref()?.autopilot_took_over);
    match took_over {
        Some(mode) => format!(
            "{drone} became unavailable: PX4 left offboard and flies it in {mode} (a hold or \
             land takes it back)"
        ),
        None => format!("{drone} became unavailable"),
    }
}

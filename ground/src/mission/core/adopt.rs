//! A Coordinator plan made the plan in force: calls that repeat their drone's previous work
//! dropped, the take-offs a small model forgets added (`implied-takeoffs`), and tasks already
//! running kept running when the new plan repeats them.

use super::book::{ActivePlan, PlanBook};
use super::cycle::same_work;
use super::effect::Effect;
use super::plan_check::missing_takeoffs;
use crate::mission::aids::Aid;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionUpdate};
use crate::mission::resume::PlanTask;
use std::collections::HashMap;
use tacos_prompts::render::{HistoryEntry, TaskStatus};
use tacos_prompts::{ActionName, Call};

/// Makes `calls` the plan in force; tasks already running keep their status (and what they were
/// sent as) when the new plan repeats them.
pub(crate) fn adopt(book: &mut PlanBook, reasoning: String, calls: Vec<Call>) -> Vec<Effect> {
    let mut effects = vec![Effect::Remember(HistoryEntry::Plan {
        reasoning: reasoning.clone(),
        plan: calls.clone(),
    })];
    let running: HashMap<(String, String), PlanTask> = book
        .plan
        .take()
        .into_iter()
        .flat_map(|p| p.tasks)
        .filter(|t| t.status == TaskStatus::Running)
        .map(|t| (same_work(&t.call), t))
        .collect();
    let tasks: Vec<PlanTask> = calls
        .into_iter()
        .map(|call| match running.get(&same_work(&call)) {
            Some(t) => PlanTask {
                call,
                status: TaskStatus::Running,
                sent: t.sent.clone(),
                failures: t.failures,
            },
            None => PlanTask {
                call,
                status: TaskStatus::NotStarted,
                sent: None,
                failures: 0,
            },
        })
        .collect();
    effects.push(Effect::WorkReplaced);
    effects.push(Effect::Note(Record::PlanAdopted {
        reasoning: reasoning.clone(),
        tasks: tasks.clone(),
    }));
    book.plan = Some(ActivePlan {
        reasoning,
        tasks,
        cycles: 0,
        stuck_since: None,
    });
    effects
}

/// The plan with a take-off added before the first goto or start_tracking of each drone that is
/// on the ground (`grounded`) and has no take-off anywhere in the plan: the Coordinator's own
/// rule ("a drone on the ground must take off before goto"), which a small model forgets.
/// Without it such a task can never start. Each addition is logged and told; the gate still
/// checks every action.
pub(crate) fn with_implied_takeoffs(
    calls: Vec<Call>,
    grounded: &[String],
) -> (Vec<Call>, Vec<Effect>) {
    let missing = missing_takeoffs(&calls, grounded);
    let mut next_id = calls
        .iter()
        .filter_map(|c| c.task.strip_prefix('T')?.parse::<u32>().ok())
        .max()
        .unwrap_or(0);
    let mut out: Vec<Call> = Vec::with_capacity(calls.len());
    let mut effects = Vec::new();
    for (i, call) in calls.iter().enumerate() {
        if missing.contains(&i) {
            next_id += 1;
            let takeoff = Call::named(
                &format!("T{next_id}"),
                &call.drone,
                ActionName::ArmTakeoff,
                tacos_prompts::schema::NO_TARGET,
            );
            let text = format!(
                "{call}: {} is on the ground and the plan never takes it off: added {takeoff}",
                call.drone
            );
            effects.push(Effect::aid_fired(Aid::ImpliedTakeoffs, text.clone()));
            effects.push(Effect::Tell(MissionUpdate::Event {
                topic: EventTopic::Note,
                text,
            }));
            out.push(takeoff);
        }
        out.push(call.clone());
    }
    (out, effects)
}

/// The plan without calls that repeat their drone's previous call in the plan (the 135M model
/// lists `alfa goto(villa)` six times in a row), and the calls dropped. Doing the same work
/// twice in a row changes nothing, and each repeat would cost a Supervisor cycle. Work repeated
/// after other work for that drone (out and back) is kept.
pub(crate) fn without_repeated_work(calls: Vec<Call>) -> (Vec<Call>, Vec<Call>) {
    let mut kept: Vec<Call> = Vec::with_capacity(calls.len());
    let mut dropped = Vec::new();
    for call in calls {
        let previous = kept.iter().rev().find(|c| c.drone == call.drone);
        if previous.is_some_and(|p| same_work(p) == same_work(&call)) {
            dropped.push(call);
        } else {
            kept.push(call);
        }
    }
    (kept, dropped)
}

/// An automatic replan's `calls` after the `pending` tasks (of the plan in force, not done and
/// not failed) whose drone is among `available` and whose work the new plan does not already
/// give out: the same call for the same drone, or a goto or start_tracking of the same place or
/// point by any drone (the replan moved it). Returns the plan, kept tasks first, and the tasks
/// kept (`replan-keeps-pending`). Task ids are the tasks' keys, so each keeps its own and a new
/// call whose id a kept task holds gets the next free one: the model's ids stay as it wrote them.
pub(crate) fn with_pending_kept(
    calls: Vec<Call>,
    pending: &[Call],
    available: &[String],
) -> (Vec<Call>, Vec<Call>) {
    let given_out = |old: &Call| {
        calls.iter().any(|new| {
            let moved = matches!(old.action, ActionName::Goto | ActionName::StartTracking)
                && new.action == old.action
                && new.target == old.target
                && new.xyz == old.xyz;
            moved || same_work(new) == same_work(old)
        })
    };
    let kept: Vec<Call> = (pending.iter())
        .filter(|old| available.contains(&old.drone) && !given_out(old))
        .cloned()
        .collect();
    let number = |c: &Call| c.task.strip_prefix('T').and_then(|n| n.parse::<u32>().ok());
    let mut next = kept
        .iter()
        .chain(&calls)
        .filter_map(number)
        .max()
        .unwrap_or(0)
        + 1;
    let mut plan = kept.clone();
    for mut call in calls {
        if plan.iter().any(|c| c.task == call.task) {
            call.task = format!("T{next}");
            next += 1;
        }
        plan.push(call);
    }
    (plan, kept)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_replan_keeps_the_pending_work_it_does_not_give_out() {
        let call = Call::named;
        let pending = vec![
            call("T2", "bravo", ActionName::Goto, "car_2"),
            call("T4", "bravo", ActionName::Goto, "car_4"),
            call("T5", "charlie", ActionName::Goto, "car_5"),
            call("T6", "delta", ActionName::Goto, "car_6"),
        ];
        // Alfa's car_1 and car_3 handed on; car_4 moved from bravo to charlie; delta is gone.
        let replan = vec![
            call("T1", "charlie", ActionName::Goto, "car_1"),
            call("T2", "bravo", ActionName::Goto, "car_3"),
            call("T3", "charlie", ActionName::Goto, "car_4"),
        ];
        let available = ["bravo".to_owned(), "charlie".to_owned()];
        let (plan, kept) = with_pending_kept(replan, &pending, &available);
        let text: Vec<String> = plan.iter().map(Call::to_string).collect();
        assert_eq!(
            text,
            [
                "T2 bravo goto(car_2)",
                "T5 charlie goto(car_5)",
                "T1 charlie goto(car_1)",
                "T6 bravo goto(car_3)",
                "T3 charlie goto(car_4)",
            ]
        );
        assert_eq!(kept, [pending[0].clone(), pending[2].clone()]);
        // A replan that gives everything out again keeps nothing.
        let (plan, kept) = with_pending_kept(pending.clone(), &pending, &available);
        assert!(kept.is_empty());
        assert_eq!(plan.len(), 4);
    }

    #[test]
    fn work_repeated_in_a_row_is_one_task() {
        let call = Call::named;
        let plan = vec![
            call("T1", "alfa", ActionName::Goto, "villa"),
            call("T2", "bravo", ActionName::Goto, "villa"),
            call("T3", "alfa", ActionName::Goto, "villa"),
            call("T4", "alfa", ActionName::Goto, "small_park"),
            call("T5", "alfa", ActionName::Goto, "villa"),
            call("T6", "alfa", ActionName::Goto, "villa"),
        ];
        let (kept, dropped) = without_repeated_work(plan);
        let tasks = |calls: &[Call]| calls.iter().map(|c| c.task.clone()).collect::<Vec<_>>();
        // Bravo's goto between alfa's two does not separate them; small_park does (out and back).
        assert_eq!(tasks(&kept), ["T1", "T2", "T4", "T5"]);
        assert_eq!(tasks(&dropped), ["T3", "T6"]);
    }

    #[test]
    fn a_replan_repeating_a_running_task_keeps_it_running_as_it_was_sent() {
        let goto = |task: &str, drone: &str, place: &str| {
            Call::named(task, drone, ActionName::Goto, place)
        };
        let drone = tacos_shared::DroneId::new("alfa").expect("valid");
        let mut book = PlanBook {
            plan: Some(ActivePlan {
                reasoning: "old".into(),
                tasks: vec![PlanTask {
                    call: goto("T1", "alfa", "car_3"),
                    status: TaskStatus::Running,
                    sent: Some((drone.clone(), 9)),
                    failures: 1,
                }],
                cycles: 4,
                stuck_since: None,
            }),
            mnl: Default::default(),
        };
        // The replan names it under another task id, and adds bravo's.
        let calls = vec![goto("T7", "alfa", "car_3"), goto("T8", "bravo", "car_4")];
        let effects = adopt(&mut book, "new".into(), calls.clone());
        let plan = book.plan.expect("adopted");
        assert_eq!(plan.cycles, 0);
        assert_eq!(
            plan.tasks[0],
            PlanTask {
                call: calls[0].clone(),
                status: TaskStatus::Running,
                sent: Some((drone, 9)),
                failures: 1,
            }
        );
        assert_eq!(plan.tasks[1].status, TaskStatus::NotStarted);
        assert_eq!(
            effects,
            [
                Effect::Remember(HistoryEntry::Plan {
                    reasoning: "new".into(),
                    plan: calls,
                }),
                Effect::WorkReplaced,
                Effect::Note(Record::PlanAdopted {
                    reasoning: "new".into(),
                    tasks: plan.tasks.clone(),
                }),
            ]
        );
    }

    #[test]
    fn a_grounded_drone_sent_somewhere_gets_the_take_off_its_plan_forgot() {
        let calls = vec![
            Call::named("T1", "alfa", ActionName::Goto, "car_3"),
            Call::named("T2", "alfa", ActionName::Goto, "car_4"),
            Call::named("T3", "bravo", ActionName::Goto, "car_5"),
        ];
        // alfa is on the ground, bravo flying.
        let (out, effects) = with_implied_takeoffs(calls, &["alfa".to_owned()]);
        let texts: Vec<String> = out.iter().map(ToString::to_string).collect();
        assert_eq!(
            texts,
            [
                "T4 alfa arm_takeoff()",
                "T1 alfa goto(car_3)",
                "T2 alfa goto(car_4)",
                "T3 bravo goto(car_5)"
            ]
        );
        let text = "T1 alfa goto(car_3): alfa is on the ground and the plan never takes it off: \
                    added T4 alfa arm_takeoff()";
        assert_eq!(
            effects,
            [
                Effect::Note(Record::AidFired {
                    aid: Aid::ImpliedTakeoffs,
                    detail: text.into(),
                }),
                Effect::Tell(MissionUpdate::Event {
                    topic: EventTopic::Note,
                    text: text.into(),
                }),
            ]
        );
    }
}

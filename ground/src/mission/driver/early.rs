//! A cycle's calls sent while the rest of its reply is still being written. The Supervisor's
//! (and the monolithic model's) schema puts the calls in a list after the reasoning; each call
//! is complete long before the reply is, and a small model on a CPU writes for seconds more.
//! So each call is judged as soon as it is whole in the streamed reply — the same checks as the
//! whole reply (one call per drone, among the startable calls, the live checks and the safety
//! gate) — and those that pass go to the core, which checks them with the gate again against
//! the swarm as it is then and has them sent (`core::cycle_reply`). The whole reply is still judged when it is in; the
//! calls already sent are not sent again.

use super::Mission;
use crate::mission::core::{Input, first_call_per_drone};
use crate::safety::CheckedAction;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tacos_prompts::Call;
use tacos_prompts::partial::partial_reply;
use tokio::sync::mpsc;

/// A call that passed the checks while its reply was still being written.
pub(super) struct EarlyCall {
    pub(super) call: Call,
    pub(super) checked: CheckedAction,
    /// How long after the call started it was complete.
    pub(super) after: Duration,
}

/// Told the reply's text each time it grows (see `Caller::on_written`).
pub(super) type OnWritten = Arc<dyn Fn(&str) + Send + Sync>;

/// The engine's side of a cycle call's early calls.
pub(super) struct EarlyCalls {
    /// `None` once the call's task has let go of its end.
    calls: Option<mpsc::UnboundedReceiver<EarlyCall>>,
}

impl EarlyCalls {
    /// The next early call; `None` when there will be no more.
    pub(super) async fn next(&mut self) -> Option<EarlyCall> {
        let call = match self.calls.as_mut() {
            Some(calls) => calls.recv().await,
            None => std::future::pending().await,
        };
        if call.is_none() {
            self.calls = None;
        }
        call
    }
}

/// What the hook has seen of a reply: the calls it handed on, and the calls it judged (each is
/// judged once). Shared with the whole reply's check, which leaves the drones handed on out
/// (their call is the engine's already, and the drone busy with it would make the same call
/// look like a repeat) and refuses their tasks to any other drone.
#[derive(Clone, Default)]
pub(super) struct Seen(Arc<Mutex<(Vec<Call>, Vec<String>)>>);

impl Seen {
    /// The calls handed on.
    pub(super) fn handed_on(&self) -> Vec<Call> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).0.clone()
    }
}

/// A hook for a cycle call, what it has seen, and the engine's end of what it finds. `judge`
/// keeps the calls that pass the whole reply's checks (with their checked actions).
pub(super) fn early_calls(
    judge: impl Fn(&[Call]) -> Vec<(Call, CheckedAction)> + Send + Sync + 'static,
) -> (OnWritten, Seen, EarlyCalls) {
    let (tx, rx) = mpsc::unbounded_channel();
    let started = Instant::now();
    let seen = Seen::default();
    let shared = seen.clone();
    let hook = move |content: &str| {
        let calls = partial_reply(content).calls;
        if calls.is_empty() {
            return;
        }
        let mut seen = shared.0.lock().unwrap_or_else(|e| e.into_inner());
        let (firsts, _) = first_call_per_drone(&calls);
        // Not a drone or a task handed on already: a task goes to one drone (the whole reply's
        // check says why when it comes).
        let fresh: Vec<Call> = firsts
            .into_iter()
            .filter(|c| {
                !seen
                    .0
                    .iter()
                    .any(|h| h.drone == c.drone || h.task == c.task)
                    && !seen.1.contains(&c.to_string())
            })
            .collect();
        if fresh.is_empty() {
            return;
        }
        seen.1.extend(fresh.iter().map(ToString::to_string));
        for (call, checked) in judge(&fresh) {
            seen.0.push(call.clone());
            let after = started.elapsed();
            let _ = tx.send(EarlyCall {
                call,
                checked,
                after,
            });
        }
    };
    let early = EarlyCalls { calls: Some(rx) };
    (Arc::new(hook), seen, early)
}

impl Mission {
    /// A call that passed while its reply is still being written: the core sends it if its
    /// work is still current, with the gate's check again (`Input::EarlyCall`).
    pub(super) fn send_early(&mut self, early: EarlyCall) {
        self.step(Input::EarlyCall {
            call: early.call,
            checked: early.checked,
            after: early.after,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::safety::SafetyGate;
    use crate::swarm::{SwarmView, test_status};
    use tacos_shared::DroneMode;
    use tacos_shared::action::Action;
    use tacos_shared::scenario::Scenario;

    fn flying(view: &mut SwarmView, id: &str, now: Instant) {
        view.apply_status(test_status(id, DroneMode::Flying), now);
    }

    fn call(task: &str, drone: &str) -> String {
        format!(
            r#"{{"task":"{task}","drone":"{drone}","action":"goto","target":"car_11","xyz":null}}"#
        )
    }

    /// A failed task may go to any drone, so a model can offer it to two at once: the first
    /// call handed on takes it, and the other drone's call of that task is not handed on.
    #[test]
    fn a_task_handed_on_is_not_handed_on_again_for_another_drone() {
        let gate = SafetyGate::new(Scenario::builtin("city").expect("city"));
        let now = Instant::now();
        let mut view = SwarmView::default();
        flying(&mut view, "alfa", now);
        flying(&mut view, "bravo", now);
        flying(&mut view, "charlie", now);
        // Every call passes; what is tested is which calls reach the judge and the engine.
        let judge = move |calls: &[Call]| {
            calls
                .iter()
                .filter_map(|c| {
                    let checked = gate.check(&view, &c.drone, &Action::Hold, now).ok()?;
                    Some((c.clone(), checked))
                })
                .collect()
        };
        let (hook, seen, mut early) = early_calls(judge);
        let head = r#"{"reasoning":"Go.","actions":["#;
        hook(&format!("{head}{},", call("T2", "alfa")));
        hook(&format!(
            "{head}{},{},",
            call("T2", "alfa"),
            call("T2", "bravo")
        ));
        hook(&format!(
            "{head}{},{},{},",
            call("T2", "alfa"),
            call("T2", "bravo"),
            call("T3", "charlie")
        ));
        let handed: Vec<String> = seen.handed_on().iter().map(ToString::to_string).collect();
        assert_eq!(
            handed,
            ["T2 alfa goto(car_11)", "T3 charlie goto(car_11)"],
            "bravo's T2 was handed on beside alfa's"
        );
        let mut sent = Vec::new();
        while let Some(rx) = early.calls.as_mut() {
            match rx.try_recv() {
                Ok(c) => sent.push(c.call.to_string()),
                Err(_) => break,
            }
        }
        assert_eq!(sent, handed);
    }
}

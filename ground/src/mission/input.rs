//! Where the pilot's lines enter a running mission. The engine reads lines only between model
//! calls, which take minutes with a small model; a pilot's `land all` must not wait for that.
//! So direct commands (`directives`) are carried out here, at once — through the safety gate and
//! the link like every action — and the engine is told through an override signal: it refuses
//! to send anything a model proposed before the command and drops its plan. Every other line is
//! queued for the engine.

use super::directives::{self, Directive};
use super::log::{MissionLog, Record};
use super::report::{EventTopic, MissionUpdate};
use crate::link::GroundLink;
use crate::safety::SafetyGate;
use std::sync::Arc;
use std::time::Duration;
use tacos_shared::DroneId;
use tacos_shared::action::Action;
use tacos_shared::messages::ActionState;
use tokio::sync::{mpsc, watch};

/// How long the outcome of a direct command's action is followed for the log (a landing from
/// the top of the city's bounds takes a few minutes).
const OUTCOME_WAIT: Duration = Duration::from_secs(300);

/// The mission no longer takes lines (it ended).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the mission no longer takes lines")]
pub struct InputClosed;

/// The pilot's side: submit lines. Cheap to clone.
#[derive(Clone)]
pub struct PilotInput {
    lines: mpsc::Sender<String>,
    link: Arc<GroundLink>,
    gate: SafetyGate,
    log: Arc<MissionLog>,
    updates: mpsc::UnboundedSender<MissionUpdate>,
    overrides: Arc<watch::Sender<u64>>,
}

/// The engine's side: the queued lines, and the count of direct commands carried out so far.
pub struct MissionInputs {
    pub lines: mpsc::Receiver<String>,
    pub overrides: watch::Receiver<u64>,
}

impl PilotInput {
    /// A pilot input and the inputs to hand to [`crate::mission::Mission::run_with`].
    pub fn new(
        link: Arc<GroundLink>,
        gate: SafetyGate,
        log: Arc<MissionLog>,
        updates: mpsc::UnboundedSender<MissionUpdate>,
    ) -> (PilotInput, MissionInputs) {
        let (lines_tx, lines) = mpsc::channel(16);
        let (overrides_tx, overrides) = watch::channel(0);
        (
            PilotInput {
                lines: lines_tx,
                link,
                gate,
                log,
                updates,
                overrides: Arc::new(overrides_tx),
            },
            MissionInputs { lines, overrides },
        )
    }

    /// A direct command, if `text` is one for this swarm.
    pub fn directive(&self, text: &str) -> Option<Directive> {
        directives::parse(text, &self.gate.scenario().slot_ids())
    }

    /// Submits one line: a direct command is carried out before this returns; anything else
    /// is queued for the engine (waiting while the queue is full).
    pub async fn submit(&self, text: &str) -> Result<(), InputClosed> {
        let text = text.trim();
        if text.is_empty() {
            return Ok(());
        }
        if self.lines.is_closed() {
            return Err(InputClosed);
        }
        match self.directive(text) {
            Some(directive) => {
                self.execute(text, directive).await;
                Ok(())
            }
            None => self
                .lines
                .send(text.to_owned())
                .await
                .map_err(|_| InputClosed),
        }
    }

    /// Whether the engine has gone.
    pub fn is_closed(&self) -> bool {
        self.lines.is_closed()
    }

    /// Checks and sends the command's actions, logs them, and raises the override. The
    /// override goes up first, so an action a model proposed cannot slip in after the command.
    /// `land all` and `hold all` go to every drone the ground knows of (a drone that fell
    /// silent is the one most likely in trouble), all at once: each drone's put runs
    /// concurrently, so one slow drone does not hold back the others.
    async fn execute(&self, text: &str, directive: Directive) {
        self.overrides.send_modify(|n| *n += 1);
        let known = || {
            self.link
                .view()
                .drones()
                .map(|d| d.id.to_string())
                .collect::<Vec<_>>()
        };
        let (targets, action) = match directive {
            Directive::LandAll => (known(), Action::Land),
            Directive::HoldAll => (known(), Action::Hold),
            Directive::Land(d) => (vec![d], Action::Land),
            Directive::Hold(d) => (vec![d], Action::Hold),
        };
        // One line for the whole command: with twenty drones, a line per drone would flood
        // the pilot's event log (the mission log keeps each action).
        let mut outcomes = Vec::new();
        let mut checked_all = Vec::new();
        {
            let view = self.link.view();
            let now = self.link.clock().instant();
            for drone in &targets {
                match self.gate.check(&view, drone, &action, now) {
                    Ok(c) => checked_all.push(c),
                    Err(r) => outcomes.push(format!("{drone}: refused: {r}")),
                }
            }
        }
        let sends = checked_all
            .iter()
            .map(|checked| async move { (checked, self.link.send(checked, None).await) });
        let mut sent = Vec::new();
        let mut records = Vec::new();
        for (checked, result) in futures_util::future::join_all(sends).await {
            let drone = checked.drone().to_string();
            match result {
                Ok(seq) => {
                    self.follow_outcome(checked.drone().clone(), action.to_string(), seq);
                    records.push(Record::action_sent(checked, None, seq));
                    sent.push(drone);
                }
                Err(e) => outcomes.push(format!("{drone}: {e}")),
            }
        }
        if !sent.is_empty() {
            outcomes.insert(0, format!("{action} sent to {}", sent.join(", ")));
        }
        let outcome = outcomes.join("; ");
        records.push(Record::Direct {
            text: text.to_owned(),
            outcome: outcome.clone(),
        });
        // Every send of the command and the command itself on the disk with one sync (20 syncs
        // one by one held `land all` for 70 ms here).
        self.log.note_all(records);
        let _ = self.updates.send(MissionUpdate::Event {
            topic: EventTopic::Direct,
            text: format!("direct command {text:?}: {outcome}"),
        });
    }

    /// Logs the outcome of a direct command's action when it comes (the engine only follows
    /// the actions of its plans); tells the pilot when it did not finish well.
    fn follow_outcome(&self, drone: DroneId, action: String, seq: u64) {
        let (link, log, updates) = (self.link.clone(), self.log.clone(), self.updates.clone());
        tokio::spawn(async move {
            let (outcome, failed) = match link.wait_outcome(&drone, seq, OUTCOME_WAIT).await {
                Ok(ActionState::Done) => ("done".to_owned(), false),
                Ok(ActionState::Failed(why)) => (format!("failed: {why}"), true),
                Ok(ActionState::Running { .. }) => ("still running".to_owned(), true),
                Err(e) => (format!("unknown: {e}"), true),
            };
            log.note(Record::ActionOutcome {
                drone: drone.to_string(),
                task: None,
                seq,
                outcome: outcome.clone(),
            });
            // The swarm table shows each drone's action and state; only what went wrong is
            // worth an event line.
            if outcome == "done" {
                return;
            }
            let _ = updates.send(MissionUpdate::Outcome {
                drone: drone.to_string(),
                action,
                outcome,
                failed,
            });
        });
    }
}

//! Carrying out the pilot's direct commands (`directives`), at once and without a model, through
//! the safety gate and the link like every action. Each raises the override first, so an action
//! a model proposed before the command cannot slip in after it, and the engine drops its plan.
//!
//! `cancel` and `undo` work from the memory of the last instruction the models carried out
//! (`undo`), which the engine keeps up to date through [`DirectCommands::begin_instruction`] and
//! [`DirectCommands::moved`].

use super::directives::Directive;
use super::log::{MissionLog, Record};
use super::report::{EventTopic, MissionUpdate};
use super::undo::{Before, InstructionMemory, UndoStep, undo_steps};
use crate::link::GroundLink;
use crate::safety::{CheckedAction, SafetyGate};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tacos_shared::action::Action;
use tacos_shared::messages::ActionState;
use tacos_shared::{DroneId, DroneMode};
use tokio::sync::{mpsc, watch};

/// How long the outcome of a direct command's action is followed (a landing from the top of the
/// city's bounds takes a few minutes).
const OUTCOME_WAIT: Duration = Duration::from_secs(300);

/// The direct commands of one mission. Cheap to clone.
#[derive(Clone)]
pub struct DirectCommands {
    link: Arc<GroundLink>,
    gate: SafetyGate,
    log: Arc<MissionLog>,
    updates: mpsc::UnboundedSender<MissionUpdate>,
    overrides: Arc<watch::Sender<u64>>,
    memory: Arc<Mutex<InstructionMemory>>,
}

impl DirectCommands {
    /// The commands, and the override count the engine watches.
    pub fn new(
        link: Arc<GroundLink>,
        gate: SafetyGate,
        log: Arc<MissionLog>,
        updates: mpsc::UnboundedSender<MissionUpdate>,
    ) -> (DirectCommands, watch::Receiver<u64>) {
        let (overrides, overrides_rx) = watch::channel(0);
        let commands = DirectCommands {
            link,
            gate,
            log,
            updates,
            overrides: Arc::new(overrides),
            memory: Arc::default(),
        };
        (commands, overrides_rx)
    }

    fn memory(&self) -> MutexGuard<'_, InstructionMemory> {
        // The memory holds plain values: one left half-updated by a panic is still usable.
        self.memory.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The engine took an instruction for the models: remember where every drone is now.
    pub fn begin_instruction(&self, text: &str) {
        let before: BTreeMap<DroneId, Before> = {
            let view = self.link.view();
            view.drones()
                .filter_map(|entry| {
                    let status = entry.status.as_ref()?;
                    let airborne = match status.mode {
                        DroneMode::Flying | DroneMode::Tracking => true,
                        DroneMode::Idle => false,
                        DroneMode::Unavailable => return None,
                    };
                    let before = Before {
                        position: status.position,
                        airborne,
                    };
                    Some((entry.id.clone(), before))
                })
                .collect()
        };
        self.memory().begin(text, before);
    }

    /// The engine sent an action of the current instruction to `drone`.
    pub fn moved(&self, drone: &DroneId) {
        self.memory().moved(drone);
    }

    /// Checks and sends the command's actions, logs them, and tells the pilot in one line.
    pub async fn execute(&self, text: &str, directive: Directive) {
        self.overrides.send_modify(|n| *n += 1);
        let lands = matches!(directive, Directive::LandAll | Directive::Land(_));
        let outcome = match directive {
            Directive::LandAll => self.to_each(self.known(), Action::Land).await,
            Directive::HoldAll => self.to_each(self.known(), Action::Hold).await,
            Directive::Land(d) => self.to_each(vec![d], Action::Land).await,
            Directive::Hold(d) => self.to_each(vec![d], Action::Hold).await,
            Directive::Cancel => self.cancel().await,
            Directive::Undo => self.undo().await,
        };
        if lands {
            // A landing is the pilot's call for safety: `undo` must not take drones up again.
            self.memory().closed = Some("was followed by a landing");
        }
        self.log.note(Record::Direct {
            text: text.to_owned(),
            outcome: outcome.clone(),
        });
        let _ = self.updates.send(MissionUpdate::Event {
            topic: EventTopic::Direct,
            text: format!("direct command {text:?}: {outcome}"),
        });
    }

    /// Every drone the ground knows of (a drone that fell silent is the one most likely in
    /// trouble).
    fn known(&self) -> Vec<String> {
        self.link
            .view()
            .drones()
            .map(|d| d.id.to_string())
            .collect()
    }

    /// Sends `action` to each drone, all at once: each put runs concurrently, so one slow drone
    /// does not hold back the others. One line for them all: with twenty drones, a line per drone
    /// would flood the pilot's event log (the mission log keeps each action).
    async fn to_each(&self, drones: Vec<String>, action: Action) -> String {
        let mut outcomes = Vec::new();
        let mut checked_all = Vec::new();
        {
            let view = self.link.view();
            let now = self.link.clock().instant();
            for drone in &drones {
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
        if outcomes.is_empty() {
            outcomes.push("no drone to send it to".into());
        }
        // Every send on the disk with one sync (20 syncs one by one held `land all` for 70 ms).
        self.log.note_all(records);
        outcomes.join("; ")
    }

    /// Ends the current plan (the override does that) and holds the drones of the last
    /// instruction that are still carrying out an action.
    async fn cancel(&self) -> String {
        let (instruction, moved) = {
            let memory = self.memory();
            (memory.instruction.clone(), memory.moved.clone())
        };
        let Some(instruction) = instruction else {
            return "nothing to cancel: no instruction has been given yet".into();
        };
        let moving: Vec<String> = {
            let view = self.link.view();
            moved
                .iter()
                .filter(|d| {
                    view.get(d).is_some_and(|e| {
                        e.busy()
                            && e.status.as_ref().is_some_and(|s| {
                                matches!(s.mode, DroneMode::Flying | DroneMode::Tracking)
                            })
                    })
                })
                .map(|d| d.to_string())
                .collect()
        };
        if moving.is_empty() {
            return format!("{instruction:?} cancelled; none of its drones was still moving");
        }
        let held = self.to_each(moving, Action::Hold).await;
        format!("{instruction:?} cancelled: {held}")
    }

    /// Flies each drone the last instruction moved back to where it was before it, one step at a
    /// time, each through the gate; a later direct command or instruction stops what is left.
    async fn undo(&self) -> String {
        let (instruction, before, moved, generation) = {
            let mut memory = self.memory();
            if let Some(why) = memory.nothing_to_undo() {
                return why;
            }
            memory.closed = Some("was undone already");
            (
                memory.instruction.clone().unwrap_or_default(),
                memory.before.clone(),
                memory.moved.clone(),
                memory.generation,
            )
        };
        let epoch = *self.overrides.borrow();
        let mut lines = Vec::new();
        for drone in moved {
            let Some(before) = before.get(&drone) else {
                lines.push(format!("{drone}: joined after it, left where it is"));
                continue;
            };
            let now = {
                let view = self.link.view();
                let now = self.link.clock().instant();
                view.get(&drone).and_then(|e| {
                    let mode = e.effective_mode(now);
                    let status = e.status.as_ref()?;
                    Some((mode, status.position))
                })
            };
            let Some((mode, position)) = now.filter(|(m, _)| *m != DroneMode::Unavailable) else {
                lines.push(format!("{drone}: unavailable, not flown back"));
                continue;
            };
            let airborne = matches!(mode, DroneMode::Flying | DroneMode::Tracking);
            let steps = undo_steps(before, position, airborne);
            if steps.is_empty() {
                lines.push(format!("{drone}: already where it was"));
                continue;
            }
            let plan: Vec<String> = steps.iter().map(UndoStep::describe).collect();
            lines.push(format!("{drone}: {}", plan.join(", then ")));
            let commands = self.clone();
            tokio::spawn(async move {
                commands
                    .fly_back(drone, steps, Stamp { epoch, generation })
                    .await;
            });
        }
        format!("undoing {instruction:?}: {}", lines.join("; "))
    }

    /// Sends `steps` to `drone` one after another, each when the one before is done, while no
    /// later command came (`stamp`). What stops it is told to the pilot.
    async fn fly_back(&self, drone: DroneId, steps: Vec<UndoStep>, stamp: Stamp) {
        for step in steps {
            if let Some(why) = self.overtaken(stamp) {
                self.tell_undo(
                    &drone,
                    format!("stopped before \"{}\": {why}", step.describe()),
                );
                return;
            }
            let checked = match self.check_step(&drone, step) {
                Ok(checked) => checked,
                Err(why) => {
                    self.tell_undo(&drone, why);
                    return;
                }
            };
            let seq = match self.link.send(&checked, None).await {
                Ok(seq) => seq,
                Err(e) => {
                    self.tell_undo(&drone, format!("{} not sent: {e}", checked.action()));
                    return;
                }
            };
            self.log.note(Record::action_sent(&checked, None, seq));
            let (text, failed) = logged_outcome(&self.link, &self.log, &drone, seq).await;
            if failed {
                self.tell_undo(&drone, format!("{} {text}", checked.action()));
                return;
            }
        }
        self.tell_undo(&drone, "back where it was".into());
    }

    /// Why an undo's next step must not be sent: a direct command or an instruction came after.
    fn overtaken(&self, stamp: Stamp) -> Option<&'static str> {
        if *self.overrides.borrow() != stamp.epoch {
            return Some("a later direct command");
        }
        if self.memory().generation != stamp.generation {
            return Some("a later instruction");
        }
        None
    }

    /// The step as an action, checked at the gate against the swarm as it is now.
    fn check_step(&self, drone: &DroneId, step: UndoStep) -> Result<CheckedAction, String> {
        let view = self.link.view();
        let action = match step {
            UndoStep::TakeOff => Action::ArmTakeoff,
            UndoStep::Land => Action::Land,
            UndoStep::Goto(target) => Action::Goto { target },
            UndoStep::GotoAbove { x, y } => {
                let height = view
                    .get(drone)
                    .and_then(|e| e.status.as_ref())
                    .map(|s| s.position.z)
                    .ok_or_else(|| format!("no position heard from {drone}"))?;
                Action::Goto {
                    target: tacos_shared::Vec3::new(x, y, height),
                }
            }
        };
        self.gate
            .check(&view, drone.as_str(), &action, self.link.clock().instant())
            .map_err(|r| format!("{action} refused: {r}"))
    }

    fn tell_undo(&self, drone: &DroneId, what: String) {
        let text = format!("undo: {drone} {what}");
        self.log.note(Record::Event { text: text.clone() });
        let _ = self.updates.send(MissionUpdate::Event {
            topic: EventTopic::Direct,
            text,
        });
    }

    /// Logs the outcome of a direct command's action when it comes (the engine only follows
    /// the actions of its plans); tells the pilot when it did not finish well.
    fn follow_outcome(&self, drone: DroneId, action: String, seq: u64) {
        let (link, log, updates) = (self.link.clone(), self.log.clone(), self.updates.clone());
        tokio::spawn(async move {
            let (outcome, failed) = logged_outcome(&link, &log, &drone, seq).await;
            // The swarm table shows each drone's action and state; only what went wrong is
            // worth an event line.
            if !failed {
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

/// Waits for the outcome of a direct command's action `seq` on `drone` and logs it; returns it
/// as the log words it, and whether it did not finish well.
async fn logged_outcome(
    link: &GroundLink,
    log: &MissionLog,
    drone: &DroneId,
    seq: u64,
) -> (String, bool) {
    let (outcome, failed) = match link.wait_outcome(drone, seq, OUTCOME_WAIT).await {
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
        failure: failed.then(|| outcome.clone()),
    });
    (outcome, failed)
}

/// When an undo began: the override count and the instruction's generation.
#[derive(Debug, Clone, Copy)]
struct Stamp {
    epoch: u64,
    generation: u64,
}

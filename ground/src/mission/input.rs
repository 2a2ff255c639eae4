//! Where the pilot's lines enter a running mission. The engine reads lines only between model
//! calls, which take minutes with a small model; a pilot's `land all` must not wait for that.
//! So direct commands (`directives`) are carried out from here, at once (`commands`), and the
//! engine is told through an override signal: it refuses to send anything a model proposed
//! before the command and drops its plan. Every other line is queued for the engine.

use super::commands::DirectCommands;
use super::directives::{self, Directive};
use super::log::MissionLog;
use super::report::MissionUpdate;
use crate::link::GroundLink;
use crate::safety::SafetyGate;
use std::sync::Arc;
use tokio::sync::{mpsc, watch};

/// The mission no longer takes lines (it ended).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the mission no longer takes lines")]
pub struct InputClosed;

/// The pilot's side: submit lines. Cheap to clone.
#[derive(Clone)]
pub struct PilotInput {
    lines: mpsc::Sender<String>,
    gate: SafetyGate,
    commands: DirectCommands,
}

/// The engine's side: the queued lines, the count of direct commands carried out so far, and
/// the commands themselves (the engine keeps their memory of the last instruction).
pub struct MissionInputs {
    pub lines: mpsc::Receiver<String>,
    pub overrides: watch::Receiver<u64>,
    pub commands: DirectCommands,
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
        let (commands, overrides) = DirectCommands::new(link, gate.clone(), log, updates);
        (
            PilotInput {
                lines: lines_tx,
                gate,
                commands: commands.clone(),
            },
            MissionInputs {
                lines,
                overrides,
                commands,
            },
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
                self.commands.execute(text, directive).await;
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
}

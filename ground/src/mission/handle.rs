//! A running mission, as every front end starts one: the pilot's input (direct commands carried
//! out at once, other lines to the engine), the engine's updates, and the engine's task. The
//! terminal, the `--say` session, scripts and the evaluation all start it here.

use super::config::MissionConfig;
use super::driver::Mission;
use super::input::PilotInput;
use super::log::MissionLog;
use super::report::{MissionStats, MissionUpdate};
use crate::link::{GroundLink, LinkError};
use crate::safety::SafetyGate;
use crate::task_guard::AbortOnDrop;
use std::sync::Arc;
use std::time::Duration;
use tacos_llm::LlmBackend;
use tokio::sync::mpsc;

/// How long [`MissionTask::stats`] waits for the engine to end once its input has closed.
const END_WAIT: Duration = Duration::from_secs(5);

/// A mission started: its parts are used apart (the input by the terminal, the updates by a
/// runner), so they are public.
pub struct MissionHandle {
    pub input: PilotInput,
    pub updates: mpsc::UnboundedReceiver<MissionUpdate>,
    pub task: MissionTask,
}

/// The engine's task; dropping it stops the engine at once (every log record is written and
/// flushed synchronously, so stopping at an await point never cuts one short).
pub struct MissionTask(AbortOnDrop<MissionStats>);

impl MissionTask {
    /// The engine's end, however long it takes (a caller bounds it).
    pub async fn join(mut self) -> Result<MissionStats, tokio::task::JoinError> {
        (&mut self.0.0).await
    }

    /// The statistics once the engine ends, which it does when every copy of the input is
    /// dropped (a call in flight is dropped, counted). An engine that does not end within
    /// [`END_WAIT`], or panicked, reports none.
    pub async fn stats(self) -> MissionStats {
        match tokio::time::timeout(END_WAIT, self.join()).await {
            Ok(Ok(stats)) => stats,
            _ => MissionStats::default(),
        }
    }
}

impl MissionHandle {
    pub async fn start(
        cfg: MissionConfig,
        backend: Arc<dyn LlmBackend>,
        gate: SafetyGate,
        link: Arc<GroundLink>,
        log: Arc<MissionLog>,
    ) -> Result<MissionHandle, LinkError> {
        let (updates_tx, updates) = mpsc::unbounded_channel();
        let (input, inputs) =
            PilotInput::new(link.clone(), gate.clone(), log.clone(), updates_tx.clone());
        let mission = Mission::new(cfg, backend, gate, link, log, updates_tx).await?;
        let task = MissionTask(AbortOnDrop(tokio::spawn(mission.run_with(inputs))));
        Ok(MissionHandle {
            input,
            updates,
            task,
        })
    }
}

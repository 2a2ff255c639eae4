//! Actions issued without a model (the pilot's direct commands, the demo's fixed pattern):
//! each goes through the safety gate, all are sent at once, then their outcomes are awaited.

use crate::link::{GroundLink, LinkError};
use crate::safety::{Rejection, SafetyGate};
use std::time::Duration;
use tacos_shared::DroneId;
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionState, FailureReason};

#[derive(Debug, thiserror::Error)]
pub enum DirectError {
    #[error("the safety gate refused: {0}")]
    Refused(Rejection),
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error("{drone}: {action} failed: {reason}")]
    Failed {
        drone: DroneId,
        action: String,
        reason: FailureReason,
    },
}

/// Checks every action, sends those that pass (none if any is refused), and waits until every
/// one has finished; the first failure is returned.
pub async fn run_actions(
    link: &GroundLink,
    gate: &SafetyGate,
    actions: &[(DroneId, Action)],
    task_id: Option<&str>,
    timeout: Duration,
) -> Result<(), DirectError> {
    let checked = {
        let view = link.view();
        let now = link.clock().instant();
        actions
            .iter()
            .map(|(drone, action)| gate.check(&view, drone.as_str(), action, now))
            .collect::<Result<Vec<_>, _>>()
            .map_err(DirectError::Refused)?
    };
    let mut sent = Vec::with_capacity(checked.len());
    for c in &checked {
        sent.push((c, link.send(c, task_id.map(str::to_owned)).await?));
    }
    for (c, seq) in sent {
        // Outcomes are recorded by the link as they arrive, so waiting in turn loses nothing.
        match link.wait_outcome(c.drone(), seq, timeout).await? {
            ActionState::Failed(reason) => {
                return Err(DirectError::Failed {
                    drone: c.drone().clone(),
                    action: c.action().to_string(),
                    reason,
                });
            }
            ActionState::Done | ActionState::Running { .. } => {}
        }
    }
    Ok(())
}

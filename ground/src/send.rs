//! `tacos-ground send`: one action to one drone, as a pilot flies by hand. It waits for the drone
//! (a ground just (re)started, a drone still reconnecting), then for the drone to follow this
//! ground station (a drone takes over a silent ground's place only after its failsafe hold
//! time), then checks the action at the safety gate, sends it and waits for its outcome.

use crate::link::{GroundLink, LinkError};
use crate::safety::SafetyGate;
use std::time::Duration;
use tacos_shared::DroneId;
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionState, DroneStatus};
use tokio::time::Instant;

/// How long `send` waits for the drone to be heard and to follow it, and then for the outcome.
#[derive(Debug, Clone, Copy)]
pub struct SendWaits {
    pub drone: Duration,
    pub outcome: Duration,
}

#[derive(Debug, thiserror::Error)]
pub enum SendError {
    #[error(
        "{drone} was not heard within {waited:.0} s (heard: {heard}); is its onboard running and on this swarm ({swarm}/)?"
    )]
    NotHeard {
        drone: DroneId,
        waited: f64,
        heard: String,
        swarm: String,
    },
    #[error("{0} is heard but has no link to its autopilot (is its tacos-px4 running?)")]
    NoAutopilot(DroneId),
    #[error(
        "{drone} still follows another ground station ({followed}) after {waited:.0} s: that one is still beating; stop it, or send through it"
    )]
    OtherGround {
        drone: DroneId,
        followed: u64,
        waited: f64,
    },
    #[error("refused by the safety gate: {0}")]
    Refused(crate::safety::Rejection),
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error("{drone}: {action} failed: {why}")]
    Failed {
        drone: DroneId,
        action: Action,
        why: tacos_shared::messages::FailureReason,
    },
    #[error("{drone}: {action} did not finish")]
    Unfinished { drone: DroneId, action: Action },
}

/// Sends `action` to `drone` over `link` and waits for it to end; `say` gets the progress
/// lines a pilot reads (waiting, sent, done).
pub async fn send(
    link: &GroundLink,
    gate: &SafetyGate,
    waits: SendWaits,
    drone: &DroneId,
    action: &Action,
    say: impl Fn(String),
) -> Result<(), SendError> {
    let started = Instant::now();
    let deadline = started + waits.drone;
    let one = std::slice::from_ref(drone);
    let left = || deadline.saturating_duration_since(Instant::now());
    if link
        .wait_for_drones(one, Duration::from_secs(1), |_| true)
        .await
        .is_err()
    {
        say(format!(
            "waiting up to {:.0} s for {drone} to be heard…",
            waits.drone.as_secs_f64()
        ));
        if link.wait_for_drones(one, left(), |_| true).await.is_err() {
            let heard: Vec<String> = link.view().drones().map(|e| e.id.to_string()).collect();
            return Err(SendError::NotHeard {
                drone: drone.clone(),
                waited: waits.drone.as_secs_f64() + 1.0,
                heard: if heard.is_empty() {
                    "none".to_owned()
                } else {
                    heard.join(", ")
                },
                swarm: link.keys().prefix().to_owned(),
            });
        }
    }
    // A drone's first statuses may precede its autopilot link.
    if link
        .wait_for_drones(one, left(), |s| s.autopilot_link)
        .await
        .is_err()
    {
        return Err(SendError::NoAutopilot(drone.clone()));
    }
    let ours = |s: &DroneStatus| s.ground == Some(link.epoch());
    if link
        .wait_for_drones(one, Duration::from_secs(1), ours)
        .await
        .is_err()
    {
        say(format!(
            "waiting for {drone} to follow this ground station (it follows the last one until that has been silent for its failsafe hold time)…"
        ));
        if link.wait_for_drones(one, left(), ours).await.is_err() {
            let followed = link
                .view()
                .get(drone)
                .and_then(|e| e.status.as_ref())
                .and_then(|s| s.ground)
                .unwrap_or_default();
            return Err(SendError::OtherGround {
                drone: drone.clone(),
                followed,
                waited: started.elapsed().as_secs_f64(),
            });
        }
    }
    say(format!(
        "{drone} follows this ground station ({:.1} s after start)",
        started.elapsed().as_secs_f64()
    ));
    let checked = {
        let view = link.view();
        gate.check(&view, drone.as_str(), action, link.clock().instant())
    }
    .map_err(SendError::Refused)?;
    let seq = link.send(&checked, None).await?;
    say(format!("sent #{seq} {action} to {drone}"));
    match link.wait_outcome(drone, seq, waits.outcome).await? {
        ActionState::Done => {
            say(format!("{drone}: {action} done"));
            Ok(())
        }
        ActionState::Failed(why) => Err(SendError::Failed {
            drone: drone.clone(),
            action: action.clone(),
            why,
        }),
        ActionState::Running { .. } => Err(SendError::Unfinished {
            drone: drone.clone(),
            action: action.clone(),
        }),
    }
}

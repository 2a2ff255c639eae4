//! The shell's side of the ground stations: which one is followed, how long it has been silent,
//! and the refusals the status tells. Heartbeats are taken in here both from their `select!`
//! branch and, before the control tick judges the silence, from whatever is still queued.

use super::Malformed;
use crate::executor::Executor;
use crate::failsafe::FailsafeTimer;
use crate::ground_follow::{Beat, GroundFollower};
use tacos_shared::messages::{ActionRefused, GroundHeartbeat};
use tracing::{info, warn};
use zenoh::sample::Sample;

pub(super) struct GroundSide {
    pub grounds: GroundFollower,
    pub failsafe: FailsafeTimer,
    /// The latest action of the followed ground refused for arriving late, told in the status.
    pub refused: Option<ActionRefused>,
    /// The other ground station last refused, logged once (heartbeats come several a second).
    refused_ground: Option<u64>,
    malformed: Malformed,
}

impl GroundSide {
    pub fn new(grounds: GroundFollower, failsafe: FailsafeTimer) -> Self {
        GroundSide {
            grounds,
            failsafe,
            refused: None,
            refused_ground: None,
            malformed: Malformed::new("ground heartbeat"),
        }
    }

    /// Takes in one heartbeat sample heard at `t`. True when the status should go out at once
    /// (another ground station is now followed).
    pub fn on_heartbeat(&mut self, sample: &Sample, executor: &mut Executor, t: f64) -> bool {
        let beat = match tacos_bus::decode::<GroundHeartbeat>(sample) {
            Ok(beat) => beat,
            Err(e) => {
                self.malformed.note(&e);
                return false;
            }
        };
        let mut publish = false;
        match self.grounds.on_heartbeat(beat.ground, beat.stamp, t) {
            Beat::Refused { followed } => {
                if self.refused_ground != Some(beat.ground) {
                    self.refused_ground = Some(beat.ground);
                    warn!(
                        other = beat.ground,
                        followed,
                        "a second ground station is beating while the followed one is: it is refused until the followed one falls silent"
                    );
                }
                return false;
            }
            Beat::Adopted { previous } => {
                info!(ground = beat.ground, ?previous, "following ground station");
                // A late refusal names an action of the ground followed before.
                self.refused = None;
                publish = true;
            }
            Beat::Followed => {}
        }
        // At once, not at the next tick: an action that follows the beat must not meet a
        // failsafe the beat has just ended.
        self.failsafe.heard(t);
        if executor.failsafe().is_some() {
            executor.set_failsafe(self.failsafe.stage(t), t);
            info!("ground heard again: failsafe cleared");
        }
        publish
    }
}

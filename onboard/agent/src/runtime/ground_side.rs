//! The shell's side of the ground stations: which one is followed, how long it has been silent,
//! its actions and the refusals the status tells. Both kinds of message are taken in on zenoh's
//! receiving thread as they arrive (see `shared_core`), so an action is judged after every
//! heartbeat that came before it.

use super::Malformed;
use crate::executor::Executor;
use crate::failsafe::FailsafeTimer;
use crate::ground_follow::{Beat, GroundFollower, Refusal};
use tacos_shared::ActionCommand;
use tacos_shared::codec::CodecError;
use tacos_shared::messages::{ActionRefused, GroundHeartbeat};
use tracing::{info, warn};

pub(super) struct GroundSide {
    pub grounds: GroundFollower,
    pub failsafe: FailsafeTimer,
    /// The latest action of the followed ground refused for arriving late, told in the status.
    pub refused: Option<ActionRefused>,
    /// Actions that could not be decoded, told in the status.
    pub malformed_actions: u64,
    /// The other ground station last refused, logged once (heartbeats come several a second).
    refused_ground: Option<u64>,
    malformed_beats: Malformed,
}

impl GroundSide {
    pub fn new(grounds: GroundFollower, failsafe: FailsafeTimer) -> Self {
        GroundSide {
            grounds,
            failsafe,
            refused: None,
            malformed_actions: 0,
            refused_ground: None,
            malformed_beats: Malformed::new("ground heartbeat"),
        }
    }

    /// Takes in one heartbeat heard at `t`. True when the status should go out at once
    /// (another ground station is now followed).
    pub fn on_heartbeat(
        &mut self,
        beat: Result<GroundHeartbeat, CodecError>,
        executor: &mut Executor,
        t: f64,
    ) -> bool {
        let beat = match beat {
            Ok(beat) => beat,
            Err(e) => {
                self.malformed_beats.note(&e);
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

    /// Takes in one action heard at `t`: admitted from the followed ground and handed to the
    /// executor, or refused. True when the status should go out at once (the executor took
    /// it, a late refusal to tell, a malformed action counted).
    pub fn on_action(
        &mut self,
        command: Result<ActionCommand, CodecError>,
        executor: &mut Executor,
        t: f64,
    ) -> bool {
        let command = match command {
            Ok(command) => command,
            Err(e) => {
                self.malformed_actions += 1;
                warn!(error = %e, count = self.malformed_actions, "malformed action ignored");
                return true;
            }
        };
        match self.grounds.admit(&command, t) {
            Ok(()) => {
                let taken = executor.on_command(&command, t);
                if taken {
                    info!(seq = command.seq, action = %command.action, "action received");
                }
                taken
            }
            Err(refusal) => {
                warn!(seq = command.seq, action = %command.action, "action refused: {refusal}");
                match refusal {
                    Refusal::Late(why) => {
                        self.refused = Some(ActionRefused {
                            seq: command.seq,
                            why,
                        });
                        true
                    }
                    Refusal::OtherGround { .. } | Refusal::Stale { .. } => false,
                }
            }
        }
    }
}

#[cfg(test)]
#[path = "ground_side_tests.rs"]
mod tests;

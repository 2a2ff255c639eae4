//! Which ground station this drone follows. Pure: the caller passes the time.
//!
//! A drone follows one ground station at a time, named by the epoch in its heartbeats and
//! actions (`GroundHeartbeat::ground`, `ActionCommand::ground`). The first one heard is
//! followed; another one is refused for as long as the followed one keeps beating, and adopted
//! once that one has been silent for `takeover_after_s` (the failsafe's hold time: a restarted or
//! replacing ground station is in control again as soon as the drone would hold anyway). From
//! the followed ground only actions with a sequence number newer than the last accepted are
//! taken: a delayed or replayed one is dropped.

use tacos_shared::action::ActionCommand;

/// What a heartbeat did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Beat {
    /// From the ground already followed.
    Followed,
    /// A ground is followed from now on (`previous`: the one it replaces, silent long enough).
    Adopted { previous: Option<u64> },
    /// From another ground while the followed one still beats: ignored.
    Refused { followed: u64 },
}

/// Why an action is not taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// Sent by a ground station that is not the one followed.
    OtherGround { sender: u64, followed: u64 },
    /// Not newer than the last action accepted from the followed ground.
    Stale { seq: u64, last: u64 },
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refusal::OtherGround { sender, followed } => write!(
                f,
                "from ground station {sender}, while ground station {followed} is in control"
            ),
            Refusal::Stale { seq, last } => {
                write!(f, "#{seq} is not newer than #{last}, already taken")
            }
        }
    }
}

#[derive(Debug, Clone)]
pub struct GroundFollower {
    takeover_after_s: f64,
    /// The followed ground and when it was last heard (a heartbeat or an action).
    followed: Option<(u64, f64)>,
    /// The last action accepted from it.
    last_seq: Option<u64>,
}

impl GroundFollower {
    pub fn new(takeover_after_s: f64) -> Self {
        GroundFollower {
            takeover_after_s,
            followed: None,
            last_seq: None,
        }
    }

    /// The ground followed, if any.
    pub fn followed(&self) -> Option<u64> {
        self.followed.map(|(g, _)| g)
    }

    fn free_for(&self, ground: u64, now: f64) -> bool {
        match self.followed {
            None => true,
            Some((g, _)) if g == ground => true,
            Some((_, heard)) => now - heard >= self.takeover_after_s,
        }
    }

    fn adopt(&mut self, ground: u64, now: f64) -> Beat {
        let previous = self.followed.map(|(g, _)| g);
        self.followed = Some((ground, now));
        self.last_seq = None;
        Beat::Adopted { previous }
    }

    pub fn on_heartbeat(&mut self, ground: u64, now: f64) -> Beat {
        match self.followed {
            Some((g, _)) if g == ground => {
                self.followed = Some((g, now));
                Beat::Followed
            }
            Some((g, _)) if !self.free_for(ground, now) => Beat::Refused { followed: g },
            _ => self.adopt(ground, now),
        }
    }

    /// Whether `command` is taken. An action from a ground when none is followed (or the
    /// followed one has gone silent) makes that ground the followed one: a ground station in
    /// control beats at once, but its first action may arrive before its first beat.
    pub fn admit(&mut self, command: &ActionCommand, now: f64) -> Result<(), Refusal> {
        if let Some((g, _)) = self.followed
            && g != command.ground
        {
            if !self.free_for(command.ground, now) {
                return Err(Refusal::OtherGround {
                    sender: command.ground,
                    followed: g,
                });
            }
            self.adopt(command.ground, now);
        } else if self.followed.is_none() {
            self.adopt(command.ground, now);
        }
        if let Some(last) = self.last_seq
            && command.seq <= last
        {
            return Err(Refusal::Stale {
                seq: command.seq,
                last,
            });
        }
        self.last_seq = Some(command.seq);
        self.followed = Some((command.ground, now));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_shared::action::Action;

    fn action(ground: u64, seq: u64) -> ActionCommand {
        ActionCommand {
            ground,
            seq,
            task_id: None,
            action: Action::Hold,
        }
    }

    #[test]
    fn one_ground_at_a_time_until_it_falls_silent() {
        let mut f = GroundFollower::new(3.0);
        assert_eq!(f.on_heartbeat(1, 0.0), Beat::Adopted { previous: None });
        assert_eq!(f.on_heartbeat(1, 0.2), Beat::Followed);
        // A second station while the first beats: refused, heartbeats and actions alike.
        assert_eq!(f.on_heartbeat(2, 1.0), Beat::Refused { followed: 1 });
        assert_eq!(
            f.admit(&action(2, 100), 1.0),
            Err(Refusal::OtherGround {
                sender: 2,
                followed: 1
            })
        );
        assert_eq!(f.admit(&action(1, 5), 1.1), Ok(()));
        // The first falls silent: past the take-over time the second is followed.
        assert_eq!(f.on_heartbeat(2, 3.5), Beat::Refused { followed: 1 });
        assert_eq!(f.on_heartbeat(2, 4.2), Beat::Adopted { previous: Some(1) });
        assert_eq!(f.followed(), Some(2));
        assert_eq!(f.admit(&action(2, 100), 4.3), Ok(()));
        // And the first, back, is now the other one.
        assert_eq!(f.on_heartbeat(1, 4.4), Beat::Refused { followed: 2 });
    }

    #[test]
    fn only_newer_actions_of_the_followed_ground_are_taken() {
        let mut f = GroundFollower::new(3.0);
        f.on_heartbeat(7, 0.0);
        assert_eq!(f.admit(&action(7, 10), 0.1), Ok(()));
        assert_eq!(
            f.admit(&action(7, 10), 0.2),
            Err(Refusal::Stale { seq: 10, last: 10 })
        );
        assert_eq!(
            f.admit(&action(7, 9), 0.3),
            Err(Refusal::Stale { seq: 9, last: 10 })
        );
        assert_eq!(f.admit(&action(7, 11), 0.4), Ok(()));
    }

    #[test]
    fn an_action_before_any_heartbeat_adopts_its_sender() {
        let mut f = GroundFollower::new(3.0);
        assert_eq!(f.admit(&action(4, 1), 0.0), Ok(()));
        assert_eq!(f.followed(), Some(4));
        assert_eq!(f.on_heartbeat(4, 0.1), Beat::Followed);
        // A new ground's sequence starts afresh: its low numbers are not "stale".
        assert_eq!(f.admit(&action(9, 1), 5.0), Ok(()));
        assert_eq!(f.followed(), Some(9));
    }
}

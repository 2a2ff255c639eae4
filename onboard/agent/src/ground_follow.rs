//! Which ground station this drone follows, and whether an action of it is taken. Pure: the
//! caller passes the time.
//!
//! A drone follows one ground station at a time, named by the epoch in its heartbeats and
//! actions (`GroundHeartbeat::ground`, `ActionCommand::ground`). The first one heard is
//! followed; another one is refused for as long as the followed one keeps beating, and adopted
//! once that one has been silent for `takeover_after_s` (the failsafe's hold time: a restarted or
//! replacing ground station is in control again as soon as the drone would hold anyway). From
//! the followed ground only actions with a sequence number newer than the last accepted are
//! taken: a delayed or replayed one is dropped.
//!
//! An action that arrives late is refused too, land and hold aside. Late is measured against the
//! same ground's heartbeats, as MAVLink's TIMESYNC does, not against a shared clock: each beat and
//! action carries the ground's clock, and the smallest `our clock − its stamp` of the last few
//! seconds is the two clocks' offset plus the quickest transit. An action whose own difference
//! exceeds that by more than `max_late_s` was held on the way (a link that stalled and then
//! delivered what it had queued): the ground has moved on since. Clocks need not agree, only run
//! at the same rate.

use std::collections::VecDeque;
use tacos_shared::action::{Action, ActionCommand};
use tacos_shared::messages::RefusedBecause;

/// How long a transit sample counts toward the reference (the newest one always counts).
const TRANSIT_WINDOW_S: f64 = 5.0;

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
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Refusal {
    /// Sent by a ground station that is not the one followed.
    OtherGround { sender: u64, followed: u64 },
    /// Not newer than the last action accepted from the followed ground.
    Stale { seq: u64, last: u64 },
    /// From the followed ground, but held on the way: the ground is told (`DroneStatus::refused`).
    Late(RefusedBecause),
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
            Refusal::Late(why) => write!(f, "{why}"),
        }
    }
}

#[derive(Debug, Clone)]
pub struct GroundFollower {
    takeover_after_s: f64,
    max_late_s: f64,
    /// The followed ground and when it was last heard (a heartbeat or an action).
    followed: Option<(u64, f64)>,
    /// The last action accepted from it.
    last_seq: Option<u64>,
    /// Of the followed ground, oldest first: (when heard, our clock − its stamp).
    transits: VecDeque<(f64, f64)>,
}

impl GroundFollower {
    pub fn new(takeover_after_s: f64, max_late_s: f64) -> Self {
        GroundFollower {
            takeover_after_s,
            max_late_s,
            followed: None,
            last_seq: None,
            transits: VecDeque::new(),
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
        self.transits.clear();
        Beat::Adopted { previous }
    }

    fn note_transit(&mut self, stamp: f64, now: f64) {
        let transit = now - stamp;
        if !transit.is_finite() {
            return;
        }
        self.transits.push_back((now, transit));
        while self.transits.len() > 1
            && self
                .transits
                .front()
                .is_some_and(|(at, _)| now - at > TRANSIT_WINDOW_S)
        {
            self.transits.pop_front();
        }
    }

    /// The quickest transit of the window (offset included), once one was heard.
    fn reference(&self) -> Option<f64> {
        self.transits.iter().map(|(_, t)| *t).reduce(f64::min)
    }

    pub fn on_heartbeat(&mut self, ground: u64, stamp: f64, now: f64) -> Beat {
        let beat = match self.followed {
            Some((g, _)) if g == ground => {
                self.followed = Some((g, now));
                Beat::Followed
            }
            Some((g, _)) if !self.free_for(ground, now) => return Beat::Refused { followed: g },
            _ => self.adopt(ground, now),
        };
        self.note_transit(stamp, now);
        beat
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
        // Land and hold are taken however late: they cannot make anything worse.
        let emergency = matches!(command.action, Action::Land | Action::Hold);
        if let Some(reference) = self.reference()
            && !emergency
        {
            let late_s = now - command.sent_at - reference;
            if late_s.is_nan() || late_s > self.max_late_s {
                return Err(Refusal::Late(RefusedBecause::Late {
                    late_s,
                    bound_s: self.max_late_s,
                }));
            }
        }
        self.last_seq = Some(command.seq);
        self.followed = Some((command.ground, now));
        self.note_transit(command.sent_at, now);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_shared::action::Action;

    /// A hold sent at `sent_at` on the ground's clock.
    fn sent(ground: u64, seq: u64, sent_at: f64, action: Action) -> ActionCommand {
        ActionCommand {
            ground,
            seq,
            sent_at,
            task_id: None,
            action,
        }
    }

    /// A hold, stamped as if it took no time on the way.
    fn action(ground: u64, seq: u64, now: f64) -> ActionCommand {
        sent(ground, seq, now, Action::Hold)
    }

    #[test]
    fn one_ground_at_a_time_until_it_falls_silent() {
        let mut f = GroundFollower::new(3.0, 2.0);
        assert_eq!(
            f.on_heartbeat(1, 0.0, 0.0),
            Beat::Adopted { previous: None }
        );
        assert_eq!(f.on_heartbeat(1, 0.2, 0.2), Beat::Followed);
        // A second station while the first beats: refused, heartbeats and actions alike.
        assert_eq!(f.on_heartbeat(2, 1.0, 1.0), Beat::Refused { followed: 1 });
        assert_eq!(
            f.admit(&action(2, 100, 1.0), 1.0),
            Err(Refusal::OtherGround {
                sender: 2,
                followed: 1
            })
        );
        assert_eq!(f.admit(&action(1, 5, 1.1), 1.1), Ok(()));
        // The first falls silent: past the take-over time the second is followed.
        assert_eq!(f.on_heartbeat(2, 3.5, 3.5), Beat::Refused { followed: 1 });
        assert_eq!(
            f.on_heartbeat(2, 4.2, 4.2),
            Beat::Adopted { previous: Some(1) }
        );
        assert_eq!(f.followed(), Some(2));
        assert_eq!(f.admit(&action(2, 100, 4.3), 4.3), Ok(()));
        // And the first, back, is now the other one.
        assert_eq!(f.on_heartbeat(1, 4.4, 4.4), Beat::Refused { followed: 2 });
    }

    #[test]
    fn only_newer_actions_of_the_followed_ground_are_taken() {
        let mut f = GroundFollower::new(3.0, 2.0);
        f.on_heartbeat(7, 0.0, 0.0);
        assert_eq!(f.admit(&action(7, 10, 0.1), 0.1), Ok(()));
        assert_eq!(
            f.admit(&action(7, 10, 0.2), 0.2),
            Err(Refusal::Stale { seq: 10, last: 10 })
        );
        assert_eq!(
            f.admit(&action(7, 9, 0.3), 0.3),
            Err(Refusal::Stale { seq: 9, last: 10 })
        );
        assert_eq!(f.admit(&action(7, 11, 0.4), 0.4), Ok(()));
    }

    #[test]
    fn an_action_before_any_heartbeat_adopts_its_sender() {
        let mut f = GroundFollower::new(3.0, 2.0);
        assert_eq!(f.admit(&action(4, 1, 0.0), 0.0), Ok(()));
        assert_eq!(f.followed(), Some(4));
        assert_eq!(f.on_heartbeat(4, 0.1, 0.1), Beat::Followed);
        // A new ground's sequence starts afresh: its low numbers are not "stale".
        assert_eq!(f.admit(&action(9, 1, 5.0), 5.0), Ok(()));
        assert_eq!(f.followed(), Some(9));
    }

    #[test]
    fn an_action_held_on_the_way_is_refused_however_the_clocks_differ() {
        // The ground's clock is 100 s behind the drone's; transits take 0.05 s.
        let mut f = GroundFollower::new(3.0, 2.0);
        let ground_clock = |now: f64| now - 100.0 - 0.05;
        for i in 0..10 {
            let now = i as f64 * 0.2;
            f.on_heartbeat(3, ground_clock(now), now);
        }
        let goto = Action::Goto {
            target: tacos_shared::Vec3::new(1.0, 2.0, 3.0),
        };
        // On time, and a little late: taken.
        assert_eq!(
            f.admit(&sent(3, 1, ground_clock(2.0), goto.clone()), 2.0),
            Ok(())
        );
        assert_eq!(
            f.admit(&sent(3, 2, ground_clock(2.0), goto.clone()), 3.9),
            Ok(())
        );
        // Sent at 2.0, arriving at 6.0: held 4 s on the way.
        let Err(Refusal::Late(RefusedBecause::Late { late_s, bound_s })) =
            f.admit(&sent(3, 3, ground_clock(2.0), goto.clone()), 6.0)
        else {
            panic!("a goto held 4 s was taken");
        };
        assert!(
            (late_s - 4.0).abs() < 1e-9 && bound_s == 2.0,
            "{late_s} {bound_s}"
        );
        // A land held as long is still taken, and so is a newer goto on time.
        assert_eq!(
            f.admit(&sent(3, 4, ground_clock(2.0), Action::Land), 6.0),
            Ok(())
        );
        assert_eq!(
            f.admit(&sent(3, 5, ground_clock(6.0), goto.clone()), 6.0),
            Ok(())
        );
        // A stamp that is no number is never on time.
        assert!(matches!(
            f.admit(&sent(3, 6, f64::NAN, goto), 6.1),
            Err(Refusal::Late(_))
        ));
    }

    #[test]
    fn the_reference_follows_the_latest_seconds_and_starts_afresh_with_a_new_ground() {
        let mut f = GroundFollower::new(3.0, 2.0);
        // Beats on a clock that drifts 15 % slow against ours (a lagging simulator): over 20 s
        // of beats the offset moves by 3 s, which a reference kept for ever would call late.
        for i in 0..100 {
            let now = i as f64 * 0.2;
            f.on_heartbeat(1, now * 0.85, now);
        }
        let goto = Action::Goto {
            target: tacos_shared::Vec3::new(0.0, 0.0, 1.0),
        };
        assert_eq!(
            f.admit(&sent(1, 1, 20.0 * 0.85, goto.clone()), 20.0),
            Ok(())
        );
        // A new ground, silent takeover: its own clock, its own reference.
        f.on_heartbeat(2, 500.0, 30.0);
        assert_eq!(f.admit(&sent(2, 1, 500.1, goto), 30.1), Ok(()));
    }
}

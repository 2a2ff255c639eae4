//! Commands for the autopilot as a pure state machine: COMMAND_LONG out, COMMAND_ACK in, one
//! command in flight at a time (others queue in arrival order), a per-try ack timeout, retries
//! with `confirmation` incremented (the MAVLink command protocol), and exactly one
//! [`CommandResultSample`] per command. The clock is passed in.

use std::collections::VecDeque;
use std::time::{Duration, Instant};
use tacos_shared::ipc::{CommandKind, CommandOutcome, CommandResultSample, CommandSample};
use tacos_shared::px4_mode;

/// How long to wait for the COMMAND_ACK of one try.
pub const ACK_TIMEOUT: Duration = Duration::from_secs(1);
/// Tries per command (the first send plus two retries).
pub const MAX_TRIES: u8 = 3;
/// After a MAV_RESULT_IN_PROGRESS ack: how long to wait for the final ack (no resends meanwhile).
pub const IN_PROGRESS_TIMEOUT: Duration = Duration::from_secs(5);
/// `CommandResultSample::mav_result` when the autopilot never answered.
pub const NO_MAV_RESULT: u32 = u32::MAX;

/// MAV_CMD values used here.
pub mod mav_cmd {
    pub const NAV_LAND: u16 = 21;
    pub const NAV_TAKEOFF: u16 = 22;
    pub const DO_SET_MODE: u16 = 176;
    pub const COMPONENT_ARM_DISARM: u16 = 400;
}

/// MAV_RESULT values used here.
pub mod mav_result {
    pub const ACCEPTED: u8 = 0;
    pub const TEMPORARILY_REJECTED: u8 = 1;
    pub const DENIED: u8 = 2;
    pub const IN_PROGRESS: u8 = 5;
}

/// One COMMAND_LONG, without the addressing (the shell fills in the autopilot's ids).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CommandLong {
    pub command: u16,
    pub params: [f32; 7],
    pub confirmation: u8,
}

/// The COMMAND_LONG for a TACOS command. `None` when `param` makes no sense for `kind`.
pub fn command_long_for(kind: CommandKind, param: f64) -> Option<CommandLong> {
    let nan = f32::NAN;
    let custom = f32::from(px4_mode::BASE_MODE_CUSTOM_ENABLED);
    let (command, params) = match kind {
        CommandKind::Arm => (
            mav_cmd::COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        ),
        CommandKind::Disarm => (
            mav_cmd::COMPONENT_ARM_DISARM,
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        ),
        CommandKind::Takeoff => {
            if !param.is_finite() || param <= 0.0 {
                return None;
            }
            // param7 = altitude. tacos-sitl reads it as metres above home. Real PX4 reads it as
            // AMSL: convert here by adding the home's AMSL altitude (HOME_POSITION.altitude / 1000)
            // once the writer listens to HOME_POSITION; NaN lat/lon/yaw = "here, current heading".
            (
                mav_cmd::NAV_TAKEOFF,
                [0.0, 0.0, 0.0, nan, nan, nan, param as f32],
            )
        }
        // NaN yaw/lat/lon/alt: land here with the current heading.
        CommandKind::Land => (mav_cmd::NAV_LAND, [0.0, 0.0, 0.0, nan, nan, nan, nan]),
        CommandKind::Offboard => (
            mav_cmd::DO_SET_MODE,
            [
                custom,
                f32::from(px4_mode::MAIN_OFFBOARD),
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            ],
        ),
        CommandKind::Hold => (
            mav_cmd::DO_SET_MODE,
            [
                custom,
                f32::from(px4_mode::MAIN_AUTO),
                f32::from(px4_mode::AUTO_LOITER),
                0.0,
                0.0,
                0.0,
                0.0,
            ],
        ),
    };
    Some(CommandLong {
        command,
        params,
        confirmation: 0,
    })
}

/// What the shell has to do after feeding the runner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CommandEvent {
    /// Send this COMMAND_LONG to the autopilot now.
    Send(CommandLong),
    /// Publish this result to the planner.
    Done(CommandResultSample),
}

#[derive(Debug, Clone, Copy)]
struct InFlight {
    seq: u64,
    kind: CommandKind,
    msg: CommandLong,
    tries: u8,
    deadline: Instant,
    in_progress: bool,
}

#[derive(Debug, Clone, Copy)]
struct Queued {
    seq: u64,
    kind: CommandKind,
    msg: CommandLong,
}

fn result(seq: u64, kind: u32, outcome: CommandOutcome, mav_result: u32) -> CommandResultSample {
    CommandResultSample {
        seq,
        kind,
        outcome: outcome as u32,
        mav_result,
        _reserved: 0,
    }
}

#[derive(Debug, Default)]
pub struct CommandRunner {
    queue: VecDeque<Queued>,
    in_flight: Option<InFlight>,
}

impl CommandRunner {
    pub fn new() -> Self {
        Self::default()
    }

    /// Queues a command from the planner. A command the writer cannot express is answered at
    /// once (`Unsupported`) and returned.
    pub fn submit(&mut self, sample: CommandSample) -> Option<CommandResultSample> {
        let Some(kind) = sample.kind() else {
            return Some(result(
                sample.seq,
                sample.kind,
                CommandOutcome::Unsupported,
                NO_MAV_RESULT,
            ));
        };
        let Some(msg) = command_long_for(kind, sample.param) else {
            return Some(result(
                sample.seq,
                sample.kind,
                CommandOutcome::Unsupported,
                NO_MAV_RESULT,
            ));
        };
        self.queue.push_back(Queued {
            seq: sample.seq,
            kind,
            msg,
        });
        None
    }

    /// A COMMAND_ACK from the autopilot. Returns the finished command's result when it matches
    /// the command in flight.
    pub fn on_ack(
        &mut self,
        command: u16,
        mav_result: u8,
        now: Instant,
    ) -> Option<CommandResultSample> {
        let flight = self
            .in_flight
            .as_mut()
            .filter(|f| f.msg.command == command)?;
        let outcome = match mav_result {
            mav_result::ACCEPTED => CommandOutcome::Accepted,
            mav_result::IN_PROGRESS => {
                // The autopilot is working on it: stop resending, wait for the final ack.
                flight.in_progress = true;
                flight.deadline = now + IN_PROGRESS_TIMEOUT;
                return None;
            }
            _ => CommandOutcome::Rejected,
        };
        let done = result(
            flight.seq,
            flight.kind as u32,
            outcome,
            u32::from(mav_result),
        );
        self.in_flight = None;
        Some(done)
    }

    /// Advances timeouts and starts queued commands. `link_ok` says whether the autopilot is
    /// reachable now; a command that comes due without a link ends as `LinkLost` at once.
    pub fn poll(&mut self, now: Instant, link_ok: bool) -> Vec<CommandEvent> {
        let mut events = Vec::new();
        if let Some(flight) = self.in_flight.as_mut()
            && now >= flight.deadline
        {
            if !flight.in_progress && flight.tries < MAX_TRIES {
                flight.tries += 1;
                flight.msg.confirmation = flight.msg.confirmation.saturating_add(1);
                flight.deadline = now + ACK_TIMEOUT;
                events.push(CommandEvent::Send(flight.msg));
            } else {
                events.push(CommandEvent::Done(result(
                    flight.seq,
                    flight.kind as u32,
                    CommandOutcome::TimedOut,
                    NO_MAV_RESULT,
                )));
                self.in_flight = None;
            }
        }
        while self.in_flight.is_none() {
            let Some(next) = self.queue.pop_front() else {
                break;
            };
            if !link_ok {
                events.push(CommandEvent::Done(result(
                    next.seq,
                    next.kind as u32,
                    CommandOutcome::LinkLost,
                    NO_MAV_RESULT,
                )));
                continue;
            }
            self.in_flight = Some(InFlight {
                seq: next.seq,
                kind: next.kind,
                msg: next.msg,
                tries: 1,
                deadline: now + ACK_TIMEOUT,
                in_progress: false,
            });
            events.push(CommandEvent::Send(next.msg));
        }
        events
    }

    /// When [`poll`](Self::poll) next has something to do (a retry or a timeout), if anything.
    pub fn next_deadline(&self) -> Option<Instant> {
        self.in_flight.map(|f| f.deadline)
    }

    pub fn is_idle(&self) -> bool {
        self.in_flight.is_none() && self.queue.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(t0: Instant, ms: u64) -> Instant {
        t0 + Duration::from_millis(ms)
    }

    fn sends(events: &[CommandEvent]) -> Vec<CommandLong> {
        events
            .iter()
            .filter_map(|e| {
                if let CommandEvent::Send(m) = e {
                    Some(*m)
                } else {
                    None
                }
            })
            .collect()
    }

    fn dones(events: &[CommandEvent]) -> Vec<CommandResultSample> {
        events
            .iter()
            .filter_map(|e| {
                if let CommandEvent::Done(r) = e {
                    Some(*r)
                } else {
                    None
                }
            })
            .collect()
    }

    #[test]
    fn command_encodings() {
        let arm = command_long_for(CommandKind::Arm, 0.0);
        assert_eq!(
            arm.map(|c| (c.command, c.params[0], c.confirmation)),
            Some((400, 1.0, 0))
        );
        assert_eq!(
            command_long_for(CommandKind::Disarm, 0.0).map(|c| (c.command, c.params[0])),
            Some((400, 0.0))
        );
        let takeoff = command_long_for(CommandKind::Takeoff, 12.5);
        assert_eq!(takeoff.map(|c| (c.command, c.params[6])), Some((22, 12.5)));
        assert_eq!(command_long_for(CommandKind::Takeoff, f64::NAN), None);
        assert_eq!(command_long_for(CommandKind::Takeoff, -1.0), None);
        assert_eq!(
            command_long_for(CommandKind::Land, 0.0).map(|c| c.command),
            Some(21)
        );
        let offboard = command_long_for(CommandKind::Offboard, 0.0);
        assert_eq!(
            offboard.map(|c| (c.command, c.params[0], c.params[1])),
            Some((176, 1.0, 6.0))
        );
        let hold = command_long_for(CommandKind::Hold, 0.0);
        assert_eq!(
            hold.map(|c| (c.command, c.params[0], c.params[1], c.params[2])),
            Some((176, 1.0, 4.0, 3.0))
        );
    }

    #[test]
    fn accepted_on_first_ack() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        assert_eq!(r.submit(CommandSample::new(7, CommandKind::Arm, 0.0)), None);
        let ev = r.poll(t0, true);
        assert_eq!(sends(&ev).len(), 1);
        // An ack for another command does not match.
        assert_eq!(
            r.on_ack(mav_cmd::NAV_LAND, mav_result::ACCEPTED, at(t0, 10)),
            None
        );
        let done = r.on_ack(400, mav_result::ACCEPTED, at(t0, 20));
        assert_eq!(
            done.map(|d| (d.seq, d.kind, d.outcome(), d.mav_result)),
            Some((7, 1, Some(CommandOutcome::Accepted), 0))
        );
        assert!(r.is_idle());
        // A late duplicate ack does nothing.
        assert_eq!(r.on_ack(400, mav_result::ACCEPTED, at(t0, 30)), None);
    }

    #[test]
    fn refusal_carries_the_mav_result() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(CommandSample::new(1, CommandKind::Takeoff, 10.0));
        r.poll(t0, true);
        let done = r.on_ack(22, mav_result::DENIED, at(t0, 5));
        assert_eq!(
            done.map(|d| (d.outcome(), d.mav_result)),
            Some((Some(CommandOutcome::Rejected), 2))
        );
    }

    #[test]
    fn unanswered_command_is_sent_three_times_with_rising_confirmation_then_times_out() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(CommandSample::new(3, CommandKind::Offboard, 0.0));
        let mut sent = sends(&r.poll(t0, true));
        assert_eq!(r.next_deadline(), Some(at(t0, 1000)));
        // Nothing before the deadline.
        assert!(r.poll(at(t0, 999), true).is_empty());
        sent.extend(sends(&r.poll(at(t0, 1000), true)));
        assert!(r.poll(at(t0, 1999), true).is_empty());
        sent.extend(sends(&r.poll(at(t0, 2000), true)));
        assert_eq!(
            sent.iter().map(|m| m.confirmation).collect::<Vec<_>>(),
            vec![0, 1, 2]
        );
        assert!(sent.iter().all(|m| m.command == 176));
        assert!(r.poll(at(t0, 2999), true).is_empty());
        let ev = r.poll(at(t0, 3000), true);
        assert!(sends(&ev).is_empty(), "no fourth try");
        let done = dones(&ev);
        assert_eq!(done.len(), 1);
        assert_eq!(
            (done[0].seq, done[0].outcome(), done[0].mav_result),
            (3, Some(CommandOutcome::TimedOut), NO_MAV_RESULT)
        );
        assert!(r.is_idle());
    }

    #[test]
    fn an_ack_to_a_retry_is_accepted() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(CommandSample::new(3, CommandKind::Land, 0.0));
        r.poll(t0, true);
        assert_eq!(sends(&r.poll(at(t0, 1000), true)).len(), 1);
        let done = r.on_ack(21, mav_result::ACCEPTED, at(t0, 1500));
        assert_eq!(
            done.and_then(|d| d.outcome()),
            Some(CommandOutcome::Accepted)
        );
    }

    #[test]
    fn commands_queue_and_run_one_at_a_time_in_order() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(CommandSample::new(1, CommandKind::Arm, 0.0));
        r.submit(CommandSample::new(2, CommandKind::Takeoff, 5.0));
        let first = sends(&r.poll(t0, true));
        assert_eq!(
            first.iter().map(|m| m.command).collect::<Vec<_>>(),
            vec![400]
        );
        assert!(r.on_ack(400, 0, at(t0, 10)).is_some());
        let second = sends(&r.poll(at(t0, 10), true));
        assert_eq!(
            second.iter().map(|m| m.command).collect::<Vec<_>>(),
            vec![22]
        );
        // A timeout of the first lets the next one start in the same poll.
        let mut r = CommandRunner::new();
        r.submit(CommandSample::new(1, CommandKind::Arm, 0.0));
        r.submit(CommandSample::new(2, CommandKind::Land, 0.0));
        r.poll(t0, true);
        r.poll(at(t0, 1000), true);
        r.poll(at(t0, 2000), true);
        let ev = r.poll(at(t0, 3000), true);
        assert_eq!(
            dones(&ev).iter().map(|d| d.seq).collect::<Vec<_>>(),
            vec![1]
        );
        assert_eq!(
            sends(&ev)
                .iter()
                .map(|m| (m.command, m.confirmation))
                .collect::<Vec<_>>(),
            vec![(21, 0)]
        );
    }

    #[test]
    fn in_progress_stops_retries_and_waits_for_the_final_ack() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(CommandSample::new(4, CommandKind::Takeoff, 10.0));
        r.poll(t0, true);
        assert_eq!(r.on_ack(22, mav_result::IN_PROGRESS, at(t0, 500)), None);
        assert!(
            r.poll(at(t0, 1500), true).is_empty(),
            "no resend while in progress"
        );
        let done = r.on_ack(22, mav_result::ACCEPTED, at(t0, 4000));
        assert_eq!(
            done.and_then(|d| d.outcome()),
            Some(CommandOutcome::Accepted)
        );
        // Without a final ack it times out.
        r.submit(CommandSample::new(5, CommandKind::Takeoff, 10.0));
        r.poll(t0, true);
        r.on_ack(22, mav_result::IN_PROGRESS, at(t0, 100));
        let ev = r.poll(at(t0, 100) + IN_PROGRESS_TIMEOUT, true);
        assert_eq!(
            dones(&ev).first().and_then(|d| d.outcome()),
            Some(CommandOutcome::TimedOut)
        );
    }

    #[test]
    fn no_link_means_link_lost_at_once_and_bad_commands_are_unsupported() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(CommandSample::new(1, CommandKind::Arm, 0.0));
        r.submit(CommandSample::new(2, CommandKind::Land, 0.0));
        let ev = r.poll(t0, false);
        assert!(sends(&ev).is_empty());
        let d = dones(&ev);
        assert_eq!(
            d.iter().map(|d| (d.seq, d.outcome())).collect::<Vec<_>>(),
            vec![
                (1, Some(CommandOutcome::LinkLost)),
                (2, Some(CommandOutcome::LinkLost))
            ]
        );
        let unknown = CommandSample {
            seq: 9,
            kind: 99,
            _reserved: 0,
            param: 0.0,
        };
        assert_eq!(
            r.submit(unknown).and_then(|d| d.outcome()),
            Some(CommandOutcome::Unsupported)
        );
        let bad_takeoff = r.submit(CommandSample::new(10, CommandKind::Takeoff, f64::INFINITY));
        assert_eq!(
            bad_takeoff.map(|d| (d.seq, d.kind, d.outcome())),
            Some((10, 3, Some(CommandOutcome::Unsupported)))
        );
        assert!(r.is_idle());
    }
}

//! The MAVLink command protocol as a pure state machine: COMMAND_LONG out, COMMAND_ACK in, one
//! command in flight at a time (others queue in arrival order), a per-try ack timeout, retries
//! with `confirmation` incremented, and exactly one outcome per command. It knows nothing of
//! what the commands mean: [`crate::procedure`] decides what to send and when. The clock is
//! passed in.

use std::collections::VecDeque;
use std::time::{Duration, Instant};
use tacos_shared::px4_mode;

/// How long to wait for the COMMAND_ACK of one try.
pub const ACK_TIMEOUT: Duration = Duration::from_secs(1);
/// Tries per command (the first send plus two retries).
pub const MAX_TRIES: u8 = 3;
/// After a MAV_RESULT_IN_PROGRESS ack: how long to wait for the final ack (no resends meanwhile).
pub const IN_PROGRESS_TIMEOUT: Duration = Duration::from_secs(5);

/// MAV_CMD values used here.
pub mod mav_cmd {
    pub const NAV_LAND: u16 = 21;
    pub const NAV_TAKEOFF: u16 = 22;
    pub const DO_SET_MODE: u16 = 176;
    pub const COMPONENT_ARM_DISARM: u16 = 400;
    pub const SET_MESSAGE_INTERVAL: u16 = 511;
    pub const REQUEST_MESSAGE: u16 = 512;
}

/// MAV_RESULT values used here.
pub mod mav_result {
    pub const ACCEPTED: u8 = 0;
    pub const TEMPORARILY_REJECTED: u8 = 1;
    pub const DENIED: u8 = 2;
    pub const UNSUPPORTED: u8 = 3;
    pub const FAILED: u8 = 4;
    pub const IN_PROGRESS: u8 = 5;
}

/// One COMMAND_LONG, without the addressing (the shell fills in the autopilot's ids).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CommandLong {
    pub command: u16,
    pub params: [f32; 7],
    pub confirmation: u8,
}

impl CommandLong {
    fn new(command: u16, params: [f32; 7]) -> Self {
        CommandLong {
            command,
            params,
            confirmation: 0,
        }
    }

    pub fn arm() -> Self {
        Self::new(
            mav_cmd::COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
    }

    pub fn disarm() -> Self {
        Self::new(mav_cmd::COMPONENT_ARM_DISARM, [0.0; 7])
    }

    /// NAV_TAKEOFF to `amsl_m` metres above mean sea level (PX4 reads param7 as AMSL); NaN
    /// lat/lon/yaw = here, current heading.
    pub fn takeoff(amsl_m: f64) -> Self {
        let nan = f32::NAN;
        Self::new(
            mav_cmd::NAV_TAKEOFF,
            [0.0, 0.0, 0.0, nan, nan, nan, amsl_m as f32],
        )
    }

    /// NAV_LAND here with the current heading.
    pub fn land() -> Self {
        let nan = f32::NAN;
        Self::new(mav_cmd::NAV_LAND, [0.0, 0.0, 0.0, nan, nan, nan, nan])
    }

    /// DO_SET_MODE to PX4's custom (main, sub) mode.
    pub fn set_mode(main: u8, sub: u8) -> Self {
        Self::new(
            mav_cmd::DO_SET_MODE,
            [
                f32::from(px4_mode::BASE_MODE_CUSTOM_ENABLED),
                f32::from(main),
                f32::from(sub),
                0.0,
                0.0,
                0.0,
                0.0,
            ],
        )
    }

    /// SET_MESSAGE_INTERVAL: stream message `id` every `interval_us` µs.
    pub fn message_interval(id: u32, interval_us: f32) -> Self {
        Self::new(
            mav_cmd::SET_MESSAGE_INTERVAL,
            [id as f32, interval_us, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
    }

    /// REQUEST_MESSAGE: send message `id` once, now.
    pub fn request_message(id: u32) -> Self {
        Self::new(
            mav_cmd::REQUEST_MESSAGE,
            [id as f32, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
    }
}

/// How one COMMAND_LONG ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AckOutcome {
    Accepted,
    /// The autopilot refused: its MAV_RESULT.
    Rejected(u8),
    /// No ack after every retry.
    TimedOut,
    /// No autopilot link when the command was due.
    LinkLost,
}

/// What the shell (or the procedure above) has to do after feeding the runner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CommandEvent {
    /// Send this COMMAND_LONG to the autopilot now.
    Send(CommandLong),
    /// Command `id` ended so.
    Done { id: u64, outcome: AckOutcome },
}

#[derive(Debug, Clone, Copy)]
struct InFlight {
    id: u64,
    msg: CommandLong,
    tries: u8,
    deadline: Instant,
    in_progress: bool,
}

#[derive(Debug, Default)]
pub struct CommandRunner {
    queue: VecDeque<(u64, CommandLong)>,
    in_flight: Option<InFlight>,
}

impl CommandRunner {
    pub fn new() -> Self {
        Self::default()
    }

    /// Queues `msg` under the caller's `id`.
    pub fn submit(&mut self, id: u64, msg: CommandLong) {
        self.queue.push_back((id, msg));
    }

    /// A COMMAND_ACK from the autopilot. Returns the finished command when it matches the one
    /// in flight.
    pub fn on_ack(
        &mut self,
        command: u16,
        mav_result: u8,
        now: Instant,
    ) -> Option<(u64, AckOutcome)> {
        let flight = self
            .in_flight
            .as_mut()
            .filter(|f| f.msg.command == command)?;
        let outcome = match mav_result {
            mav_result::ACCEPTED => AckOutcome::Accepted,
            mav_result::IN_PROGRESS => {
                // The autopilot is working on it: stop resending, wait for the final ack.
                flight.in_progress = true;
                flight.deadline = now + IN_PROGRESS_TIMEOUT;
                return None;
            }
            other => AckOutcome::Rejected(other),
        };
        let id = flight.id;
        self.in_flight = None;
        Some((id, outcome))
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
                events.push(CommandEvent::Done {
                    id: flight.id,
                    outcome: AckOutcome::TimedOut,
                });
                self.in_flight = None;
            }
        }
        while self.in_flight.is_none() {
            let Some((id, msg)) = self.queue.pop_front() else {
                break;
            };
            if !link_ok {
                events.push(CommandEvent::Done {
                    id,
                    outcome: AckOutcome::LinkLost,
                });
                continue;
            }
            self.in_flight = Some(InFlight {
                id,
                msg,
                tries: 1,
                deadline: now + ACK_TIMEOUT,
                in_progress: false,
            });
            events.push(CommandEvent::Send(msg));
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
            .filter_map(|e| match e {
                CommandEvent::Send(m) => Some(*m),
                CommandEvent::Done { .. } => None,
            })
            .collect()
    }

    fn dones(events: &[CommandEvent]) -> Vec<(u64, AckOutcome)> {
        events
            .iter()
            .filter_map(|e| match e {
                CommandEvent::Done { id, outcome } => Some((*id, *outcome)),
                CommandEvent::Send(_) => None,
            })
            .collect()
    }

    #[test]
    fn command_encodings() {
        let arm = CommandLong::arm();
        assert_eq!(
            (arm.command, arm.params[0], arm.confirmation),
            (400, 1.0, 0)
        );
        let disarm = CommandLong::disarm();
        assert_eq!((disarm.command, disarm.params[0]), (400, 0.0));
        let takeoff = CommandLong::takeoff(499.4);
        assert_eq!((takeoff.command, takeoff.params[6]), (22, 499.4));
        assert!(takeoff.params[3].is_nan() && takeoff.params[4].is_nan());
        assert_eq!(CommandLong::land().command, 21);
        let offboard = CommandLong::set_mode(px4_mode::MAIN_OFFBOARD, 0);
        assert_eq!(
            (offboard.command, offboard.params[0], offboard.params[1]),
            (176, 1.0, 6.0)
        );
        let hold = CommandLong::set_mode(px4_mode::MAIN_AUTO, px4_mode::AUTO_LOITER);
        assert_eq!(
            (hold.command, hold.params[0], hold.params[1], hold.params[2]),
            (176, 1.0, 4.0, 3.0)
        );
        let interval = CommandLong::message_interval(32, 20_000.0);
        assert_eq!(
            (interval.command, interval.params[0], interval.params[1]),
            (511, 32.0, 20_000.0)
        );
        let request = CommandLong::request_message(242);
        assert_eq!((request.command, request.params[0]), (512, 242.0));
    }

    #[test]
    fn accepted_on_first_ack() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(7, CommandLong::arm());
        assert_eq!(sends(&r.poll(t0, true)).len(), 1);
        // An ack for another command does not match.
        assert_eq!(
            r.on_ack(mav_cmd::NAV_LAND, mav_result::ACCEPTED, at(t0, 10)),
            None
        );
        assert_eq!(
            r.on_ack(400, mav_result::ACCEPTED, at(t0, 20)),
            Some((7, AckOutcome::Accepted))
        );
        assert!(r.is_idle());
        // A late duplicate ack does nothing.
        assert_eq!(r.on_ack(400, mav_result::ACCEPTED, at(t0, 30)), None);
    }

    #[test]
    fn refusal_carries_the_mav_result() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(1, CommandLong::takeoff(500.0));
        r.poll(t0, true);
        assert_eq!(
            r.on_ack(22, mav_result::DENIED, at(t0, 5)),
            Some((1, AckOutcome::Rejected(mav_result::DENIED)))
        );
    }

    #[test]
    fn unanswered_command_is_sent_three_times_with_rising_confirmation_then_times_out() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(3, CommandLong::set_mode(px4_mode::MAIN_OFFBOARD, 0));
        let mut sent = sends(&r.poll(t0, true));
        assert_eq!(r.next_deadline(), Some(at(t0, 1000)));
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
        assert_eq!(dones(&ev), vec![(3, AckOutcome::TimedOut)]);
        assert!(r.is_idle());
    }

    #[test]
    fn an_ack_to_a_retry_is_accepted() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(3, CommandLong::land());
        r.poll(t0, true);
        assert_eq!(sends(&r.poll(at(t0, 1000), true)).len(), 1);
        assert_eq!(
            r.on_ack(21, mav_result::ACCEPTED, at(t0, 1500)),
            Some((3, AckOutcome::Accepted))
        );
    }

    #[test]
    fn commands_queue_and_run_one_at_a_time_in_order() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(1, CommandLong::arm());
        r.submit(2, CommandLong::takeoff(495.0));
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
        r.submit(1, CommandLong::arm());
        r.submit(2, CommandLong::land());
        r.poll(t0, true);
        r.poll(at(t0, 1000), true);
        r.poll(at(t0, 2000), true);
        let ev = r.poll(at(t0, 3000), true);
        assert_eq!(dones(&ev), vec![(1, AckOutcome::TimedOut)]);
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
        r.submit(4, CommandLong::takeoff(500.0));
        r.poll(t0, true);
        assert_eq!(r.on_ack(22, mav_result::IN_PROGRESS, at(t0, 500)), None);
        assert!(
            r.poll(at(t0, 1500), true).is_empty(),
            "no resend while in progress"
        );
        assert_eq!(
            r.on_ack(22, mav_result::ACCEPTED, at(t0, 4000)),
            Some((4, AckOutcome::Accepted))
        );
        // Without a final ack it times out.
        r.submit(5, CommandLong::takeoff(500.0));
        r.poll(t0, true);
        r.on_ack(22, mav_result::IN_PROGRESS, at(t0, 100));
        let ev = r.poll(at(t0, 100) + IN_PROGRESS_TIMEOUT, true);
        assert_eq!(dones(&ev), vec![(5, AckOutcome::TimedOut)]);
    }

    #[test]
    fn no_link_means_link_lost_at_once() {
        let t0 = Instant::now();
        let mut r = CommandRunner::new();
        r.submit(1, CommandLong::arm());
        r.submit(2, CommandLong::land());
        let ev = r.poll(t0, false);
        assert!(sends(&ev).is_empty());
        assert_eq!(
            dones(&ev),
            vec![(1, AckOutcome::LinkLost), (2, AckOutcome::LinkLost)]
        );
        assert!(r.is_idle());
    }
}

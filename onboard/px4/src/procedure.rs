//! PX4's procedures around the command protocol, as a pure state machine: what must hold before
//! a TACOS command is sent, what it is sent with, and what confirms it. Measured on PX4 SITL
//! (`deploy/README.md`, "Real PX4"):
//!
//! - **Arm**: PX4 arms only in an armable mode (AUTO.LOITER; OFFBOARD while setpoints stream;
//!   after an offboard flight lands it is back in OFFBOARD with no stream and refuses), and only
//!   once its pre-flight checks pass (HEARTBEAT system_status STANDBY). So: switch to
//!   AUTO.LOITER unless armable where it is, wait for readiness (bounded), arm.
//! - **Offboard on the ground** is refused until the pre-flight checks pass: wait for them.
//! - **Take-off**: MAV_CMD_NAV_TAKEOFF's param7 is AMSL. The command's height above the vehicle
//!   is added to the vehicle's own AMSL altitude (GLOBAL_POSITION_INT, requested when missing).
//! - **Mode switches** are acknowledged twice by PX4 (first ACCEPTED from the receiver, then the
//!   real result): a switch is done when the HEARTBEAT shows the mode or the second ack says so,
//!   refused when the second ack refuses it.
//! - A refusal carries PX4's own words: the latest warning STATUSTEXT since the command started.
//!
//! The COMMAND_LONG protocol itself (acks, retries) is [`crate::commands::CommandRunner`]'s.

use crate::commands::{AckOutcome, CommandEvent, CommandLong, CommandRunner, mav_cmd, mav_result};
use crate::setup::SetupState;
use std::collections::VecDeque;
use std::time::{Duration, Instant};
use tacos_shared::ipc::{CommandKind, CommandOutcome, CommandResultSample, CommandSample};
use tacos_shared::px4_mode::{self, Px4Mode};

/// How long an arm waits for PX4's pre-flight checks to pass (PX4 SITL needs a few seconds after
/// boot; a real vehicle's GPS can take longer, and the executor's take-off deadline is longer).
pub const READY_TIMEOUT: Duration = Duration::from_secs(30);
/// How long a take-off waits for the vehicle's AMSL altitude after asking for it.
pub const ALTITUDE_TIMEOUT: Duration = Duration::from_secs(5);
/// After a mode switch is accepted: how long PX4 may take to show it (heartbeats are 1 Hz).
pub const MODE_CONFIRM_TIMEOUT: Duration = Duration::from_secs(3);
/// A STATUSTEXT this much older than the command's start is not its reason.
pub const TEXT_LOOKBACK: Duration = Duration::from_secs(2);
/// `CommandResultSample::mav_result` when the autopilot gave none.
pub const NO_MAV_RESULT: u32 = u32::MAX;
/// MAVLink message ids requested here.
pub const GLOBAL_POSITION_INT_ID: u32 = 33;

/// What the procedures need to know of the autopilot now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutopilotFacts {
    pub link_ok: bool,
    /// PX4's pre-flight checks pass (system_status STANDBY) or it is armed.
    pub ready: bool,
    pub armed: bool,
    pub mode: Px4Mode,
    /// The vehicle's current altitude above mean sea level, metres, if fresh.
    pub amsl_m: Option<f64>,
}

/// What the shell has to do.
#[derive(Debug, Clone, PartialEq)]
pub enum ProcedureEvent {
    /// Send this COMMAND_LONG now.
    Send(CommandLong),
    /// A TACOS command ended: publish this result to the planner.
    Done(CommandResultSample),
    /// A command of the writer's own (a stream request) ended: log it.
    Internal { command: u16, outcome: AckOutcome },
}

/// Where a command's procedure stands.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Step {
    /// Not started yet.
    Start,
    /// Waiting for PX4 to report ready to arm (an arm, or an offboard switch on the ground).
    WaitReady { until: Instant },
    /// Waiting for a fresh AMSL altitude (take-off).
    WaitAltitude { until: Instant, requested: bool },
    /// A COMMAND_LONG with this runner id is out.
    Command { id: u64, then: Then },
    /// A mode switch was accepted: waiting to see the mode.
    ConfirmMode {
        target: Px4Mode,
        until: Instant,
        then: Then,
    },
}

/// What follows a command or a confirmed mode switch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Then {
    /// The TACOS command is done.
    Finish,
    /// The switch to AUTO.LOITER before arming is done: wait for readiness, then arm.
    WaitReadyThenArm,
}

#[derive(Debug, Clone, Copy)]
struct Job {
    seq: u64,
    kind: CommandKind,
    param: f64,
    started: Instant,
    step: Step,
}

/// Runs TACOS commands one at a time through their PX4 procedures.
#[derive(Debug)]
pub struct Procedures {
    /// The failsafe parameters and the geofence: no arming before they are confirmed.
    setup: SetupState,
    runner: CommandRunner,
    queue: VecDeque<(CommandSample, CommandKind)>,
    job: Option<Job>,
    /// Runner ids of the writer's own commands, and their command numbers.
    internal: Vec<(u64, u16)>,
    next_id: u64,
    last_text: Option<(String, Instant)>,
}

fn mode_command(mode: Px4Mode) -> CommandLong {
    match mode {
        Px4Mode::Offboard => CommandLong::set_mode(px4_mode::MAIN_OFFBOARD, 0),
        _ => CommandLong::set_mode(px4_mode::MAIN_AUTO, px4_mode::AUTO_LOITER),
    }
}

/// Whether PX4 would arm in its current mode without a remote control: AUTO.LOITER and
/// AUTO.TAKEOFF always; OFFBOARD only while setpoints stream, which PX4 shows as readiness
/// (after an offboard flight lands it is back in OFFBOARD with no stream and refuses). The
/// onboard takes off by arming in OFFBOARD, so the planner flies the climb.
fn armable(facts: &AutopilotFacts) -> bool {
    match facts.mode {
        Px4Mode::Hold | Px4Mode::Takeoff => true,
        Px4Mode::Offboard => facts.ready,
        _ => false,
    }
}

fn mav_result_name(code: u8) -> &'static str {
    match code {
        mav_result::ACCEPTED => "ACCEPTED",
        mav_result::TEMPORARILY_REJECTED => "TEMPORARILY_REJECTED",
        mav_result::DENIED => "DENIED",
        mav_result::UNSUPPORTED => "UNSUPPORTED",
        mav_result::FAILED => "FAILED",
        _ => "an unknown MAV_RESULT",
    }
}

impl Default for Procedures {
    fn default() -> Self {
        Procedures {
            setup: SetupState::Pending,
            runner: CommandRunner::default(),
            queue: VecDeque::new(),
            job: None,
            internal: Vec::new(),
            next_id: 0,
            last_text: None,
        }
    }
}

impl Procedures {
    /// Arming waits for [`Procedures::on_setup`] to say the autopilot is set up.
    pub fn new() -> Self {
        Self::default()
    }

    /// Where the autopilot's setup (parameters, geofence) stands.
    pub fn on_setup(&mut self, state: SetupState) {
        self.setup = state;
    }

    fn id(&mut self) -> u64 {
        self.next_id += 1;
        self.next_id
    }

    /// Queues a command from the planner. One the writer cannot express is answered at once.
    pub fn submit(&mut self, sample: CommandSample) -> Option<CommandResultSample> {
        let unsupported = |why: &str| {
            Some(
                CommandResultSample::new(
                    sample.seq,
                    sample.kind,
                    CommandOutcome::Unsupported,
                    NO_MAV_RESULT,
                )
                .with_reason(why),
            )
        };
        let Some(kind) = sample.kind() else {
            return unsupported("unknown command code");
        };
        if kind == CommandKind::Takeoff && !(sample.param.is_finite() && sample.param > 0.0) {
            return unsupported("a take-off height must be a positive number of metres");
        }
        self.queue.push_back((sample, kind));
        None
    }

    /// Asks the autopilot to stream message `id` every `interval_us` µs (the writer's own
    /// command: its result is only logged).
    pub fn request_stream(&mut self, message_id: u32, interval_us: f32) {
        let id = self.id();
        self.internal.push((id, mav_cmd::SET_MESSAGE_INTERVAL));
        self.runner
            .submit(id, CommandLong::message_interval(message_id, interval_us));
    }

    /// Lands the vehicle on the writer's own account (its planner is gone: see `orphan`); the
    /// result is only logged.
    pub fn land_on_own(&mut self) {
        let id = self.id();
        self.internal.push((id, mav_cmd::NAV_LAND));
        self.runner.submit(id, CommandLong::land());
    }

    /// A STATUSTEXT of warning severity or worse.
    pub fn on_status_text(&mut self, text: &str, now: Instant) {
        self.last_text = Some((text.to_owned(), now));
    }

    /// A COMMAND_ACK. Returns what it finished.
    pub fn on_ack(
        &mut self,
        command: u16,
        result: u8,
        now: Instant,
        facts: &AutopilotFacts,
    ) -> Vec<ProcedureEvent> {
        if let Some((id, outcome)) = self.runner.on_ack(command, result, now) {
            return self.on_command_done(id, outcome, now, facts);
        }
        // PX4's second answer to a mode switch: the real result.
        let mut events = Vec::new();
        if command == mav_cmd::DO_SET_MODE
            && let Some(job) = self.job
            && let Step::ConfirmMode { target, then, .. } = job.step
        {
            if result == mav_result::ACCEPTED {
                self.after(then, now, facts, &mut events);
            } else {
                let why = format!(
                    "the switch to {target:?} was refused ({})",
                    mav_result_name(result)
                );
                self.finish_rejected(u32::from(result), &why, &mut events);
            }
        }
        events
    }

    fn reason(&self, why: &str, since: Instant) -> String {
        match &self.last_text {
            Some((text, at)) if *at + TEXT_LOOKBACK >= since => {
                format!("{why}: PX4 says \"{text}\"")
            }
            _ => why.to_owned(),
        }
    }

    fn finish(
        &mut self,
        outcome: CommandOutcome,
        mav_result: u32,
        why: Option<&str>,
        events: &mut Vec<ProcedureEvent>,
    ) {
        let Some(job) = self.job.take() else { return };
        let mut result = CommandResultSample::new(job.seq, job.kind as u32, outcome, mav_result);
        if let Some(why) = why {
            result = result.with_reason(&self.reason(why, job.started));
        }
        events.push(ProcedureEvent::Done(result));
    }

    fn finish_rejected(&mut self, mav_result: u32, why: &str, events: &mut Vec<ProcedureEvent>) {
        self.finish(CommandOutcome::Rejected, mav_result, Some(why), events);
    }

    fn send(&mut self, msg: CommandLong, then: Then) {
        let id = self.id();
        self.runner.submit(id, msg);
        if let Some(job) = self.job.as_mut() {
            job.step = Step::Command { id, then };
        }
    }

    fn on_command_done(
        &mut self,
        id: u64,
        outcome: AckOutcome,
        now: Instant,
        facts: &AutopilotFacts,
    ) -> Vec<ProcedureEvent> {
        let mut events = Vec::new();
        if let Some(pos) = self.internal.iter().position(|(i, _)| *i == id) {
            let (_, command) = self.internal.swap_remove(pos);
            events.push(ProcedureEvent::Internal { command, outcome });
            return events;
        }
        let Some(job) = self.job else { return events };
        let Step::Command { id: waiting, then } = job.step else {
            return events;
        };
        if waiting != id {
            return events;
        }
        match outcome {
            AckOutcome::Accepted => {
                let target = match (job.kind, then) {
                    (_, Then::WaitReadyThenArm) => Some(Px4Mode::Hold),
                    (CommandKind::Offboard, _) => Some(Px4Mode::Offboard),
                    (CommandKind::Hold, _) => Some(Px4Mode::Hold),
                    _ => None,
                };
                match target {
                    Some(target) if facts.mode != target => {
                        if let Some(job) = self.job.as_mut() {
                            job.step = Step::ConfirmMode {
                                target,
                                until: now + MODE_CONFIRM_TIMEOUT,
                                then,
                            };
                        }
                    }
                    _ => self.after(then, now, facts, &mut events),
                }
            }
            AckOutcome::Rejected(code) => {
                let what = match then {
                    Then::WaitReadyThenArm => "the switch to Hold before arming".to_owned(),
                    Then::Finish => format!("{:?}", job.kind),
                };
                let why = format!("{what} was refused ({})", mav_result_name(code));
                self.finish_rejected(u32::from(code), &why, &mut events);
            }
            AckOutcome::TimedOut => self.finish(
                CommandOutcome::TimedOut,
                NO_MAV_RESULT,
                Some("no COMMAND_ACK after 3 tries"),
                &mut events,
            ),
            AckOutcome::LinkLost => self.finish(
                CommandOutcome::LinkLost,
                NO_MAV_RESULT,
                Some("no autopilot link"),
                &mut events,
            ),
        }
        events
    }

    /// The step after a command or a confirmed switch.
    fn after(
        &mut self,
        then: Then,
        now: Instant,
        facts: &AutopilotFacts,
        events: &mut Vec<ProcedureEvent>,
    ) {
        match then {
            Then::Finish => self.finish(
                CommandOutcome::Accepted,
                u32::from(mav_result::ACCEPTED),
                None,
                events,
            ),
            Then::WaitReadyThenArm => {
                if let Some(job) = self.job.as_mut() {
                    job.step = Step::WaitReady {
                        until: now + READY_TIMEOUT,
                    };
                }
                self.advance(now, facts, events);
            }
        }
    }

    /// Moves the current job on from a waiting step.
    fn advance(&mut self, now: Instant, facts: &AutopilotFacts, events: &mut Vec<ProcedureEvent>) {
        let Some(job) = self.job else { return };
        match job.step {
            Step::Start => match job.kind {
                CommandKind::Arm if !facts.armed && !armable(facts) => {
                    self.send(mode_command(Px4Mode::Hold), Then::WaitReadyThenArm)
                }
                CommandKind::Arm => self.after(Then::WaitReadyThenArm, now, facts, events),
                CommandKind::Takeoff => {
                    if let Some(job) = self.job.as_mut() {
                        job.step = Step::WaitAltitude {
                            until: now + ALTITUDE_TIMEOUT,
                            requested: false,
                        };
                    }
                    self.advance(now, facts, events);
                }
                CommandKind::Disarm => self.send(CommandLong::disarm(), Then::Finish),
                CommandKind::Land => self.send(CommandLong::land(), Then::Finish),
                // On the ground PX4 refuses the switch until its pre-flight checks pass.
                CommandKind::Offboard if !facts.armed && !facts.ready => {
                    if let Some(job) = self.job.as_mut() {
                        job.step = Step::WaitReady {
                            until: now + READY_TIMEOUT,
                        };
                    }
                }
                CommandKind::Offboard => self.send(mode_command(Px4Mode::Offboard), Then::Finish),
                CommandKind::Hold => self.send(mode_command(Px4Mode::Hold), Then::Finish),
            },
            Step::WaitReady { until } if job.kind == CommandKind::Offboard => {
                if facts.armed || facts.ready {
                    self.send(mode_command(Px4Mode::Offboard), Then::Finish);
                } else if !facts.link_ok {
                    self.finish(
                        CommandOutcome::LinkLost,
                        NO_MAV_RESULT,
                        Some("the autopilot link was lost while waiting for it to be ready"),
                        events,
                    );
                } else if now >= until {
                    let why = format!(
                        "the autopilot was not ready for offboard control after {} s (its pre-flight checks did not pass)",
                        READY_TIMEOUT.as_secs()
                    );
                    self.finish_rejected(NO_MAV_RESULT, &why, events);
                }
            }
            Step::WaitReady { until } => {
                if let SetupState::Failed(why) = &self.setup {
                    let why = format!("the autopilot could not be prepared for flight: {why}");
                    self.finish_rejected(NO_MAV_RESULT, &why, events);
                } else if facts.armed || (facts.ready && self.setup.allows_arming()) {
                    self.send(CommandLong::arm(), Then::Finish);
                } else if !facts.link_ok {
                    self.finish(
                        CommandOutcome::LinkLost,
                        NO_MAV_RESULT,
                        Some("the autopilot link was lost while waiting for it to be ready"),
                        events,
                    );
                } else if now >= until {
                    let why = if self.setup.allows_arming() {
                        format!(
                            "the autopilot was not ready to arm after {} s (its pre-flight checks did not pass)",
                            READY_TIMEOUT.as_secs()
                        )
                    } else {
                        format!(
                            "the autopilot's failsafe parameters and geofence were not confirmed within {} s",
                            READY_TIMEOUT.as_secs()
                        )
                    };
                    self.finish_rejected(NO_MAV_RESULT, &why, events);
                }
            }
            Step::WaitAltitude { until, requested } => {
                if let Some(amsl) = facts.amsl_m {
                    self.send(CommandLong::takeoff(amsl + job.param), Then::Finish);
                } else if now >= until {
                    let why = format!(
                        "no AMSL altitude from the autopilot (GLOBAL_POSITION_INT) within {} s: PX4's take-off altitude is AMSL",
                        ALTITUDE_TIMEOUT.as_secs()
                    );
                    self.finish_rejected(NO_MAV_RESULT, &why, events);
                } else if !requested {
                    let id = self.id();
                    self.internal.push((id, mav_cmd::REQUEST_MESSAGE));
                    self.runner
                        .submit(id, CommandLong::request_message(GLOBAL_POSITION_INT_ID));
                    if let Some(job) = self.job.as_mut() {
                        job.step = Step::WaitAltitude {
                            until,
                            requested: true,
                        };
                    }
                }
            }
            Step::ConfirmMode {
                target,
                until,
                then,
            } => {
                if facts.mode == target {
                    self.after(then, now, facts, events);
                } else if now >= until {
                    let why = format!(
                        "PX4 accepted the switch to {target:?} but still reports {:?} after {} s",
                        facts.mode,
                        MODE_CONFIRM_TIMEOUT.as_secs()
                    );
                    self.finish_rejected(NO_MAV_RESULT, &why, events);
                }
            }
            Step::Command { .. } => {}
        }
    }

    /// The command protocol's sends, and the commands it ended.
    fn poll_runner(
        &mut self,
        now: Instant,
        facts: &AutopilotFacts,
        events: &mut Vec<ProcedureEvent>,
    ) {
        for event in self.runner.poll(now, facts.link_ok) {
            match event {
                CommandEvent::Send(msg) => events.push(ProcedureEvent::Send(msg)),
                CommandEvent::Done { id, outcome } => {
                    let done = self.on_command_done(id, outcome, now, facts);
                    events.extend(done);
                }
            }
        }
    }

    /// Advances waits and timeouts, starts queued commands.
    pub fn poll(&mut self, now: Instant, facts: &AutopilotFacts) -> Vec<ProcedureEvent> {
        let mut events = Vec::new();
        self.poll_runner(now, facts, &mut events);
        // Each pass either starts a job or leaves one waiting, so this ends.
        for _ in 0..=self.queue.len() {
            if self.job.is_none() {
                let Some((sample, kind)) = self.queue.pop_front() else {
                    break;
                };
                self.job = Some(Job {
                    seq: sample.seq,
                    kind,
                    param: sample.param,
                    started: now,
                    step: Step::Start,
                });
            }
            self.advance(now, facts, &mut events);
            if self.job.is_some() {
                break;
            }
        }
        // Commands submitted just now go out in the same poll.
        self.poll_runner(now, facts, &mut events);
        events
    }

    /// When [`poll`](Self::poll) next has something to do, if anything.
    pub fn next_deadline(&self) -> Option<Instant> {
        let waiting = self.job.and_then(|j| match j.step {
            Step::WaitReady { until }
            | Step::WaitAltitude { until, .. }
            | Step::ConfirmMode { until, .. } => Some(until),
            _ => None,
        });
        match (waiting, self.runner.next_deadline()) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    pub fn is_idle(&self) -> bool {
        self.job.is_none() && self.queue.is_empty() && self.runner.is_idle()
    }
}

#[cfg(test)]
#[path = "procedure_tests.rs"]
mod tests;

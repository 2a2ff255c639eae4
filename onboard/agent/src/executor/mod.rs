//! The action executor: one drone's mode machine (unavailable → idle → flying ⇄ tracking),
//! one action at a time, turned into autopilot commands and a steering request: a still point
//! while the autopilot flies (take-off, landing), or a goal for the planner (goto, hold,
//! tracking).
//!
//! Pure: it is fed actions, vehicle state, command results, tracking stations and the time, and
//! returns what to send. The task shell (`runtime`) does the I/O; `motion` turns the steering
//! into setpoints.

use crate::motion::{Station, Steering};
use crate::planner::Goal;
use tacos_shared::action::{Action, ActionCommand, mode_forbids};
use tacos_shared::ipc::{
    CommandKind, CommandOutcome, CommandResultSample, CommandSample, VehicleStateSample,
};
use tacos_shared::messages::{ActionProgress, ActionState, FailsafeStage, FailureReason};
use tacos_shared::px4_mode::Px4Mode;
use tacos_shared::{DroneMode, Vec3};

mod failsafe;
mod landing;
mod takeoff;
mod view;

use landing::LandPhase;
use takeoff::TakeoffStep;
pub use view::{ExecutorConfig, POSITION_STALE_MS, TickOutput, VehicleView};

/// MAV_RESULT_TEMPORARILY_REJECTED: the autopilot may accept the same command a little later
/// (PX4 says so for an offboard switch before its setpoint stream has settled, which a loaded
/// companion computer can delay).
const MAV_RESULT_TEMPORARILY_REJECTED: u32 = 1;
/// How often, and how far apart, a temporarily rejected command is asked again.
const RETRIES_AFTER_TEMPORARY_REJECTION: u32 = 4;
const RETRY_AFTER_S: f64 = 0.5;

/// After an offboard switch is accepted, PX4's heartbeat (1 Hz) may still show the old mode for
/// this long; only after it do we believe a non-offboard mode means PX4 left offboard.
const MODE_REPORT_GRACE_S: f64 = 1.6;
/// A goto past its deadline still runs while it closes in: it fails once it has not come
/// nearer to its target by the arrival tolerance for this long. In a 20-drone swap through the
/// skyscrapers the last drone through the crowd at the centre needs more than the deadline's
/// 40% of top speed on average, while a drone that is stuck stops closing in.
const GOTO_STALL_S: f64 = 30.0;

#[derive(Debug, Clone, PartialEq)]
enum Task {
    /// Nothing commanded: the reference follows the vehicle.
    Idle,
    /// Taking off under offboard control from `pad` (see `takeoff`).
    Takeoff {
        step: TakeoffStep,
        pad: Vec3,
        deadline: f64,
    },
    /// The planner flies to `target` (around obstacles, apart from neighbours).
    Goto {
        target: Vec3,
        /// Distance to the target when the goto started, for progress.
        initial_distance: f64,
        /// Fails after this unless it is still closing in (see `GOTO_STALL_S`).
        deadline: f64,
        /// The nearest the vehicle has come to the target, and when it last came nearer by
        /// the arrival tolerance.
        nearest: f64,
        closed_in_at: f64,
    },
    /// The planner follows `target`'s station (see `motion::Station`) at `altitude`.
    Track {
        target: String,
        altitude: f64,
        started: f64,
        /// The latest station, once the target has been seen.
        station: Option<Goal>,
        /// The station was reached once: the action is done, the following goes on.
        acquired: bool,
        initial_distance: Option<f64>,
    },
    /// Airborne at `hold_point` under offboard control.
    Hold,
    /// Landing (see `landing`), failing after `deadline`.
    Land { phase: LandPhase, deadline: f64 },
}

pub struct Executor {
    cfg: ExecutorConfig,
    vehicle: Option<VehicleView>,
    task: Task,
    hold_point: Option<Vec3>,
    progress: Option<ActionProgress>,
    awaiting: Option<CommandSample>,
    /// A temporarily rejected command to ask again at a time, and the retries already made.
    retry: Option<(CommandSample, f64)>,
    retries: u32,
    outbox: Vec<CommandSample>,
    next_command_seq: u64,
    offboard_since: Option<f64>,
    failsafe: Option<FailsafeStage>,
    /// No neighbour heard for the bound (see `failsafe`).
    peers_silent: bool,
    /// PX4's mode while it flies the hovering drone after leaving offboard unasked.
    took_over: Option<Px4Mode>,
}

impl Executor {
    pub fn new(cfg: ExecutorConfig) -> Self {
        Executor {
            cfg,
            vehicle: None,
            task: Task::Idle,
            hold_point: None,
            progress: None,
            awaiting: None,
            retry: None,
            retries: 0,
            outbox: Vec::new(),
            next_command_seq: 1,
            offboard_since: None,
            failsafe: None,
            peers_silent: false,
            took_over: None,
        }
    }

    pub fn vehicle(&self) -> Option<&VehicleView> {
        self.vehicle.as_ref()
    }

    pub fn progress(&self) -> Option<&ActionProgress> {
        self.progress.as_ref()
    }

    pub fn failsafe(&self) -> Option<FailsafeStage> {
        self.failsafe
    }

    /// PX4's mode while PX4, not TACOS, flies the drone: it left offboard in flight without
    /// being asked (`DroneStatus::autopilot_took_over`). A running goto or tracking has failed
    /// with the reason; the drone holds until an action asks for offboard again.
    pub fn autopilot_took_over(&self) -> Option<Px4Mode> {
        self.took_over
    }

    /// The paper's mode of this drone.
    pub fn mode(&self) -> DroneMode {
        match &self.vehicle {
            None => DroneMode::Unavailable,
            Some(v) if !v.link_ok => DroneMode::Unavailable,
            Some(v) if !v.armed => DroneMode::Idle,
            Some(_) if matches!(self.task, Task::Track { .. }) => DroneMode::Tracking,
            Some(_) => DroneMode::Flying,
        }
    }

    /// The target followed now and the altitude to follow it at, for `motion::Motion::station`.
    pub fn following(&self) -> Option<(&str, f64)> {
        match &self.task {
            Task::Track {
                target, altitude, ..
            } => Some((target.as_str(), *altitude)),
            _ => None,
        }
    }

    /// Where the followed target's tracker says this drone should be now.
    pub fn on_station(&mut self, station: Station, now: f64) {
        let Some(vehicle) = self.vehicle else { return };
        let Task::Track {
            target,
            started,
            station: held,
            acquired,
            initial_distance,
            ..
        } = &mut self.task
        else {
            return;
        };
        let (target, started, was_acquired) = (target.clone(), *started, *acquired);
        let goal = match station {
            Station::At(goal) => goal,
            Station::Unseen if now - started <= self.cfg.unseen_timeout_s => return,
            Station::Unseen | Station::Lost => {
                self.hold_point = Some(vehicle.position);
                let reason = FailureReason::TargetLost(target);
                if was_acquired {
                    // The action finished when the station was reached; it is reported failed
                    // now, so whoever reads the status learns why the drone stopped following.
                    if let Some(p) = self.progress.as_mut() {
                        p.state = ActionState::Failed(reason.clone());
                    }
                }
                return self.fail(reason);
            }
        };
        *held = Some(goal);
        if was_acquired {
            return;
        }
        let distance = (vehicle.position - goal.position).norm();
        let initial = *initial_distance.get_or_insert(distance);
        if distance <= self.cfg.acquire_tolerance {
            *acquired = true;
            self.finish(ActionState::Done);
        } else if now - started > self.cfg.acquire_timeout_s {
            self.hold_point = Some(vehicle.position);
            self.fail(FailureReason::TimedOut);
        } else {
            let progress = 1.0 - distance / initial.max(1e-6);
            self.set_running(progress.clamp(0.0, 0.99) as f32);
        }
    }

    /// Armed and off the ground, with the autopilot link up.
    pub fn airborne(&self) -> bool {
        self.vehicle
            .is_some_and(|v| v.link_ok && v.armed && !v.landed)
    }

    fn request(&mut self, kind: CommandKind, param: f64) {
        self.retries = 0;
        self.send_request(kind, param);
    }

    fn send_request(&mut self, kind: CommandKind, param: f64) {
        let command = CommandSample::new(self.next_command_seq, kind, param);
        self.next_command_seq += 1;
        self.retry = None;
        self.awaiting = Some(command);
        self.outbox.push(command);
    }

    fn finish(&mut self, state: ActionState) {
        if let Some(p) = self.progress.as_mut().filter(|p| !p.state.is_finished()) {
            p.state = state;
        }
    }

    fn fail(&mut self, reason: FailureReason) {
        self.finish(ActionState::Failed(reason));
        self.awaiting = None;
        self.retry = None;
        self.task = if self.airborne() {
            Task::Hold
        } else {
            Task::Idle
        };
        if self.airborne() && self.hold_point.is_none() {
            self.hold_point = self.vehicle.map(|v| v.position);
        }
    }

    fn set_running(&mut self, progress: f32) {
        if let Some(p) = self.progress.as_mut().filter(|p| !p.state.is_finished()) {
            p.state = ActionState::Running { progress };
        }
    }

    fn in_offboard(&self) -> bool {
        self.vehicle.is_some_and(|v| v.px4 == Px4Mode::Offboard)
    }

    /// An offboard switch is in flight or waits to be asked again.
    fn offboard_asked(&self) -> bool {
        self.awaiting
            .or(self.retry.map(|(c, _)| c))
            .is_some_and(|c| c.kind() == Some(CommandKind::Offboard))
    }

    /// Asks for offboard unless PX4 is already there or the request is in flight.
    fn ensure_offboard(&mut self) {
        if !self.in_offboard() && !self.offboard_asked() {
            self.request(CommandKind::Offboard, 0.0);
        }
    }

    /// A new action from the ground. Returns false when it repeats the current one (same seq)
    /// and was ignored.
    pub fn on_command(&mut self, command: &ActionCommand, now: f64) -> bool {
        if self.progress.as_ref().is_some_and(|p| p.seq == command.seq) {
            return false;
        }
        // Whatever ran before is replaced; the ground sees the newer seq in the status.
        self.progress = Some(ActionProgress::started(command));
        self.awaiting = None;
        self.retry = None;
        if let Some(why) = mode_forbids(&command.action, self.mode()) {
            self.finish(ActionState::Failed(FailureReason::InvalidForMode(
                why.to_owned(),
            )));
            return true;
        }
        if let Some(why) = self.failsafe_refusal(&command.action) {
            self.finish(ActionState::Failed(FailureReason::Failsafe(why.into())));
            return true;
        }
        let Some(vehicle) = self.vehicle else {
            self.finish(ActionState::Failed(FailureReason::AutopilotLinkLost));
            return true;
        };
        let limits = self.cfg.limits;
        match &command.action {
            Action::ArmTakeoff => self.start_takeoff(vehicle.position, now),
            Action::Goto { target } => {
                // Only the point itself can make a goto impossible: the planner flies round
                // whatever stands between.
                let radius = self.cfg.limits.drone_radius;
                if let Err(why) = self.cfg.world.check_point(target, radius) {
                    self.fail(FailureReason::Unreachable(why.to_string()));
                    return true;
                }
                let initial_distance = (target - vehicle.position).norm();
                // Room for detours and for giving way, at 40% of the top speed on average.
                let deadline = now + initial_distance / (0.4 * limits.max_speed) + 30.0;
                self.task = Task::Goto {
                    target: *target,
                    initial_distance,
                    deadline,
                    nearest: initial_distance,
                    closed_in_at: now,
                };
                self.ensure_offboard();
            }
            Action::Hold => {
                if self.airborne() {
                    self.hold_point = Some(vehicle.position);
                    self.task = Task::Hold;
                    self.ensure_offboard();
                    if self.in_offboard() {
                        self.finish(ActionState::Done);
                    }
                } else {
                    self.finish(ActionState::Done);
                }
            }
            Action::Land => self.start_landing(now),
            Action::StopTracking => {
                // Whether it was tracking or just flying, holding where it is is the result.
                self.hold_point = Some(vehicle.position);
                self.task = Task::Hold;
                self.finish(ActionState::Done);
            }
            Action::StartTracking { target } => {
                let altitude = self
                    .hold_point
                    .map_or(vehicle.position.z, |p| p.z)
                    .max(limits.takeoff_altitude);
                self.hold_point = Some(vehicle.position);
                self.task = Task::Track {
                    target: target.clone(),
                    altitude,
                    started: now,
                    station: None,
                    acquired: false,
                    initial_distance: None,
                };
                self.ensure_offboard();
            }
        }
        true
    }

    /// New vehicle state from the writer.
    pub fn on_vehicle(&mut self, state: &VehicleStateSample) {
        self.vehicle = Some(VehicleView::from(state));
        self.take_over_if_flying();
    }

    /// An onboard with nothing to do beside a vehicle flying under offboard control (it was
    /// restarted mid-flight, or the autopilot link came back) holds where the vehicle is,
    /// through the planner: it goes on giving way and correcting drift, and reports itself
    /// flying, so the ground can give it work. Streaming "stay where you are now" instead
    /// never corrected drift and gave way to nobody. A vehicle in another PX4 mode (PX4's own
    /// failsafe, a pilot's switch) is left to PX4.
    fn take_over_if_flying(&mut self) {
        if self.task == Task::Idle && self.airborne() && self.in_offboard() {
            self.hold_point = self.vehicle.map(|v| v.position);
            self.task = Task::Hold;
        }
    }

    /// The writer has gone quiet: treat the autopilot link as lost until state arrives again.
    pub fn on_writer_silent(&mut self) {
        if let Some(v) = self.vehicle.as_mut() {
            v.link_ok = false;
        }
    }

    /// A command result from the writer.
    pub fn on_result(&mut self, result: &CommandResultSample, now: f64) {
        let Some(awaiting) = self.awaiting.filter(|c| c.seq == result.seq) else {
            return; // a result for a command we no longer wait on
        };
        self.awaiting = None;
        let kind = awaiting.kind();
        match result.outcome() {
            Some(CommandOutcome::Accepted) => {}
            // PX4 refuses a disarm it does not think landed: its own disarm after landing
            // (COM_DISARM_LAND) follows, or the landing's fallback does.
            Some(_)
                if kind == Some(CommandKind::Disarm) && matches!(self.task, Task::Land { .. }) =>
            {
                return;
            }
            Some(CommandOutcome::Rejected)
                if result.mav_result == MAV_RESULT_TEMPORARILY_REJECTED
                    && self.retries < RETRIES_AFTER_TEMPORARY_REJECTION =>
            {
                self.retries += 1;
                self.retry = Some((awaiting, now + RETRY_AFTER_S));
                return;
            }
            Some(CommandOutcome::Rejected) => {
                let why = match result.reason() {
                    Some(reason) => format!("{kind:?} refused: {reason}"),
                    None => format!("{kind:?} refused (MAV_RESULT {})", result.mav_result),
                };
                return self.fail(FailureReason::Rejected(why));
            }
            Some(CommandOutcome::TimedOut) => return self.fail(FailureReason::TimedOut),
            Some(CommandOutcome::LinkLost) => return self.fail(FailureReason::AutopilotLinkLost),
            Some(CommandOutcome::Unsupported) | None => {
                return self.fail(FailureReason::Rejected(format!(
                    "{kind:?} not supported by the writer"
                )));
            }
        }
        if kind == Some(CommandKind::Offboard) {
            self.offboard_since = Some(now);
        }
        match (&self.task, kind) {
            (Task::Takeoff { .. }, Some(kind)) => self.takeoff_accepted(kind),
            (Task::Hold, Some(CommandKind::Offboard)) => self.finish(ActionState::Done),
            (Task::Land { .. }, Some(CommandKind::Land)) => self.landing_accepted(),
            _ => {}
        }
    }

    /// Advances the task; returns the reference to stream and the commands to send.
    pub fn tick(&mut self, now: f64) -> TickOutput {
        let Some(vehicle) = self.vehicle else {
            return TickOutput::default();
        };
        if !vehicle.link_ok {
            if self
                .progress
                .as_ref()
                .is_some_and(|p| !p.state.is_finished())
            {
                self.fail(FailureReason::AutopilotLinkLost);
            }
            self.task = Task::Idle;
        }
        if let Some((command, at)) = self.retry
            && now >= at
            && let Some(kind) = command.kind()
        {
            self.send_request(kind, command.param);
        }
        self.advance(vehicle, now);
        self.took_over = self.px4_flies_it(&vehicle, now).then_some(vehicle.px4);
        let hold_point = self.hold_point.unwrap_or(vehicle.position);
        let steering = match &self.task {
            Task::Goto { target, .. } => Steering::Toward(Goal::fixed(*target)),
            // Until the target is seen, wait where the tracking started.
            Task::Track { station, .. } => {
                Steering::Toward(station.unwrap_or(Goal::fixed(hold_point)))
            }
            Task::Hold => Steering::Toward(Goal::fixed(hold_point)),
            Task::Takeoff { step, pad, .. } => self.takeoff_steering(*step, *pad),
            Task::Land { phase, .. } => self
                .landing_steering(phase, now)
                .unwrap_or(Steering::Still(vehicle.position)),
            Task::Idle => Steering::Still(vehicle.position),
        };
        TickOutput {
            steering: Some(steering),
            commands: std::mem::take(&mut self.outbox),
        }
    }

    /// PX4, not TACOS, flies the airborne drone: it left offboard under a hold (a goto or
    /// tracking it ended is a hold by now, the task having advanced), or this onboard found it
    /// flying in another mode (a restarted onboard or writer: PX4's offboard-loss failsafe
    /// had it). Not during a take-off or landing, which run in PX4's own modes.
    fn px4_flies_it(&self, vehicle: &VehicleView, now: f64) -> bool {
        self.airborne()
            && match self.task {
                Task::Hold => self.left_offboard(vehicle, now),
                Task::Idle => vehicle.px4 != Px4Mode::Offboard && !self.offboard_asked(),
                _ => false,
            }
    }

    fn left_offboard(&self, vehicle: &VehicleView, now: f64) -> bool {
        let settled = self
            .offboard_since
            .is_some_and(|t| now - t > MODE_REPORT_GRACE_S);
        settled && !self.offboard_asked() && vehicle.px4 != Px4Mode::Offboard
    }

    fn advance(&mut self, vehicle: VehicleView, now: f64) {
        let limits = self.cfg.limits;
        match self.task.clone() {
            Task::Idle => {
                if !vehicle.armed {
                    self.hold_point = None;
                }
            }
            Task::Takeoff {
                step,
                pad,
                deadline,
            } => self.advance_takeoff(step, pad, deadline, now),
            Task::Goto {
                target,
                initial_distance,
                deadline,
                nearest,
                closed_in_at,
            } => {
                if !vehicle.armed {
                    return self.fail(disarmed_in_flight());
                }
                if self.left_offboard(&vehicle, now) {
                    self.hold_point = Some(vehicle.position);
                    return self.fail(FailureReason::Rejected(format!(
                        "the autopilot left offboard for {}",
                        vehicle.px4
                    )));
                }
                let distance = (vehicle.position - target).norm();
                let close = distance <= self.cfg.arrive_tolerance;
                let slow = vehicle.velocity.norm() <= (0.1 * limits.max_speed).max(0.2);
                if close && slow {
                    self.hold_point = Some(target);
                    self.task = Task::Hold;
                    self.finish(ActionState::Done);
                } else if now > deadline.max(closed_in_at + GOTO_STALL_S) {
                    self.hold_point = Some(vehicle.position);
                    self.fail(FailureReason::TimedOut);
                } else {
                    if distance < nearest - self.cfg.arrive_tolerance {
                        self.task = Task::Goto {
                            target,
                            initial_distance,
                            deadline,
                            nearest: distance,
                            closed_in_at: now,
                        };
                    }
                    let progress = 1.0 - distance / initial_distance.max(1e-6);
                    self.set_running(progress.clamp(0.0, 0.99) as f32);
                }
            }
            Task::Track { .. } => {
                if self.left_offboard(&vehicle, now) {
                    self.hold_point = Some(vehicle.position);
                    return self.fail(FailureReason::Rejected(format!(
                        "the autopilot left offboard for {}",
                        vehicle.px4
                    )));
                }
                if !vehicle.armed {
                    self.fail(disarmed_in_flight());
                }
            }
            Task::Hold => {
                if self.hold_point.is_none() {
                    self.hold_point = Some(vehicle.position);
                }
                if !vehicle.armed {
                    self.task = Task::Idle;
                }
            }
            Task::Land { phase, deadline } => self.advance_landing(phase, deadline, now),
        }
    }
}

/// A goto or a tracking whose vehicle disarmed under it: it came down (a crash, or PX4's land
/// detector after the drone was pressed into the ground) and cannot go on.
fn disarmed_in_flight() -> FailureReason {
    FailureReason::InvalidForMode("the vehicle disarmed: it is on the ground".into())
}

#[cfg(test)]
mod failsafe_tests;
#[cfg(test)]
mod landing_tests;
#[cfg(test)]
mod tests;

//! Shared-memory payloads between `tacos-onboard` and `tacos-px4` (iceoryx2).
//!
//! Plain `#[repr(C)]` data with no pointers, so they can live in shared memory. Positions and
//! velocities are in the world frame (ENU); only the writer converts to the vehicle's NED.

use crate::geometry::Vec3;
use iceoryx2::prelude::ZeroCopySend;

/// One position/velocity/acceleration reference for the offboard stream.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct SetpointSample {
    pub seq: u64,
    /// Sender's clock, nanoseconds (used for latency measurement and staleness).
    pub stamp_ns: u64,
    pub position: [f64; 3],
    pub velocity: [f64; 3],
    pub acceleration: [f64; 3],
    /// ENU yaw in radians; NaN keeps the current heading.
    pub yaw: f64,
}

impl SetpointSample {
    pub fn position(&self) -> Vec3 {
        Vec3::from(self.position)
    }
    pub fn velocity(&self) -> Vec3 {
        Vec3::from(self.velocity)
    }
    pub fn acceleration(&self) -> Vec3 {
        Vec3::from(self.acceleration)
    }
    pub fn is_finite(&self) -> bool {
        self.position
            .iter()
            .chain(&self.velocity)
            .chain(&self.acceleration)
            .all(|c| c.is_finite())
    }
}

/// A command for the autopilot, carried out by the writer with acks, timeouts and retries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum CommandKind {
    Arm = 1,
    Disarm = 2,
    /// `param` = altitude above home, metres.
    Takeoff = 3,
    Land = 4,
    /// Switch to offboard (the writer has been streaming setpoints).
    Offboard = 5,
    /// Switch to PX4's hold (AUTO.LOITER).
    Hold = 6,
}

impl CommandKind {
    pub fn from_code(code: u32) -> Option<CommandKind> {
        Some(match code {
            1 => CommandKind::Arm,
            2 => CommandKind::Disarm,
            3 => CommandKind::Takeoff,
            4 => CommandKind::Land,
            5 => CommandKind::Offboard,
            6 => CommandKind::Hold,
            _ => return None,
        })
    }
}

#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct CommandSample {
    pub seq: u64,
    /// A [`CommandKind`] code.
    pub kind: u32,
    pub _reserved: u32,
    pub param: f64,
}

impl CommandSample {
    pub fn new(seq: u64, kind: CommandKind, param: f64) -> Self {
        CommandSample {
            seq,
            kind: kind as u32,
            _reserved: 0,
            param,
        }
    }
    pub fn kind(&self) -> Option<CommandKind> {
        CommandKind::from_code(self.kind)
    }
}

/// How a command ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum CommandOutcome {
    Accepted = 0,
    /// The autopilot answered with a refusal; `mav_result` holds its MAV_RESULT.
    Rejected = 1,
    /// No ack after every retry.
    TimedOut = 2,
    /// No autopilot link when the command was due.
    LinkLost = 3,
    /// The command code was not understood by the writer.
    Unsupported = 4,
}

impl CommandOutcome {
    pub fn from_code(code: u32) -> Option<CommandOutcome> {
        Some(match code {
            0 => CommandOutcome::Accepted,
            1 => CommandOutcome::Rejected,
            2 => CommandOutcome::TimedOut,
            3 => CommandOutcome::LinkLost,
            4 => CommandOutcome::Unsupported,
            _ => return None,
        })
    }
}

/// Room for a result's reason: PX4's STATUSTEXT is at most 50 characters, and the writer's own
/// words round it (what it waited for, for how long).
pub const REASON_BYTES: usize = 160;

#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct CommandResultSample {
    pub seq: u64,
    pub kind: u32,
    /// A [`CommandOutcome`] code.
    pub outcome: u32,
    /// MAV_RESULT from the COMMAND_ACK, when there was one.
    pub mav_result: u32,
    /// How many bytes of `reason` are used.
    pub reason_len: u32,
    /// Why it ended so, in UTF-8: the autopilot's own words (STATUSTEXT) where it gave any.
    pub reason: [u8; REASON_BYTES],
}

impl Default for CommandResultSample {
    fn default() -> Self {
        CommandResultSample {
            seq: 0,
            kind: 0,
            outcome: 0,
            mav_result: 0,
            reason_len: 0,
            reason: [0; REASON_BYTES],
        }
    }
}

impl CommandResultSample {
    pub fn new(seq: u64, kind: u32, outcome: CommandOutcome, mav_result: u32) -> Self {
        CommandResultSample {
            seq,
            kind,
            outcome: outcome as u32,
            mav_result,
            ..Default::default()
        }
    }

    /// The same result with `reason` (cut at a character boundary to fit).
    pub fn with_reason(mut self, reason: &str) -> Self {
        let mut end = reason.len().min(REASON_BYTES);
        while !reason.is_char_boundary(end) {
            end -= 1;
        }
        self.reason = [0; REASON_BYTES];
        self.reason[..end].copy_from_slice(&reason.as_bytes()[..end]);
        self.reason_len = end as u32;
        self
    }

    pub fn outcome(&self) -> Option<CommandOutcome> {
        CommandOutcome::from_code(self.outcome)
    }

    /// The reason, if any; bytes that are not UTF-8 (a foreign writer) give none.
    pub fn reason(&self) -> Option<&str> {
        let len = (self.reason_len as usize).min(REASON_BYTES);
        std::str::from_utf8(&self.reason[..len])
            .ok()
            .filter(|r| !r.is_empty())
    }
}

/// The vehicle as the writer sees it over MAVLink, published at the rate LOCAL_POSITION_NED
/// arrives and whenever the link state changes.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct VehicleStateSample {
    pub stamp_ns: u64,
    /// 1 while heartbeats arrive (none for 3 s → 0).
    pub link_ok: u32,
    pub armed: u32,
    /// PX4 custom mode from the last HEARTBEAT (see `px4_mode`).
    pub custom_mode: u32,
    /// 1 when PX4 reports the vehicle on the ground (EXTENDED_SYS_STATE or altitude).
    pub landed: u32,
    /// World frame (ENU), metres.
    pub position: [f64; 3],
    /// World frame (ENU), m/s.
    pub velocity: [f64; 3],
    /// Milliseconds since the last heartbeat.
    pub heartbeat_age_ms: u64,
    /// Milliseconds since the last position from the autopilot ([`NEVER_MS`] before the first):
    /// an autopilot whose heartbeats still come but whose estimate is gone has a stale position.
    pub position_age_ms: u64,
    /// 1 when the autopilot says it can arm (PX4: HEARTBEAT system_status STANDBY, its
    /// pre-flight checks pass) or is already armed.
    pub ready: u32,
    pub _reserved: u32,
}

/// `heartbeat_age_ms` / `position_age_ms` before the first one.
pub const NEVER_MS: u64 = u64::MAX;

impl VehicleStateSample {
    pub fn position(&self) -> Vec3 {
        Vec3::from(self.position)
    }
    pub fn velocity(&self) -> Vec3 {
        Vec3::from(self.velocity)
    }
    pub fn mode(&self) -> crate::px4_mode::Px4Mode {
        crate::px4_mode::Px4Mode::from_custom_mode(self.custom_mode)
    }
}

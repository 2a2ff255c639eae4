//! Which messages a vehicle streams on its MAVLink link, and how often: PX4's per-link stream
//! table, changed by `MAV_CMD_SET_MESSAGE_INTERVAL` and read once by `MAV_CMD_REQUEST_MESSAGE`;
//! and the link's queue of protocol replies ([`Reply`]: parameters, geofence), which go out
//! with the next telemetry, before the streams that are due.
//! Pure: the clock (sim seconds) is passed in.

use mavlink::dialects::common::{MavMissionResult, MavMissionType, MavResult};
use std::collections::VecDeque;
use std::fmt;
use std::str::FromStr;

/// A message the stand-in can stream, or a queued reply.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Stream {
    Heartbeat,
    SysStatus,
    Attitude,
    LocalPosition,
    GlobalPosition,
    HomePosition,
    ExtendedSysState,
    /// Not a stream: a reply of the parameter or mission protocol, sent once.
    Reply(Reply),
}

/// A reply of PX4's parameter or mission protocol, built from the vehicle when it goes out.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Reply {
    /// PARAM_VALUE of parameter `index` ([`crate::params`]).
    ParamValue(u16),
    /// MISSION_REQUEST_INT for item `seq` of a geofence upload ([`crate::fence`]).
    FenceRequest(u16),
    /// MISSION_ITEM_INT `seq` of the stored geofence.
    FenceItem(u16),
    /// MISSION_COUNT of what is stored of this mission type.
    MissionCount(MavMissionType),
    /// MISSION_ACK of a transfer of this mission type.
    MissionAck(MavMissionType, MavMissionResult),
}

impl Reply {
    pub fn message_id(self) -> u32 {
        match self {
            Reply::ParamValue(_) => 22,
            Reply::FenceRequest(_) => 51,
            Reply::FenceItem(_) => 73,
            Reply::MissionCount(_) => 44,
            Reply::MissionAck(..) => 47,
        }
    }
}

impl Stream {
    /// Every stream, in the order they go out when several are due at once.
    pub const ALL: [Stream; 7] = [
        Stream::Heartbeat,
        Stream::SysStatus,
        Stream::Attitude,
        Stream::LocalPosition,
        Stream::GlobalPosition,
        Stream::HomePosition,
        Stream::ExtendedSysState,
    ];

    /// The MAVLink message id.
    pub fn message_id(self) -> u32 {
        match self {
            Stream::Heartbeat => 0,
            Stream::SysStatus => 1,
            Stream::Attitude => 30,
            Stream::LocalPosition => 32,
            Stream::GlobalPosition => 33,
            Stream::HomePosition => 242,
            Stream::ExtendedSysState => 245,
            Stream::Reply(r) => r.message_id(),
        }
    }

    pub fn from_message_id(id: u32) -> Option<Stream> {
        Stream::ALL.into_iter().find(|s| s.message_id() == id)
    }

    /// A message id as a command parameter carries it (PX4 rounds it), if it names a stream.
    pub fn from_param(param: f32) -> Option<Stream> {
        if !(0.0..=1.0e6).contains(&param) {
            return None;
        }
        Stream::from_message_id(param.round() as u32)
    }
}

/// PX4's two stream tables that matter here: `-m onboard` (the SITL offboard link on 14540+i,
/// what the writer talks to) and `-m normal` (a telemetry radio on TELEM1, PX4's default on
/// hardware).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LinkProfile {
    #[default]
    Onboard,
    Normal,
}

impl LinkProfile {
    /// The default rate of a stream in Hz (0 = not streamed unless asked for).
    ///
    /// PX4's onboard mode: HEARTBEAT 1, SYS_STATUS 5, LOCAL_POSITION_NED 30, GLOBAL_POSITION_INT
    /// 50, HOME_POSITION 0.5, EXTENDED_SYS_STATE 5, ATTITUDE 100. Normal mode: 1, 1, 1, 5, 0.5,
    /// 1, 15. The stand-in models no attitude, so ATTITUDE (level, facing north) is off by
    /// default in both and sent only when asked for.
    pub fn default_rate_hz(self, stream: Stream) -> f64 {
        use Stream as S;
        match (self, stream) {
            (_, S::Heartbeat) => 1.0,
            (_, S::Attitude) => 0.0,
            (_, S::HomePosition) => 0.5,
            (LinkProfile::Onboard, S::SysStatus) => 5.0,
            (LinkProfile::Onboard, S::LocalPosition) => 30.0,
            (LinkProfile::Onboard, S::GlobalPosition) => 50.0,
            (LinkProfile::Onboard, S::ExtendedSysState) => 5.0,
            (LinkProfile::Normal, S::SysStatus) => 1.0,
            (LinkProfile::Normal, S::LocalPosition) => 1.0,
            (LinkProfile::Normal, S::GlobalPosition) => 5.0,
            (LinkProfile::Normal, S::ExtendedSysState) => 1.0,
            (_, S::Reply(_)) => 0.0,
        }
    }
}

impl FromStr for LinkProfile {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "onboard" => Ok(LinkProfile::Onboard),
            "normal" => Ok(LinkProfile::Normal),
            other => Err(format!(
                "unknown link profile {other:?} (onboard or normal)"
            )),
        }
    }
}

impl fmt::Display for LinkProfile {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            LinkProfile::Onboard => "onboard",
            LinkProfile::Normal => "normal",
        })
    }
}

#[derive(Debug, Clone, Copy)]
struct Entry {
    stream: Stream,
    /// Seconds between two sends; `None` = stopped.
    period: Option<f64>,
    next: f64,
}

/// The streams of one link.
#[derive(Debug, Clone)]
pub struct Streams {
    profile: LinkProfile,
    entries: Vec<Entry>,
    replies: VecDeque<Reply>,
}

/// Intervals shorter than this are taken as this (the simulator's physics step).
const MIN_PERIOD: f64 = 0.01;
/// Replies kept for a link that does not send (its link is down); the oldest go first.
const MAX_PENDING_REPLIES: usize = 256;

fn period_of(rate_hz: f64) -> Option<f64> {
    (rate_hz.is_finite() && rate_hz > 0.0).then(|| (1.0 / rate_hz).max(MIN_PERIOD))
}

impl Streams {
    /// The profile's default rates, everything due at `now`.
    pub fn new(profile: LinkProfile, now: f64) -> Self {
        Streams {
            profile,
            entries: Stream::ALL
                .into_iter()
                .map(|stream| Entry {
                    stream,
                    period: period_of(profile.default_rate_hz(stream)),
                    next: now,
                })
                .collect(),
            replies: VecDeque::new(),
        }
    }

    /// Queues a protocol reply for the next [`Streams::due`].
    pub fn reply(&mut self, reply: Reply) {
        if self.replies.len() >= MAX_PENDING_REPLIES {
            self.replies.pop_front();
        }
        self.replies.push_back(reply);
    }

    /// [`Streams::reply`] for each, in order.
    pub fn reply_all(&mut self, replies: impl IntoIterator<Item = Reply>) {
        for reply in replies {
            self.reply(reply);
        }
    }

    /// Seconds between two sends of `stream`; `None` when it is not streamed.
    pub fn period(&self, stream: Stream) -> Option<f64> {
        self.entries
            .iter()
            .find(|e| e.stream == stream)
            .and_then(|e| e.period)
    }

    /// The queued replies, then the streams due at `now`, each at most once per call, in
    /// [`Stream::ALL`] order.
    pub fn due(&mut self, now: f64) -> Vec<Stream> {
        let mut due: Vec<Stream> = self.replies.drain(..).map(Stream::Reply).collect();
        for e in &mut self.entries {
            let Some(period) = e.period else { continue };
            // A little slack, so that a schedule on the tick grid is not missed by rounding.
            if now + 1e-9 < e.next {
                continue;
            }
            due.push(e.stream);
            e.next += period;
            if e.next <= now {
                e.next = now + period;
            }
        }
        due
    }

    /// `MAV_CMD_SET_MESSAGE_INTERVAL`: `param1` the message id, `param2` the interval in µs
    /// (< 0 stops the stream, 0 or NaN restores the default). As PX4: FAILED for HEARTBEAT
    /// (its rate is fixed) and for a message it does not stream.
    pub fn set_interval(&mut self, param1: f32, param2: f32, now: f64) -> MavResult {
        let Some(stream) = Stream::from_param(param1) else {
            return MavResult::MAV_RESULT_FAILED;
        };
        if stream == Stream::Heartbeat {
            return MavResult::MAV_RESULT_FAILED;
        }
        let profile = self.profile;
        let Some(e) = self.entries.iter_mut().find(|e| e.stream == stream) else {
            return MavResult::MAV_RESULT_FAILED;
        };
        e.period = if param2 < -1e-5 {
            None
        } else if param2 > 1e-5 {
            Some((f64::from(param2) * 1e-6).max(MIN_PERIOD))
        } else {
            period_of(profile.default_rate_hz(stream))
        };
        if let Some(period) = e.period {
            e.next = e.next.min(now + period);
        }
        MavResult::MAV_RESULT_ACCEPTED
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// How many times `stream` goes out over `seconds` of 10 ms ticks.
    fn count(streams: &mut Streams, stream: Stream, from: f64, seconds: f64) -> usize {
        let ticks = (seconds / 0.01).round() as usize;
        (0..ticks)
            .filter(|k| streams.due(from + *k as f64 * 0.01).contains(&stream))
            .count()
    }

    #[test]
    fn onboard_defaults_are_px4s() {
        let mut s = Streams::new(LinkProfile::Onboard, 0.0);
        assert_eq!(
            s.due(0.0),
            vec![
                Stream::Heartbeat,
                Stream::SysStatus,
                Stream::LocalPosition,
                Stream::GlobalPosition,
                Stream::HomePosition,
                Stream::ExtendedSysState
            ],
            "everything but ATTITUDE at once"
        );
        let mut s = Streams::new(LinkProfile::Onboard, 0.0);
        assert_eq!(count(&mut s.clone(), Stream::Heartbeat, 0.0, 10.0), 10);
        assert_eq!(count(&mut s.clone(), Stream::LocalPosition, 0.0, 10.0), 300);
        assert_eq!(
            count(&mut s.clone(), Stream::GlobalPosition, 0.0, 10.0),
            500
        );
        assert_eq!(
            count(&mut s.clone(), Stream::ExtendedSysState, 0.0, 10.0),
            50
        );
        assert_eq!(count(&mut s.clone(), Stream::SysStatus, 0.0, 10.0), 50);
        assert_eq!(count(&mut s.clone(), Stream::HomePosition, 0.0, 10.0), 5);
        assert_eq!(count(&mut s, Stream::Attitude, 0.0, 10.0), 0);
        let mut n = Streams::new(LinkProfile::Normal, 0.0);
        assert_eq!(count(&mut n, Stream::LocalPosition, 0.0, 10.0), 10);
    }

    #[test]
    fn set_message_interval_changes_stops_and_restores() {
        let mut s = Streams::new(LinkProfile::Normal, 0.0);
        let lpn = Stream::LocalPosition.message_id() as f32;
        assert_eq!(
            s.set_interval(lpn, 20_000.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(count(&mut s, Stream::LocalPosition, 0.0, 10.0), 500);
        assert_eq!(
            s.set_interval(lpn, -1.0, 10.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(count(&mut s, Stream::LocalPosition, 10.0, 5.0), 0);
        assert_eq!(
            s.set_interval(lpn, 0.0, 15.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(
            count(&mut s, Stream::LocalPosition, 15.0, 10.0),
            10,
            "1 Hz again"
        );
        // ATTITUDE can be switched on; 1 µs is capped at the physics rate.
        assert_eq!(
            s.set_interval(30.0, 1.0, 25.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(s.period(Stream::Attitude), Some(MIN_PERIOD));
    }

    #[test]
    fn heartbeat_and_unknown_messages_fail() {
        let mut s = Streams::new(LinkProfile::Onboard, 0.0);
        for (id, interval) in [(0.0, 100_000.0), (147.0, 1e6), (f32::NAN, 1e6), (-3.0, 1e6)] {
            assert_eq!(
                s.set_interval(id, interval, 0.0),
                MavResult::MAV_RESULT_FAILED,
                "{id}"
            );
        }
        assert_eq!(s.period(Stream::Heartbeat), Some(1.0));
        assert_eq!(Stream::from_param(241.6), Some(Stream::HomePosition));
        assert_eq!(Stream::from_param(1e30), None);
    }

    #[test]
    fn replies_go_first_and_once() {
        let mut s = Streams::new(LinkProfile::Onboard, 0.0);
        s.due(0.0);
        s.reply_all([Reply::ParamValue(3), Reply::FenceRequest(0)]);
        assert_eq!(
            s.due(0.005),
            vec![
                Stream::Reply(Reply::ParamValue(3)),
                Stream::Reply(Reply::FenceRequest(0))
            ]
        );
        assert!(s.due(0.006).is_empty());
        assert_eq!(Stream::Reply(Reply::ParamValue(0)).message_id(), 22);
        assert_eq!(Stream::from_message_id(22), None, "not a stream");
        for i in 0..300 {
            s.reply(Reply::ParamValue(i));
        }
        let kept = s.due(0.007);
        assert_eq!(kept.len(), MAX_PENDING_REPLIES);
        assert_eq!(
            kept[0],
            Stream::Reply(Reply::ParamValue(44)),
            "oldest dropped"
        );
    }

    #[test]
    fn profiles_parse() {
        assert_eq!("normal".parse::<LinkProfile>(), Ok(LinkProfile::Normal));
        assert_eq!(LinkProfile::Onboard.to_string(), "onboard");
        assert!("fast".parse::<LinkProfile>().is_err());
    }
}

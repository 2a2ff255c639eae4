//! The autopilot parameters that decide what PX4 does when TACOS goes away, read and set with
//! the MAVLink parameter protocol, as a pure state machine (the clock is passed in).
//!
//! Each parameter is first read (PARAM_REQUEST_READ → PARAM_VALUE), which also gives its type;
//! a wanted value that differs is then set (PARAM_SET) and confirmed by PX4's echo. PX4 carries
//! INT32 values byte for byte in the float field (measured on PX4 SITL). A parameter that does
//! not answer after three tries is asked again after a pause, in up to four such rounds: fifteen
//! PX4 instances starting together on two cores left one silent for over 3 s. One that still
//! does not answer, or that PX4 will not take, fails the whole set: the writer then refuses to
//! arm and says which.

use std::time::{Duration, Instant};

/// How long to wait for a PARAM_VALUE.
pub const PARAM_TIMEOUT: Duration = Duration::from_secs(1);
pub const PARAM_TRIES: u8 = 3;
/// Rounds of [`PARAM_TRIES`] before a silent parameter fails the set, and the pause between.
pub const PARAM_ROUNDS: u8 = 4;
pub const PARAM_PAUSE: Duration = Duration::from_secs(2);
/// MAV_PARAM_TYPE values PX4 uses.
pub const TYPE_INT32: u8 = 6;
pub const TYPE_REAL32: u8 = 9;

/// A parameter value as PX4 types it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ParamValue {
    Int(i32),
    Real(f32),
}

impl ParamValue {
    /// From PARAM_VALUE's float field and type; `None` for types PX4 does not use.
    pub fn from_wire(value: f32, param_type: u8) -> Option<ParamValue> {
        match param_type {
            TYPE_INT32 => Some(ParamValue::Int(i32::from_le_bytes(value.to_le_bytes()))),
            TYPE_REAL32 => Some(ParamValue::Real(value)),
            _ => None,
        }
    }

    /// PARAM_SET's float field and type.
    pub fn to_wire(self) -> (f32, u8) {
        match self {
            ParamValue::Int(v) => (f32::from_le_bytes(v.to_le_bytes()), TYPE_INT32),
            ParamValue::Real(v) => (v, TYPE_REAL32),
        }
    }

    /// `wanted` in this value's type (an integer parameter takes a whole number only).
    fn with(self, wanted: f64) -> Option<ParamValue> {
        match self {
            ParamValue::Int(_) if wanted.fract() == 0.0 && wanted.abs() <= f64::from(i32::MAX) => {
                Some(ParamValue::Int(wanted as i32))
            }
            ParamValue::Int(_) => None,
            ParamValue::Real(_) => Some(ParamValue::Real(wanted as f32)),
        }
    }

    fn equals(self, other: ParamValue) -> bool {
        match (self, other) {
            (ParamValue::Int(a), ParamValue::Int(b)) => a == b,
            (ParamValue::Real(a), ParamValue::Real(b)) => (a - b).abs() <= 1e-6 * a.abs().max(1.0),
            _ => false,
        }
    }
}

impl std::fmt::Display for ParamValue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ParamValue::Int(v) => write!(f, "{v}"),
            ParamValue::Real(v) => write!(f, "{v}"),
        }
    }
}

/// One parameter: read it, and set it to `value` when given.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamWant {
    pub name: String,
    pub value: Option<f64>,
}

impl ParamWant {
    pub fn set(name: &str, value: f64) -> Self {
        ParamWant {
            name: name.to_owned(),
            value: Some(value),
        }
    }

    pub fn read(name: &str) -> Self {
        ParamWant {
            name: name.to_owned(),
            value: None,
        }
    }
}

/// The writer's defaults: what PX4 does when TACOS goes away.
pub fn failsafe_defaults() -> Vec<ParamWant> {
    vec![
        // Offboard lost (the writer died, the link dropped): hold where it is, not PX4's
        // default return-to-launch, which climbs to 60 m and flies home outside the planner's
        // deconfliction (0 Position, 3 Return, 4 Land, 5 Hold).
        ParamWant::set("COM_OBL_RC_ACT", 5.0),
        // After 1 s without setpoints.
        ParamWant::set("COM_OF_LOSS_T", 1.0),
        // The TACOS ground station is not a MAVLink GCS: a missing QGroundControl must not
        // trigger the data-link failsafe; the onboard's ground-silence failsafe covers the
        // ground instead.
        ParamWant::set("NAV_DLL_ACT", 0.0),
        // RC loss does not end offboard control (bit 2: offboard).
        ParamWant::set("COM_RCL_EXCEPT", 4.0),
        // Read only, for the log: what RC loss does and where RC comes from.
        ParamWant::read("NAV_RCL_ACT"),
        ParamWant::read("COM_RC_IN_MODE"),
    ]
}

/// What to send.
#[derive(Debug, Clone, PartialEq)]
pub enum ParamRequest {
    Read(String),
    Set(String, ParamValue),
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    Reading,
    Setting(ParamValue),
}

#[derive(Debug, Clone, PartialEq)]
struct Item {
    want: ParamWant,
    before: Option<ParamValue>,
    after: Option<ParamValue>,
}

/// Where the set stands.
#[derive(Debug, Clone, PartialEq)]
pub enum SyncState {
    Pending,
    Done,
    Failed(String),
}

#[derive(Debug, Clone)]
pub struct ParamSync {
    items: Vec<Item>,
    /// The item being worked on, its phase, tries and deadline.
    current: Option<(usize, Phase, u8, Instant)>,
    next: usize,
    failed: Option<String>,
    /// The item that went unanswered and the rounds it has had.
    rounds: (usize, u8),
    /// A pause after a round without an answer: asked again from then.
    resume_at: Option<Instant>,
}

impl ParamSync {
    pub fn new(wants: Vec<ParamWant>) -> Self {
        ParamSync {
            items: wants
                .into_iter()
                .map(|want| Item {
                    want,
                    before: None,
                    after: None,
                })
                .collect(),
            current: None,
            next: 0,
            failed: None,
            rounds: (0, 0),
            resume_at: None,
        }
    }

    pub fn state(&self) -> SyncState {
        match &self.failed {
            Some(why) => SyncState::Failed(why.clone()),
            None if self.next >= self.items.len() && self.current.is_none() => SyncState::Done,
            None => SyncState::Pending,
        }
    }

    /// (name, value before, value after) of every parameter handled so far.
    pub fn report(&self) -> Vec<(String, Option<ParamValue>, Option<ParamValue>)> {
        self.items
            .iter()
            .map(|i| (i.want.name.clone(), i.before, i.after))
            .collect()
    }

    fn request(&self, index: usize, phase: Phase) -> Option<ParamRequest> {
        let name = self.items.get(index)?.want.name.clone();
        Some(match phase {
            Phase::Reading => ParamRequest::Read(name),
            Phase::Setting(v) => ParamRequest::Set(name, v),
        })
    }

    /// Retries, timeouts and the next parameter.
    pub fn poll(&mut self, now: Instant) -> Vec<ParamRequest> {
        if self.failed.is_some() {
            return Vec::new();
        }
        match self.resume_at {
            Some(at) if now < at => return Vec::new(),
            Some(_) => self.resume_at = None,
            None => {}
        }
        if let Some((index, phase, tries, deadline)) = self.current {
            if now < deadline {
                return Vec::new();
            }
            if tries < PARAM_TRIES {
                self.current = Some((index, phase, tries + 1, now + PARAM_TIMEOUT));
                return self.request(index, phase).into_iter().collect();
            }
            self.current = None;
            let rounds = if self.rounds.0 == index {
                self.rounds.1 + 1
            } else {
                1
            };
            self.rounds = (index, rounds);
            if rounds < PARAM_ROUNDS {
                // The same parameter again, from its read, after a pause.
                self.next = index;
                self.resume_at = Some(now + PARAM_PAUSE);
                return Vec::new();
            }
            let name = self.items.get(index).map_or("?", |i| i.want.name.as_str());
            let tries = u16::from(PARAM_ROUNDS) * u16::from(PARAM_TRIES);
            self.failed = Some(match phase {
                Phase::Reading => {
                    format!("parameter {name} did not answer {tries} requests (is it in this PX4?)")
                }
                Phase::Setting(v) => format!("parameter {name} was not set to {v}"),
            });
            return Vec::new();
        }
        if self.next >= self.items.len() {
            return Vec::new();
        }
        let index = self.next;
        self.next += 1;
        self.current = Some((index, Phase::Reading, 1, now + PARAM_TIMEOUT));
        self.request(index, Phase::Reading).into_iter().collect()
    }

    /// A PARAM_VALUE from the autopilot.
    pub fn on_value(&mut self, name: &str, value: ParamValue, now: Instant) -> Vec<ParamRequest> {
        let Some((index, phase, _, _)) = self.current else {
            return Vec::new();
        };
        let Some(item) = self.items.get_mut(index).filter(|i| i.want.name == name) else {
            return Vec::new();
        };
        match phase {
            Phase::Reading => {
                item.before = Some(value);
                let target = item.want.value.map(|w| (w, value.with(w)));
                match target {
                    None => {
                        item.after = Some(value);
                        self.current = None;
                    }
                    Some((_, Some(t))) if t.equals(value) => {
                        item.after = Some(value);
                        self.current = None;
                    }
                    Some((_, Some(t))) => {
                        self.current = Some((index, Phase::Setting(t), 1, now + PARAM_TIMEOUT));
                        return self.request(index, Phase::Setting(t)).into_iter().collect();
                    }
                    Some((w, None)) => {
                        self.failed =
                            Some(format!("parameter {name} is an integer; {w} cannot be set"));
                        self.current = None;
                    }
                }
            }
            Phase::Setting(t) => {
                if t.equals(value) {
                    item.after = Some(value);
                    self.current = None;
                }
                // Another value echoed: PX4 kept the old one; the retry or timeout decides.
            }
        }
        self.poll(now)
    }

    pub fn next_deadline(&self) -> Option<Instant> {
        self.current.map(|(_, _, _, d)| d).or(self.resume_at)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(t0: Instant, ms: u64) -> Instant {
        t0 + Duration::from_millis(ms)
    }

    #[test]
    fn integers_travel_byte_for_byte_as_px4_sends_them() {
        // Measured: PX4 SITL answers COM_OBL_RC_ACT = 5 with param_value 7.0e-45 (the bits of
        // 5), type 6.
        assert_eq!(
            ParamValue::from_wire(f32::from_bits(5), TYPE_INT32),
            Some(ParamValue::Int(5))
        );
        assert_eq!(ParamValue::Int(5).to_wire().1, TYPE_INT32);
        assert_eq!(
            ParamValue::from_wire(ParamValue::Int(-3).to_wire().0, TYPE_INT32),
            Some(ParamValue::Int(-3))
        );
        assert_eq!(
            ParamValue::from_wire(1.0, TYPE_REAL32),
            Some(ParamValue::Real(1.0))
        );
        assert_eq!(ParamValue::from_wire(1.0, 1), None);
    }

    #[test]
    fn read_then_set_what_differs_then_confirm() {
        let t0 = Instant::now();
        let mut s = ParamSync::new(vec![
            ParamWant::set("COM_OBL_RC_ACT", 5.0),
            ParamWant::read("NAV_RCL_ACT"),
        ]);
        assert_eq!(
            s.poll(t0),
            vec![ParamRequest::Read("COM_OBL_RC_ACT".into())]
        );
        assert!(s.poll(at(t0, 10)).is_empty(), "one at a time");
        let set = s.on_value("COM_OBL_RC_ACT", ParamValue::Int(0), at(t0, 20));
        assert_eq!(
            set,
            vec![ParamRequest::Set(
                "COM_OBL_RC_ACT".into(),
                ParamValue::Int(5)
            )]
        );
        // An unrelated echo changes nothing.
        assert!(
            s.on_value("OTHER", ParamValue::Int(5), at(t0, 25))
                .is_empty()
        );
        let next = s.on_value("COM_OBL_RC_ACT", ParamValue::Int(5), at(t0, 30));
        assert_eq!(next, vec![ParamRequest::Read("NAV_RCL_ACT".into())]);
        assert_eq!(s.state(), SyncState::Pending);
        assert!(
            s.on_value("NAV_RCL_ACT", ParamValue::Int(2), at(t0, 40))
                .is_empty()
        );
        assert_eq!(s.state(), SyncState::Done);
        assert_eq!(
            s.report(),
            vec![
                (
                    "COM_OBL_RC_ACT".into(),
                    Some(ParamValue::Int(0)),
                    Some(ParamValue::Int(5))
                ),
                (
                    "NAV_RCL_ACT".into(),
                    Some(ParamValue::Int(2)),
                    Some(ParamValue::Int(2))
                ),
            ]
        );
    }

    /// Asked three times a second apart, then again after a 2 s pause, four rounds in all;
    /// then the set fails. A parameter that answers in a later round goes on as usual.
    #[test]
    fn a_silent_parameter_is_asked_in_rounds_then_fails_the_set() {
        let t0 = Instant::now();
        let mut s = ParamSync::new(vec![ParamWant::set("COM_OF_LOSS_T", 1.0)]);
        let mut asked = Vec::new();
        for ms in (0..=20_000).step_by(100) {
            if !s.poll(at(t0, ms)).is_empty() {
                asked.push(ms);
            }
        }
        assert_eq!(
            asked,
            [
                0, 1000, 2000, 5000, 6000, 7000, 10000, 11000, 12000, 15000, 16000, 17000
            ]
        );
        match s.state() {
            SyncState::Failed(why) => assert!(
                why.contains("COM_OF_LOSS_T") && why.contains("12 requests"),
                "{why}"
            ),
            other => panic!("expected a failure, got {other:?}"),
        }

        let mut s = ParamSync::new(vec![
            ParamWant::set("COM_OF_LOSS_T", 1.0),
            ParamWant::read("NAV_RCL_ACT"),
        ]);
        s.poll(t0);
        for ms in [1000, 2000, 3000] {
            s.poll(at(t0, ms));
        }
        assert_eq!(s.state(), SyncState::Pending, "paused, not failed");
        assert_eq!(s.next_deadline(), Some(at(t0, 5000)));
        assert_eq!(
            s.poll(at(t0, 5000)),
            [ParamRequest::Read("COM_OF_LOSS_T".into())]
        );
        assert_eq!(
            s.on_value("COM_OF_LOSS_T", ParamValue::Real(1.0), at(t0, 5100)),
            [ParamRequest::Read("NAV_RCL_ACT".into())]
        );
        s.on_value("NAV_RCL_ACT", ParamValue::Int(2), at(t0, 5200));
        assert_eq!(s.state(), SyncState::Done);
    }

    #[test]
    fn a_value_already_right_is_not_set_and_a_fraction_for_an_integer_fails() {
        let t0 = Instant::now();
        let mut s = ParamSync::new(vec![ParamWant::set("COM_OF_LOSS_T", 1.0)]);
        s.poll(t0);
        assert!(
            s.on_value("COM_OF_LOSS_T", ParamValue::Real(1.0), at(t0, 5))
                .is_empty()
        );
        assert_eq!(s.state(), SyncState::Done);
        let mut s = ParamSync::new(vec![ParamWant::set("NAV_DLL_ACT", 0.5)]);
        s.poll(t0);
        s.on_value("NAV_DLL_ACT", ParamValue::Int(0), at(t0, 5));
        assert!(matches!(s.state(), SyncState::Failed(_)));
    }

    /// PX4 answers, but keeps its old value: the set fails once its rounds are spent.
    #[test]
    fn a_refused_set_fails_after_its_tries() {
        let t0 = Instant::now();
        let mut s = ParamSync::new(vec![ParamWant::set("NAV_DLL_ACT", 0.0)]);
        let mut sets = 0;
        for ms in (0..=30_000).step_by(50) {
            for request in s.poll(at(t0, ms)) {
                // Read or set, the echo is the old value.
                sets += usize::from(matches!(request, ParamRequest::Set(..)));
                let name = match &request {
                    ParamRequest::Read(n) | ParamRequest::Set(n, _) => n.clone(),
                };
                for echo in s.on_value(&name, ParamValue::Int(2), at(t0, ms + 5)) {
                    sets += usize::from(matches!(echo, ParamRequest::Set(..)));
                }
            }
        }
        assert!(matches!(s.state(), SyncState::Failed(why) if why.contains("not set")));
        assert_eq!(
            sets,
            usize::from(PARAM_ROUNDS * PARAM_TRIES),
            "three sets a round"
        );
    }
}

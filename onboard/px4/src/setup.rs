//! Defence in depth on the autopilot: when the link comes up, the failsafe parameters are read
//! and set ([`crate::params`]), then the scenario's bounds are uploaded as PX4's geofence
//! ([`crate::fence`]) with its altitude limit and breach action. Until both are confirmed the
//! writer does not arm ([`crate::procedure`] waits on [`SetupState`]); if either fails, arming
//! is refused with the reason. Pure: the clock is passed in.

use crate::fence::{self, FenceRequest, FenceState, FenceUpload, Vertex};
use crate::params::{ParamRequest, ParamSync, ParamValue, ParamWant, SyncState};
use std::time::Instant;
use tacos_shared::Vec3;

/// PX4's GF_ACTION for a breach: 2 = hold where it is (1 warn, 3 return, 5 land).
pub const FENCE_ACTION_HOLD: f64 = 2.0;

/// The world box the geofence encloses (world ENU).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geofence {
    pub min: Vec3,
    pub max: Vec3,
}

/// How far outside the map's bounds PX4's geofence sits by default, metres. The safety gate
/// and the planner keep the drones inside the bounds; the fence is the backstop for when they
/// fail, so it must not trip on a drone TACOS holds inside them. On the lab map, whose pads
/// are 0.5 m from its south wall, a fence at the bounds tripped (PX4: "Geofence: approaching
/// or outside geofence", then its hold) on a drone hovering above its pad while PX4 SIH's
/// position estimate wandered about 1 m.
pub const DEFAULT_FENCE_MARGIN_M: f64 = 1.0;

impl Geofence {
    /// The box grown by `margin` on every side but the floor (the ceiling included).
    pub fn grown(self, margin: f64) -> Geofence {
        let m = Vec3::new(margin, margin, margin);
        Geofence {
            min: Vec3::new(self.min.x - margin, self.min.y - margin, self.min.z),
            max: self.max + m,
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub enum SetupState {
    Pending,
    Done,
    Failed(String),
    /// Not asked for (`--no-autopilot-setup`).
    Skipped,
}

impl SetupState {
    pub fn allows_arming(&self) -> bool {
        matches!(self, SetupState::Done | SetupState::Skipped)
    }
}

/// What to send.
#[derive(Debug, Clone, PartialEq)]
pub enum SetupRequest {
    Param(ParamRequest),
    Fence(FenceRequest),
}

/// What the autopilot said that the setup listens to.
#[derive(Debug, Clone, PartialEq)]
pub enum SetupMessage {
    ParamValue {
        name: String,
        value: ParamValue,
    },
    /// MISSION_REQUEST(_INT) for the fence.
    FenceRequest(u16),
    /// MISSION_ACK for the fence.
    FenceAck(u8),
    /// MISSION_COUNT of the fence.
    FenceCount(u16),
    /// MISSION_ITEM_INT of the fence.
    FenceItem {
        seq: u16,
        command: u16,
        vertex: Vertex,
    },
}

/// Where the vehicle is on Earth and in the world at once, to place the fence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeoFix {
    pub here: Vec3,
    pub lat_e7: i32,
    pub lon_e7: i32,
}

#[derive(Debug, Clone)]
pub struct AutopilotSetup {
    params: ParamSync,
    geofence: Option<Geofence>,
    fence: Option<FenceUpload>,
    skipped: bool,
}

impl AutopilotSetup {
    /// `params` plus, with a geofence, its altitude limit above `home_z` and its action.
    pub fn new(mut params: Vec<ParamWant>, geofence: Option<Geofence>, home_z: f64) -> Self {
        if let Some(g) = geofence {
            params.push(ParamWant::set("GF_ACTION", FENCE_ACTION_HOLD));
            params.push(ParamWant::set(
                "GF_MAX_VER_DIST",
                (g.max.z - home_z).max(1.0),
            ));
        }
        AutopilotSetup {
            params: ParamSync::new(params),
            geofence,
            fence: None,
            skipped: false,
        }
    }

    /// No setup: the autopilot is flown as configured by hand.
    pub fn skipped() -> Self {
        AutopilotSetup {
            params: ParamSync::new(Vec::new()),
            geofence: None,
            fence: None,
            skipped: true,
        }
    }

    pub fn state(&self) -> SetupState {
        if self.skipped {
            return SetupState::Skipped;
        }
        match self.params.state() {
            SyncState::Failed(why) => return SetupState::Failed(why),
            SyncState::Pending => return SetupState::Pending,
            SyncState::Done => {}
        }
        match (self.geofence, &self.fence) {
            (None, _) => SetupState::Done,
            (Some(_), None) => SetupState::Pending,
            (Some(_), Some(f)) => match f.state() {
                FenceState::Done => SetupState::Done,
                FenceState::Pending => SetupState::Pending,
                FenceState::Failed(why) => SetupState::Failed(why),
            },
        }
    }

    /// The parameters handled: (name, before, after).
    pub fn report(&self) -> Vec<(String, Option<ParamValue>, Option<ParamValue>)> {
        self.params.report()
    }

    /// Advances; the fence is built once the parameters are set and `fix` is known.
    pub fn poll(&mut self, now: Instant, fix: Option<GeoFix>) -> Vec<SetupRequest> {
        if self.skipped {
            return Vec::new();
        }
        let mut out: Vec<SetupRequest> = self
            .params
            .poll(now)
            .into_iter()
            .map(SetupRequest::Param)
            .collect();
        if self.params.state() != SyncState::Done {
            return out;
        }
        if let (Some(g), None, Some(fix)) = (self.geofence, &self.fence, fix) {
            let vertices = fence::rectangle(g.min, g.max, fix.here, fix.lat_e7, fix.lon_e7);
            self.fence = Some(FenceUpload::new(vertices));
        }
        if let Some(f) = self.fence.as_mut() {
            out.extend(f.poll(now).into_iter().map(SetupRequest::Fence));
        }
        out
    }

    pub fn on_message(&mut self, message: SetupMessage, now: Instant) -> Vec<SetupRequest> {
        if self.skipped {
            return Vec::new();
        }
        let fence = |f: &mut Option<FenceUpload>,
                     run: &dyn Fn(&mut FenceUpload) -> Vec<FenceRequest>| {
            f.as_mut()
                .map(|f| run(f).into_iter().map(SetupRequest::Fence).collect())
                .unwrap_or_default()
        };
        match message {
            SetupMessage::ParamValue { name, value } => self
                .params
                .on_value(&name, value, now)
                .into_iter()
                .map(SetupRequest::Param)
                .collect(),
            SetupMessage::FenceRequest(seq) => fence(&mut self.fence, &|f| f.on_request(seq, now)),
            SetupMessage::FenceAck(result) => fence(&mut self.fence, &|f| f.on_ack(result, now)),
            SetupMessage::FenceCount(count) => fence(&mut self.fence, &|f| f.on_count(count, now)),
            SetupMessage::FenceItem {
                seq,
                command,
                vertex,
            } => fence(&mut self.fence, &|f| f.on_item(seq, command, vertex, now)),
        }
    }

    pub fn next_deadline(&self) -> Option<Instant> {
        [
            self.params.next_deadline(),
            self.fence.as_ref().and_then(FenceUpload::next_deadline),
        ]
        .into_iter()
        .flatten()
        .min()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn the_fence_grows_on_the_sides_and_the_ceiling_but_not_into_the_floor() {
        let lab = Geofence {
            min: Vec3::new(-4.0, -4.0, 0.0),
            max: Vec3::new(4.0, 4.0, 2.5),
        };
        let fence = lab.grown(1.0);
        assert_eq!(fence.min, Vec3::new(-5.0, -5.0, 0.0));
        assert_eq!(fence.max, Vec3::new(5.0, 5.0, 3.5));
        assert_eq!(lab.grown(0.0), lab);
    }

    #[test]
    fn parameters_then_the_fence_then_done() {
        let t0 = Instant::now();
        let g = Geofence {
            min: Vec3::new(-100.0, -100.0, 0.0),
            max: Vec3::new(100.0, 100.0, 60.0),
        };
        let mut s = AutopilotSetup::new(vec![ParamWant::set("COM_OBL_RC_ACT", 5.0)], Some(g), 0.0);
        let fix = GeoFix {
            here: Vec3::zeros(),
            lat_e7: 473_977_420,
            lon_e7: 85_455_940,
        };
        let mut out = s.poll(t0, Some(fix));
        // Answer like PX4: each read with a differing value, each set with its echo.
        let mut steps = 0;
        while let Some(request) = out.pop() {
            steps += 1;
            assert!(steps < 40, "the setup does not end");
            let now = t0 + Duration::from_millis(steps);
            let message = match request {
                SetupRequest::Param(ParamRequest::Read(name)) => SetupMessage::ParamValue {
                    value: if name == "GF_MAX_VER_DIST" {
                        ParamValue::Real(0.0)
                    } else {
                        ParamValue::Int(0)
                    },
                    name,
                },
                SetupRequest::Param(ParamRequest::Set(name, value)) => {
                    SetupMessage::ParamValue { name, value }
                }
                SetupRequest::Fence(FenceRequest::Count(_)) => SetupMessage::FenceRequest(0),
                SetupRequest::Fence(FenceRequest::Item { seq, count, .. }) if seq + 1 < count => {
                    SetupMessage::FenceRequest(seq + 1)
                }
                SetupRequest::Fence(FenceRequest::Item { .. }) => SetupMessage::FenceAck(0),
                SetupRequest::Fence(FenceRequest::RequestList) => SetupMessage::FenceCount(4),
                SetupRequest::Fence(FenceRequest::RequestItem(seq)) => {
                    let v = fence::rectangle(g.min, g.max, fix.here, fix.lat_e7, fix.lon_e7);
                    SetupMessage::FenceItem {
                        seq,
                        command: fence::VERTEX_INCLUSION,
                        vertex: v[usize::from(seq)],
                    }
                }
                SetupRequest::Fence(FenceRequest::Ack) => break,
            };
            assert_eq!(s.state(), SetupState::Pending);
            out = s.on_message(message, now);
            if out.is_empty() {
                out = s.poll(now, Some(fix));
            }
        }
        assert_eq!(s.state(), SetupState::Done);
        let report = s.report();
        assert!(
            report
                .iter()
                .any(|(n, _, after)| n == "GF_MAX_VER_DIST"
                    && *after == Some(ParamValue::Real(60.0)))
        );
        assert!(
            report
                .iter()
                .any(|(n, _, after)| n == "GF_ACTION" && *after == Some(ParamValue::Int(2)))
        );
    }

    #[test]
    fn a_failed_parameter_blocks_arming_and_skipping_does_not() {
        let t0 = Instant::now();
        let mut s = AutopilotSetup::new(vec![ParamWant::set("NO_SUCH_PARAM", 1.0)], None, 0.0);
        // Every round of tries, and the pauses between them (`params::PARAM_ROUNDS`).
        for ms in (0..=20_000).step_by(500) {
            s.poll(t0 + Duration::from_millis(ms), None);
            if ms == 3000 {
                assert_eq!(
                    s.state(),
                    SetupState::Pending,
                    "paused after the first round"
                );
                assert!(!s.state().allows_arming());
            }
        }
        assert!(matches!(s.state(), SetupState::Failed(_)));
        assert!(!s.state().allows_arming());
        assert!(AutopilotSetup::skipped().state().allows_arming());
        assert_eq!(
            AutopilotSetup::new(Vec::new(), None, 0.0).state(),
            SetupState::Done,
            "nothing to set"
        );
    }
}

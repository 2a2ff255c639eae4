//! The scenario's bounds as PX4's own geofence, so that the autopilot stops a drone that leaves
//! them whatever the companion computer does: an inclusion polygon uploaded with the MAVLink
//! mission protocol (mission_type FENCE), read back and compared. The maximum altitude and the
//! breach action are parameters (`GF_MAX_VER_DIST`, `GF_ACTION`), set with the others
//! ([`crate::params`]). Pure: the clock is passed in.
//!
//! Upload: MISSION_COUNT → PX4 asks MISSION_REQUEST_INT(seq) for each item → MISSION_ITEM_INT →
//! MISSION_ACK. Read-back: MISSION_REQUEST_LIST → MISSION_COUNT → MISSION_REQUEST_INT(seq) →
//! MISSION_ITEM_INT, closed by our MISSION_ACK (measured on PX4 SITL).

use std::time::{Duration, Instant};
use tacos_shared::Vec3;

/// How long to wait for the autopilot's next step before asking again.
pub const STEP_TIMEOUT: Duration = Duration::from_secs(1);
pub const TRIES: u8 = 3;
/// MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION.
pub const VERTEX_INCLUSION: u16 = 5001;
const METRES_PER_DEG_LAT: f64 = 111_319.49;

/// A vertex in degrees × 10⁷, as MISSION_ITEM_INT carries it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Vertex {
    pub lat_e7: i32,
    pub lon_e7: i32,
}

/// The corners of the world ENU rectangle `min`..`max` (x, y) as geodetic vertices, from one
/// known point: the vehicle at `here` (world ENU) reported (`lat_e7`, `lon_e7`). Flat-earth
/// offsets, exact to centimetres over a map of a few hundred metres.
pub fn rectangle(min: Vec3, max: Vec3, here: Vec3, lat_e7: i32, lon_e7: i32) -> Vec<Vertex> {
    let lat = f64::from(lat_e7) / 1e7;
    let lon = f64::from(lon_e7) / 1e7;
    let at = |x: f64, y: f64| {
        let dlat = (y - here.y) / METRES_PER_DEG_LAT;
        let dlon = (x - here.x) / (METRES_PER_DEG_LAT * lat.to_radians().cos());
        Vertex {
            lat_e7: ((lat + dlat) * 1e7).round() as i32,
            lon_e7: ((lon + dlon) * 1e7).round() as i32,
        }
    };
    // Counter-clockwise from the south-west corner.
    vec![
        at(min.x, min.y),
        at(max.x, min.y),
        at(max.x, max.y),
        at(min.x, max.y),
    ]
}

/// What to send.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FenceRequest {
    Count(u16),
    /// Item `seq` of `count` (a polygon vertex knows how many vertices its polygon has).
    Item {
        seq: u16,
        count: u16,
        vertex: Vertex,
    },
    RequestList,
    RequestItem(u16),
    /// Closes a read-back.
    Ack,
}

#[derive(Debug, Clone, PartialEq)]
enum Phase {
    Uploading,
    ListRequested,
    Reading {
        count: u16,
        got: Vec<Option<Vertex>>,
    },
    Done,
    Failed(String),
}

#[derive(Debug, Clone)]
pub struct FenceUpload {
    vertices: Vec<Vertex>,
    phase: Phase,
    tries: u8,
    deadline: Option<Instant>,
}

/// Where the fence stands.
#[derive(Debug, Clone, PartialEq)]
pub enum FenceState {
    Pending,
    Done,
    Failed(String),
}

impl FenceUpload {
    pub fn new(vertices: Vec<Vertex>) -> Self {
        FenceUpload {
            vertices,
            phase: Phase::Uploading,
            tries: 0,
            deadline: None,
        }
    }

    pub fn state(&self) -> FenceState {
        match &self.phase {
            Phase::Done => FenceState::Done,
            Phase::Failed(why) => FenceState::Failed(why.clone()),
            _ => FenceState::Pending,
        }
    }

    fn count(&self) -> u16 {
        u16::try_from(self.vertices.len()).unwrap_or(u16::MAX)
    }

    fn fail(&mut self, why: String) {
        self.phase = Phase::Failed(why);
        self.deadline = None;
    }

    /// Starts and retries.
    pub fn poll(&mut self, now: Instant) -> Vec<FenceRequest> {
        if self.deadline.is_some_and(|d| now < d) {
            return Vec::new();
        }
        let request = match &self.phase {
            Phase::Done | Phase::Failed(_) => return Vec::new(),
            Phase::Uploading => FenceRequest::Count(self.count()),
            Phase::ListRequested => FenceRequest::RequestList,
            Phase::Reading { got, .. } => match got.iter().position(Option::is_none) {
                Some(seq) => FenceRequest::RequestItem(seq as u16),
                None => return Vec::new(),
            },
        };
        if self.tries >= TRIES {
            let what = match self.phase {
                Phase::Uploading => "the upload",
                _ => "the read-back",
            };
            self.fail(format!(
                "the geofence was not taken: no answer to {what} after {TRIES} tries"
            ));
            return Vec::new();
        }
        self.tries += 1;
        self.deadline = Some(now + STEP_TIMEOUT);
        vec![request]
    }

    fn progressed(&mut self, now: Instant) {
        self.tries = 0;
        self.deadline = Some(now + STEP_TIMEOUT);
    }

    /// MISSION_REQUEST_INT (or MISSION_REQUEST) for the fence.
    pub fn on_request(&mut self, seq: u16, now: Instant) -> Vec<FenceRequest> {
        if self.phase != Phase::Uploading {
            return Vec::new();
        }
        let Some(vertex) = self.vertices.get(usize::from(seq)).copied() else {
            self.fail(format!(
                "the autopilot asked for fence item {seq} of {}",
                self.count()
            ));
            return Vec::new();
        };
        self.progressed(now);
        vec![FenceRequest::Item {
            seq,
            count: self.count(),
            vertex,
        }]
    }

    /// MISSION_ACK for the fence; `result` is MAV_MISSION_RESULT (0 = accepted).
    pub fn on_ack(&mut self, result: u8, now: Instant) -> Vec<FenceRequest> {
        if self.phase != Phase::Uploading {
            return Vec::new();
        }
        if result != 0 {
            self.fail(format!(
                "the autopilot refused the geofence (MAV_MISSION_RESULT {result})"
            ));
            return Vec::new();
        }
        self.phase = Phase::ListRequested;
        self.tries = 0;
        self.deadline = None;
        self.poll(now)
    }

    /// MISSION_COUNT of the fence, during the read-back.
    pub fn on_count(&mut self, count: u16, now: Instant) -> Vec<FenceRequest> {
        if self.phase != Phase::ListRequested {
            return Vec::new();
        }
        if count != self.count() {
            self.fail(format!(
                "the autopilot holds {count} fence items, {} were sent",
                self.count()
            ));
            return Vec::new();
        }
        self.phase = Phase::Reading {
            count,
            got: vec![None; usize::from(count)],
        };
        self.tries = 0;
        self.deadline = None;
        self.poll(now)
    }

    /// MISSION_ITEM_INT of the fence, during the read-back.
    pub fn on_item(
        &mut self,
        seq: u16,
        command: u16,
        vertex: Vertex,
        now: Instant,
    ) -> Vec<FenceRequest> {
        let Phase::Reading { got, .. } = &mut self.phase else {
            return Vec::new();
        };
        let Some(slot) = got.get_mut(usize::from(seq)) else {
            return Vec::new();
        };
        *slot = Some(vertex);
        let sent = self.vertices.get(usize::from(seq)).copied();
        if command != VERTEX_INCLUSION || sent != Some(vertex) {
            self.fail(format!(
                "fence item {seq} read back as {vertex:?} (command {command}), {sent:?} was sent"
            ));
            return Vec::new();
        }
        let complete =
            matches!(&self.phase, Phase::Reading { got, .. } if got.iter().all(Option::is_some));
        if complete {
            self.phase = Phase::Done;
            self.deadline = None;
            return vec![FenceRequest::Ack];
        }
        self.progressed(now);
        self.deadline = None;
        self.poll(now)
    }

    pub fn next_deadline(&self) -> Option<Instant> {
        self.deadline
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(t0: Instant, ms: u64) -> Instant {
        t0 + Duration::from_millis(ms)
    }

    fn square() -> Vec<Vertex> {
        rectangle(
            Vec3::new(-100.0, -100.0, 0.0),
            Vec3::new(100.0, 100.0, 60.0),
            Vec3::new(0.0, 0.0, 0.0),
            473_977_420,
            85_455_940,
        )
    }

    #[test]
    fn the_rectangle_is_metres_around_the_known_point() {
        let v = square();
        assert_eq!(v.len(), 4);
        // 100 m north ≈ 8983 × 1e-7 degrees of latitude.
        assert_eq!(v[2].lat_e7 - 473_977_420, 8_983);
        assert_eq!(v[0].lat_e7 - 473_977_420, -8_983);
        assert!(v[1].lon_e7 > 85_455_940 && v[0].lon_e7 < 85_455_940);
        // Seen from elsewhere, the same corner.
        let moved = rectangle(
            Vec3::new(-100.0, -100.0, 0.0),
            Vec3::new(100.0, 100.0, 60.0),
            Vec3::new(0.0, 100.0, 0.0),
            v[2].lat_e7,
            85_455_940,
        );
        assert_eq!(moved[2], v[2]);
    }

    #[test]
    fn upload_then_read_back_and_compare() {
        let t0 = Instant::now();
        let mut f = FenceUpload::new(square());
        assert_eq!(f.poll(t0), vec![FenceRequest::Count(4)]);
        for seq in 0..4u16 {
            let out = f.on_request(seq, at(t0, 10));
            assert!(
                matches!(out.as_slice(), [FenceRequest::Item { seq: s, count: 4, .. }] if *s == seq)
            );
        }
        assert_eq!(f.on_ack(0, at(t0, 20)), vec![FenceRequest::RequestList]);
        assert_eq!(
            f.on_count(4, at(t0, 30)),
            vec![FenceRequest::RequestItem(0)]
        );
        let v = square();
        for seq in 0..3u16 {
            let out = f.on_item(seq, VERTEX_INCLUSION, v[usize::from(seq)], at(t0, 40));
            assert_eq!(out, vec![FenceRequest::RequestItem(seq + 1)]);
        }
        assert_eq!(
            f.on_item(3, VERTEX_INCLUSION, v[3], at(t0, 50)),
            vec![FenceRequest::Ack]
        );
        assert_eq!(f.state(), FenceState::Done);
    }

    #[test]
    fn refusals_differences_and_silence_fail_with_the_reason() {
        let t0 = Instant::now();
        let mut f = FenceUpload::new(square());
        f.poll(t0);
        f.on_ack(4, at(t0, 5));
        assert!(matches!(f.state(), FenceState::Failed(w) if w.contains("refused")));

        let mut f = FenceUpload::new(square());
        f.poll(t0);
        f.on_ack(0, at(t0, 5));
        f.on_count(4, at(t0, 6));
        let wrong = Vertex {
            lat_e7: 0,
            lon_e7: 0,
        };
        f.on_item(0, VERTEX_INCLUSION, wrong, at(t0, 7));
        assert!(matches!(f.state(), FenceState::Failed(w) if w.contains("read back")));

        let mut f = FenceUpload::new(square());
        assert_eq!(f.poll(t0).len(), 1);
        assert!(f.poll(at(t0, 999)).is_empty());
        assert_eq!(
            f.poll(at(t0, 1000)),
            vec![FenceRequest::Count(4)],
            "asked again"
        );
        assert_eq!(f.poll(at(t0, 2000)).len(), 1);
        assert!(f.poll(at(t0, 3000)).is_empty());
        assert!(matches!(f.state(), FenceState::Failed(w) if w.contains("no answer")));
    }
}

//! PX4's geofence as the MAVLink mission protocol sees it (mission_type FENCE), measured on PX4
//! SITL:
//! - Upload: MISSION_COUNT(n) → the vehicle asks MISSION_REQUEST_INT(seq) for seq 0..n-1, each
//!   answered with MISSION_ITEM_INT → after the last one, MISSION_ACK (ACCEPTED, or why not).
//!   A count of 0 clears the fence. A new MISSION_COUNT restarts an upload in progress (the
//!   client's retry after a lost message); the repeat of the item just received is ignored, an
//!   item out of order ends the upload with INVALID_SEQUENCE.
//! - Read-back: MISSION_REQUEST_LIST → MISSION_COUNT → MISSION_ITEM_INT for each
//!   MISSION_REQUEST_INT(seq), closed by the client's MISSION_ACK.
//!
//! An upload is checked as PX4 checks it before storing it: fence items only (5000 return
//! point, 5001/5002 polygon vertices, 5003/5004 circles) in a global frame, each polygon as
//! many consecutive vertices of one kind as its param1 says (at least 3), each circle with a
//! positive radius. The stored fence is only held and read back: the stand-in does not enforce
//! it (see [`crate::vehicle`]). Other mission types (missions, rally points) are not modelled:
//! an upload is refused as UNSUPPORTED and a download reports 0 items.
//! Pure: the replies come back as [`Reply`]s for the link's streams.

use crate::streams::Reply;
use mavlink::dialects::common::{
    MISSION_ITEM_INT_DATA, MavCmd, MavFrame, MavMissionResult, MavMissionType,
};

/// The most items the stand-in's fence holds.
pub const MAX_ITEMS: u16 = 64;

const RETURN_POINT: u32 = 5000;
const POLYGON_INCLUSION: u32 = 5001;
const POLYGON_EXCLUSION: u32 = 5002;
const CIRCLE_INCLUSION: u32 = 5003;
const CIRCLE_EXCLUSION: u32 = 5004;

#[derive(Debug, Clone, PartialEq)]
struct Upload {
    count: u16,
    items: Vec<MISSION_ITEM_INT_DATA>,
}

/// One vehicle's geofence and the transfer in progress.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Geofence {
    items: Vec<MISSION_ITEM_INT_DATA>,
    upload: Option<Upload>,
    /// (system, component) of the last client that spoke the mission protocol: replies are
    /// addressed to it (0, 0 = broadcast when unknown).
    partner: (u8, u8),
}

impl Geofence {
    /// The stored fence items, in order.
    pub fn items(&self) -> &[MISSION_ITEM_INT_DATA] {
        &self.items
    }

    pub fn partner(&self) -> (u8, u8) {
        self.partner
    }

    /// The stored count as MISSION_COUNT carries it.
    pub fn count(&self) -> u16 {
        u16::try_from(self.items.len()).unwrap_or(u16::MAX)
    }

    fn ack(result: MavMissionResult) -> Reply {
        Reply::MissionAck(MavMissionType::MAV_MISSION_TYPE_FENCE, result)
    }

    /// MISSION_COUNT for the fence from `partner`.
    pub fn on_count(&mut self, count: u16, partner: (u8, u8)) -> Vec<Reply> {
        self.partner = partner;
        if count == 0 {
            self.items.clear();
            self.upload = None;
            return vec![Self::ack(MavMissionResult::MAV_MISSION_ACCEPTED)];
        }
        if count > MAX_ITEMS {
            self.upload = None;
            return vec![Self::ack(MavMissionResult::MAV_MISSION_NO_SPACE)];
        }
        self.upload = Some(Upload {
            count,
            items: Vec::new(),
        });
        vec![Reply::FenceRequest(0)]
    }

    /// MISSION_ITEM_INT for the fence.
    pub fn on_item(&mut self, item: &MISSION_ITEM_INT_DATA, partner: (u8, u8)) -> Vec<Reply> {
        let Some(upload) = self.upload.as_mut() else {
            // Not uploading: PX4 ignores a stray item.
            return Vec::new();
        };
        self.partner = partner;
        let expected = u16::try_from(upload.items.len()).unwrap_or(u16::MAX);
        if item.seq.checked_add(1) == Some(expected) {
            return Vec::new(); // the repeat of the last one: its request is out already
        }
        if item.seq != expected {
            self.upload = None;
            return vec![Self::ack(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE)];
        }
        upload.items.push(item.clone());
        if upload.items.len() < usize::from(upload.count) {
            return vec![Reply::FenceRequest(expected + 1)];
        }
        let items = std::mem::take(&mut upload.items);
        self.upload = None;
        let result = check(&items);
        if result == MavMissionResult::MAV_MISSION_ACCEPTED {
            self.items = items;
        }
        vec![Self::ack(result)]
    }

    /// MISSION_REQUEST_LIST for the fence.
    pub fn on_request_list(&mut self, partner: (u8, u8)) -> Vec<Reply> {
        self.partner = partner;
        vec![Reply::MissionCount(MavMissionType::MAV_MISSION_TYPE_FENCE)]
    }

    /// MISSION_REQUEST_INT for item `seq` of the fence.
    pub fn on_request(&mut self, seq: u16, partner: (u8, u8)) -> Vec<Reply> {
        self.partner = partner;
        if usize::from(seq) < self.items.len() {
            vec![Reply::FenceItem(seq)]
        } else {
            vec![Self::ack(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE)]
        }
    }

    /// MISSION_CLEAR_ALL for the fence.
    pub fn on_clear(&mut self, partner: (u8, u8)) -> Vec<Reply> {
        self.partner = partner;
        self.items.clear();
        self.upload = None;
        vec![Self::ack(MavMissionResult::MAV_MISSION_ACCEPTED)]
    }
}

/// Whether PX4 takes these fence items; why not otherwise.
fn check(items: &[MISSION_ITEM_INT_DATA]) -> MavMissionResult {
    // MAV_FRAME_GLOBAL_INT is deprecated for MAV_FRAME_GLOBAL (which MISSION_ITEM_INT carries
    // scaled by 10⁷); PX4 takes both, and the relative-altitude ones.
    #[allow(deprecated)]
    let global = |frame: MavFrame| {
        matches!(
            frame,
            MavFrame::MAV_FRAME_GLOBAL
                | MavFrame::MAV_FRAME_GLOBAL_INT
                | MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT
                | MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        )
    };
    if !items.iter().all(|item| global(item.frame)) {
        return MavMissionResult::MAV_MISSION_UNSUPPORTED_FRAME;
    }
    let mut i = 0;
    while let Some(item) = items.get(i) {
        match command_id(item.command) {
            RETURN_POINT => i += 1,
            CIRCLE_INCLUSION | CIRCLE_EXCLUSION => {
                if !(item.param1.is_finite() && item.param1 > 0.0) {
                    return MavMissionResult::MAV_MISSION_INVALID_PARAM1;
                }
                i += 1;
            }
            kind @ (POLYGON_INCLUSION | POLYGON_EXCLUSION) => {
                let n = item.param1;
                if !(n.is_finite() && n >= 3.0 && n.fract() == 0.0) {
                    return MavMissionResult::MAV_MISSION_INVALID_PARAM1;
                }
                let n = n as usize;
                let polygon = items.get(i..i + n);
                let whole = polygon.is_some_and(|p| {
                    p.iter()
                        .all(|v| command_id(v.command) == kind && v.param1 == item.param1)
                });
                if !whole {
                    return MavMissionResult::MAV_MISSION_INVALID_PARAM1;
                }
                i += n;
            }
            _ => return MavMissionResult::MAV_MISSION_UNSUPPORTED,
        }
    }
    MavMissionResult::MAV_MISSION_ACCEPTED
}

fn command_id(command: MavCmd) -> u32 {
    command as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    const WRITER: (u8, u8) = (1, 191);

    fn vertex(seq: u16, n: f32, lat: i32, lon: i32) -> MISSION_ITEM_INT_DATA {
        MISSION_ITEM_INT_DATA {
            param1: n,
            x: lat,
            y: lon,
            seq,
            command: MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            frame: MavFrame::MAV_FRAME_GLOBAL,
            autocontinue: 1,
            mission_type: MavMissionType::MAV_MISSION_TYPE_FENCE,
            ..Default::default()
        }
    }

    fn square() -> Vec<MISSION_ITEM_INT_DATA> {
        [(0, 0), (0, 10), (10, 10), (10, 0)]
            .into_iter()
            .enumerate()
            .map(|(i, (lat, lon))| vertex(i as u16, 4.0, lat, lon))
            .collect()
    }

    fn accepted() -> Vec<Reply> {
        vec![Geofence::ack(MavMissionResult::MAV_MISSION_ACCEPTED)]
    }

    #[test]
    fn upload_then_read_back() {
        let mut f = Geofence::default();
        let items = square();
        assert_eq!(f.on_count(4, WRITER), vec![Reply::FenceRequest(0)]);
        for item in &items[..3] {
            assert_eq!(
                f.on_item(item, WRITER),
                vec![Reply::FenceRequest(item.seq + 1)]
            );
        }
        assert!(f.on_item(&items[2], WRITER).is_empty(), "a repeat");
        assert_eq!(f.on_item(&items[3], WRITER), accepted());
        assert_eq!(f.items(), &items[..]);
        assert_eq!(f.partner(), WRITER);
        assert_eq!(
            f.on_request_list(WRITER),
            vec![Reply::MissionCount(MavMissionType::MAV_MISSION_TYPE_FENCE)]
        );
        assert_eq!(f.count(), 4);
        assert_eq!(f.on_request(3, WRITER), vec![Reply::FenceItem(3)]);
        assert_eq!(
            f.on_request(4, WRITER),
            vec![Geofence::ack(
                MavMissionResult::MAV_MISSION_INVALID_SEQUENCE
            )]
        );
        // A stray item changes nothing; a count of 0 clears.
        assert!(f.on_item(&items[0], WRITER).is_empty());
        assert_eq!(f.on_count(0, WRITER), accepted());
        assert!(f.items().is_empty());
    }

    #[test]
    fn a_new_count_restarts_and_order_matters() {
        let mut f = Geofence::default();
        let items = square();
        f.on_count(4, WRITER);
        f.on_item(&items[0], WRITER);
        assert_eq!(f.on_count(4, WRITER), vec![Reply::FenceRequest(0)]);
        assert_eq!(
            f.on_item(&items[2], WRITER),
            vec![Geofence::ack(
                MavMissionResult::MAV_MISSION_INVALID_SEQUENCE
            )]
        );
        assert!(f.items().is_empty());
        assert_eq!(
            f.on_count(MAX_ITEMS + 1, WRITER),
            vec![Geofence::ack(MavMissionResult::MAV_MISSION_NO_SPACE)]
        );
    }

    #[test]
    fn what_px4_refuses() {
        let upload = |items: &[MISSION_ITEM_INT_DATA]| {
            let mut f = Geofence::default();
            f.on_count(items.len() as u16, WRITER);
            let mut last = Vec::new();
            for item in items {
                last = f.on_item(item, WRITER);
            }
            (last, f.items().len())
        };
        let refused = |r| (vec![Geofence::ack(r)], 0);
        assert_eq!(upload(&square()), (accepted(), 4));
        // A polygon of four announced, three sent.
        let mut short = square();
        short.truncate(3);
        assert_eq!(
            upload(&short),
            refused(MavMissionResult::MAV_MISSION_INVALID_PARAM1)
        );
        // Two vertices are no polygon.
        let two: Vec<_> = (0..2).map(|i| vertex(i, 2.0, 0, 0)).collect();
        assert_eq!(
            upload(&two),
            refused(MavMissionResult::MAV_MISSION_INVALID_PARAM1)
        );
        let mut local = square();
        local[1].frame = MavFrame::MAV_FRAME_LOCAL_NED;
        assert_eq!(
            upload(&local),
            refused(MavMissionResult::MAV_MISSION_UNSUPPORTED_FRAME)
        );
        let mut waypoint = square();
        waypoint[0].command = MavCmd::MAV_CMD_NAV_WAYPOINT;
        assert_eq!(
            upload(&waypoint),
            refused(MavMissionResult::MAV_MISSION_UNSUPPORTED)
        );
        // A circle and a return point are fence items too.
        let mut circle = vertex(0, 25.0, 0, 0);
        circle.command = MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION;
        let mut home = vertex(1, 0.0, 0, 0);
        home.command = MavCmd::MAV_CMD_NAV_FENCE_RETURN_POINT;
        assert_eq!(upload(&[circle, home]), (accepted(), 2));
    }
}

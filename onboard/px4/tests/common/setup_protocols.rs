//! The fake autopilot's side of PX4's parameter and mission (geofence) protocols, as the
//! writer meets them when it sets the autopilot up.

use super::ApState;
use mavlink::MavHeader;
use mavlink::dialects::common::{
    MISSION_ACK_DATA, MISSION_COUNT_DATA, MISSION_ITEM_INT_DATA, MISSION_REQUEST_INT_DATA, MavCmd,
    MavFrame, MavMessage, MavMissionResult, MavMissionType, MavParamType, PARAM_VALUE_DATA,
};

/// A PX4 parameter's value in its own type.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Param {
    Int(i32),
    Real(f32),
}

impl Param {
    /// PARAM_VALUE's float field and type: an INT32 travels byte for byte, as PX4 sends it.
    fn to_wire(self) -> (f32, MavParamType) {
        match self {
            Param::Int(v) => (
                f32::from_le_bytes(v.to_le_bytes()),
                MavParamType::MAV_PARAM_TYPE_INT32,
            ),
            Param::Real(v) => (v, MavParamType::MAV_PARAM_TYPE_REAL32),
        }
    }

    /// PARAM_SET's float field read in this parameter's type. PX4 copies the four bytes into
    /// the parameter whatever param_type says, so a float sent for an integer arrives garbled.
    fn with_wire(self, value: f32) -> Param {
        match self {
            Param::Int(_) => Param::Int(i32::from_le_bytes(value.to_le_bytes())),
            Param::Real(_) => Param::Real(value),
        }
    }
}

/// PX4's defaults of the parameters the writer reads and sets (measured on PX4 SITL).
pub fn px4_default_params() -> Vec<(String, Param)> {
    [
        ("COM_OBL_RC_ACT", Param::Int(0)),
        ("COM_OF_LOSS_T", Param::Real(1.0)),
        ("NAV_DLL_ACT", Param::Int(0)),
        ("COM_RCL_EXCEPT", Param::Int(0)),
        ("NAV_RCL_ACT", Param::Int(2)),
        ("COM_RC_IN_MODE", Param::Int(1)),
        ("GF_ACTION", Param::Int(2)),
        ("GF_MAX_VER_DIST", Param::Real(0.0)),
    ]
    .into_iter()
    .map(|(n, v)| (n.to_owned(), v))
    .collect()
}

fn param_value(params: &[(String, Param)], index: usize) -> Option<MavMessage> {
    let (name, value) = params.get(index)?;
    let (param_value, param_type) = value.to_wire();
    let mut id = [0u8; 16];
    for (slot, byte) in id.iter_mut().zip(name.bytes()) {
        *slot = byte;
    }
    Some(MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
        param_value,
        param_count: params.len() as u16,
        param_index: index as u16,
        param_id: mavlink::types::CharArray::new(id),
        param_type,
    }))
}

fn name_of(id: &[u8]) -> String {
    let end = id.iter().position(|b| *b == 0).unwrap_or(id.len());
    String::from_utf8_lossy(&id[..end]).into_owned()
}

const FENCE: MavMissionType = MavMissionType::MAV_MISSION_TYPE_FENCE;

/// Whether a completed fence upload is one PX4 takes: fence commands only, global frames, and
/// polygons of at least three vertices whose param1 says how many.
fn check_fence(items: &[MISSION_ITEM_INT_DATA]) -> MavMissionResult {
    for item in items {
        let command = item.command as u32;
        if !(5000..=5004).contains(&command) {
            return MavMissionResult::MAV_MISSION_UNSUPPORTED;
        }
        // MAV_FRAME_GLOBAL_INT is deprecated for MAV_FRAME_GLOBAL (which MISSION_ITEM_INT
        // carries scaled by 10⁷); PX4 takes both.
        #[allow(deprecated)]
        let global = matches!(
            item.frame,
            MavFrame::MAV_FRAME_GLOBAL | MavFrame::MAV_FRAME_GLOBAL_INT
        );
        if !global {
            return MavMissionResult::MAV_MISSION_UNSUPPORTED_FRAME;
        }
        if (command == 5001 || command == 5002) && (item.param1.is_nan() || item.param1 < 3.0) {
            return MavMissionResult::MAV_MISSION_INVALID_PARAM1;
        }
    }
    MavMissionResult::MAV_MISSION_ACCEPTED
}

/// PX4's parameter and mission (geofence) protocols: the replies to one message.
pub(super) fn setup_protocols(
    s: &mut ApState,
    header: &MavHeader,
    msg: &MavMessage,
    replies: &mut Vec<MavMessage>,
) {
    let (to_system, to_component) = (header.system_id as u8, header.component_id);
    let ack = |result| {
        MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system: to_system,
            target_component: to_component,
            mavtype: result,
            mission_type: FENCE,
            opaque_id: 0,
        })
    };
    let request = |seq| {
        MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq,
            target_system: to_system,
            target_component: to_component,
            mission_type: FENCE,
        })
    };
    match msg {
        MavMessage::PARAM_REQUEST_READ(r) if s.param_protocol => {
            let index = if r.param_index < 0 {
                let name = name_of(&r.param_id[..]);
                s.params.iter().position(|(n, _)| *n == name)
            } else {
                Some(r.param_index as usize)
            };
            replies.extend(index.and_then(|i| param_value(&s.params, i)));
        }
        MavMessage::PARAM_REQUEST_LIST(_) if s.param_protocol => {
            replies.extend((0..s.params.len()).filter_map(|i| param_value(&s.params, i)));
        }
        MavMessage::PARAM_SET(p) if s.param_protocol => {
            let name = name_of(&p.param_id[..]);
            if let Some(i) = s.params.iter().position(|(n, _)| *n == name) {
                s.params[i].1 = s.params[i].1.with_wire(p.param_value);
                replies.extend(param_value(&s.params, i));
            }
        }
        MavMessage::MISSION_COUNT(c) if c.mission_type == FENCE => {
            if c.count == 0 {
                s.fence.clear();
                s.fence_upload = None;
                s.fence_results.push(MavMissionResult::MAV_MISSION_ACCEPTED);
                replies.push(ack(MavMissionResult::MAV_MISSION_ACCEPTED));
            } else {
                // A repeated count restarts the upload.
                s.fence_upload = Some((c.count, Vec::new()));
                replies.push(request(0));
            }
        }
        MavMessage::MISSION_ITEM_INT(item) if item.mission_type == FENCE => {
            let Some((count, items)) = s.fence_upload.as_mut() else {
                return;
            };
            let expected = items.len() as u16;
            if item.seq + 1 == expected {
                return; // a repeat of the last one: its request is already out
            }
            if item.seq != expected {
                s.fence_upload = None;
                s.fence_results
                    .push(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE);
                replies.push(ack(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE));
                return;
            }
            items.push(item.clone());
            if items.len() < usize::from(*count) {
                replies.push(request(expected + 1));
                return;
            }
            let items = std::mem::take(items);
            s.fence_upload = None;
            let result = check_fence(&items);
            if result == MavMissionResult::MAV_MISSION_ACCEPTED {
                s.fence = items;
            }
            s.fence_results.push(result);
            replies.push(ack(result));
        }
        MavMessage::MISSION_REQUEST_LIST(r) if r.mission_type == FENCE => {
            replies.push(MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: s.fence.len() as u16,
                target_system: to_system,
                target_component: to_component,
                mission_type: FENCE,
                opaque_id: 0,
            }));
        }
        MavMessage::MISSION_REQUEST_INT(r) if r.mission_type == FENCE => {
            match s.fence.get(usize::from(r.seq)) {
                Some(item) => replies.push(MavMessage::MISSION_ITEM_INT(MISSION_ITEM_INT_DATA {
                    target_system: to_system,
                    target_component: to_component,
                    ..item.clone()
                })),
                None => replies.push(ack(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE)),
            }
        }
        _ => {}
    }
}

/// Whether a fence item is a vertex of an inclusion polygon (what the writer uploads).
pub fn is_inclusion_vertex(item: &MISSION_ITEM_INT_DATA) -> bool {
    item.command == MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
}

//! What another ground station (QGroundControl, an RC pilot's mode switch) does to a vehicle
//! behind TACOS's back: a MAVLink DO_SET_MODE sent to its autopilot from a socket of its own.

use std::net::{SocketAddr, UdpSocket};
use tacos_shared::px4_mode::{self, Px4Mode};

/// A ground station's system id (QGroundControl's).
const GCS_SYSID: u8 = 255;

/// Sends one COMMAND_LONG DO_SET_MODE to `mode` to the autopilot at `autopilot` (system
/// `sysid`, component 1), as MAVLink v2 bytes. The ack goes to the autopilot's first partner,
/// not here: the caller watches the mode the vehicle reports instead.
pub fn switch_mode(autopilot: SocketAddr, sysid: u8, mode: Px4Mode) -> anyhow::Result<()> {
    use mavlink::dialects::common::{COMMAND_LONG_DATA, MavCmd, MavMessage};
    let custom = mode.custom_mode();
    let main = ((custom >> 16) & 0xff) as u8;
    let sub = ((custom >> 24) & 0xff) as u8;
    let message = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: f32::from(px4_mode::BASE_MODE_CUSTOM_ENABLED),
        param2: f32::from(main),
        param3: f32::from(sub),
        param4: 0.0,
        param5: 0.0,
        param6: 0.0,
        param7: 0.0,
        command: MavCmd::MAV_CMD_DO_SET_MODE,
        target_system: sysid,
        target_component: 1,
        confirmation: 0,
    });
    let header = mavlink::MavHeader {
        system_id: u32::from(GCS_SYSID),
        component_id: 190,
        sequence: 0,
    };
    let mut bytes = Vec::new();
    mavlink::write_v2_msg(&mut bytes, header, &message)
        .map_err(|e| anyhow::anyhow!("DO_SET_MODE not framed: {e}"))?;
    let socket = UdpSocket::bind("127.0.0.1:0")?;
    socket.send_to(&bytes, autopilot)?;
    Ok(())
}

//! What another ground station (QGroundControl, an RC pilot's mode switch) does to a vehicle
//! behind TACOS's back: a MAVLink DO_SET_MODE sent to its autopilot from a socket of its own,
//! framed by the writer's own MAVLink code.

use std::net::{SocketAddr, UdpSocket};
use tacos_px4::commands::CommandLong;
use tacos_px4::mav::{Encoder, command_long};
use tacos_shared::px4_mode::Px4Mode;

/// A ground station's system id (QGroundControl's).
const GCS_SYSID: u8 = 255;

/// Sends one COMMAND_LONG DO_SET_MODE to `mode` to the autopilot at `autopilot` (system
/// `sysid`, component 1), as MAVLink v2 bytes. The ack goes to the autopilot's first partner,
/// not here: the caller watches the mode the vehicle reports instead.
pub fn switch_mode(autopilot: SocketAddr, sysid: u8, mode: Px4Mode) -> anyhow::Result<()> {
    let (main, sub) = mode.main_sub();
    let message = command_long(&CommandLong::set_mode(main, sub), sysid, 1)
        .ok_or_else(|| anyhow::anyhow!("DO_SET_MODE has no MAVLink command"))?;
    let bytes = Encoder::new(GCS_SYSID).encode(&message);
    anyhow::ensure!(!bytes.is_empty(), "DO_SET_MODE not framed");
    let socket = UdpSocket::bind("127.0.0.1:0")?;
    socket.send_to(&bytes, autopilot)?;
    Ok(())
}

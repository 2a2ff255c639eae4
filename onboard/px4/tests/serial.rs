//! The real `tacos-px4` binary on a serial line: a pseudo-terminal pair stands in for a flight
//! controller's TELEM2 port (the writer sets it raw at 921600 baud, as it would a real UART);
//! the test plays the autopilot on the other end, byte stream and all.

mod common;

use common::*;
use mavlink::dialects::common::{
    HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA, MavAutopilot, MavMessage, MavModeFlag, MavState,
    MavType,
};
use mavlink::{MavHeader, MavlinkReader};
use std::fs::File;
use std::io::{Read, Write};
use std::os::fd::FromRawFd;
use std::sync::mpsc;
use std::time::{Duration, Instant};
use tacos_ipc::IpcNode;

/// A pty pair: (the autopilot's end, the device path the writer opens).
fn pty() -> (File, String, File) {
    let (mut master, mut slave) = (0, 0);
    // SAFETY: openpty writes two new descriptors into the given ints; the name and termios
    // arguments may be null.
    let rc = unsafe {
        libc::openpty(
            &mut master,
            &mut slave,
            std::ptr::null_mut(),
            std::ptr::null(),
            std::ptr::null(),
        )
    };
    assert_eq!(rc, 0, "openpty failed: {}", std::io::Error::last_os_error());
    // SAFETY: ttyname returns a pointer to a static buffer holding a NUL-terminated path.
    let name = unsafe { std::ffi::CStr::from_ptr(libc::ttyname(slave)) }
        .to_string_lossy()
        .into_owned();
    // SAFETY: both descriptors were just opened by openpty and are owned here only.
    unsafe { (File::from_raw_fd(master), name, File::from_raw_fd(slave)) }
}

fn frame(msg: &MavMessage, seq: u8) -> Vec<u8> {
    let header = MavHeader {
        system_id: 1,
        component_id: 1,
        sequence: seq,
    };
    let mut out = Vec::new();
    mavlink::write_v2_msg(&mut out, header, msg).expect("encoding a frame");
    out
}

#[test]
fn the_writer_flies_over_a_serial_line() {
    let (mut master, device, _slave) = pty();
    let swarm = unique_swarm("serial");
    let node = IpcNode::new(&swarm, &drone()).expect("iceoryx2 node");
    let ports = node.onboard_ports().expect("onboard ports");
    let link = format!("serial:{device}:921600");
    let writer =
        WriterProcess::start_with_link(&swarm, "0,0,0", &link, 0, &["--no-autopilot-setup"]);

    // What the writer sends, read on the autopilot's end of the line.
    let (tx, rx) = mpsc::channel::<Vec<u8>>();
    let mut reader = master.try_clone().expect("cloning the pty master");
    std::thread::spawn(move || {
        let mut buf = [0u8; 4096];
        while let Ok(n) = reader.read(&mut buf) {
            if n == 0 || tx.send(buf[..n].to_vec()).is_err() {
                break;
            }
        }
    });

    let heartbeat = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: tacos_shared::px4_mode::Px4Mode::Hold.custom_mode(),
        mavtype: MavType::MAV_TYPE_QUADROTOR,
        autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
        base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
        system_status: MavState::MAV_STATE_STANDBY,
        mavlink_version: 3,
    });
    let position = MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
        time_boot_ms: 0,
        x: 1.0,
        y: 2.0,
        z: -3.0,
        vx: 0.0,
        vy: 0.0,
        vz: 0.0,
    });
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut heard = Vec::new();
    let mut state = None;
    let mut seq = 0u8;
    while Instant::now() < deadline && (state.is_none() || heard.is_empty()) {
        // The autopilot's frames, split across writes as a UART delivers them.
        let mut bytes = frame(&heartbeat, seq);
        bytes.extend(frame(&position, seq.wrapping_add(1)));
        seq = seq.wrapping_add(2);
        let (a, b) = bytes.split_at(bytes.len() / 3);
        master.write_all(a).expect("writing to the line");
        std::thread::sleep(Duration::from_millis(5));
        master.write_all(b).expect("writing to the line");
        std::thread::sleep(Duration::from_millis(100));
        while let Ok(chunk) = rx.try_recv() {
            heard.extend(chunk);
        }
        if let Ok(samples) = ports.state.drain() {
            state = state.or(samples
                .into_iter()
                .find(|s| s.link_ok == 1 && s.position[2] > 2.5));
        }
    }
    let state =
        state.unwrap_or_else(|| panic!("no state with the link up; log:\n{}", writer.log_text()));
    assert_eq!(
        state.position,
        [2.0, 1.0, 3.0],
        "NED (1, 2, -3) from home (0, 0, 0) is ENU (2, 1, 3)"
    );
    // The writer's own heartbeat and its stream requests came back over the line.
    let mut reader = MavlinkReader::new(&heard[..]);
    let mut ours = 0;
    while let Ok((header, msg)) = reader.read_any_message::<MavMessage>() {
        if matches!(msg, MavMessage::HEARTBEAT(_))
            && (header.system_id, header.component_id) == (1, 191)
        {
            ours += 1;
        }
    }
    assert!(
        ours >= 1,
        "no writer heartbeat on the line; log:\n{}",
        writer.log_text()
    );
}

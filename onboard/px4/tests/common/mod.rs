//! Test kit for the writer's integration tests: unique ids, free ports, the real binary as a
//! child process, a minimal autopilot over a real UDP socket, and deadline-bounded waits.
#![allow(dead_code)] // each test file uses a different part of the kit

mod setup_protocols;

use setup_protocols::setup_protocols;
#[allow(unused_imports)] // as above
pub use setup_protocols::{Param, is_inclusion_vertex, px4_default_params};

use mavlink::dialects::common::{
    COMMAND_ACK_DATA, GLOBAL_POSITION_INT_DATA, HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA,
    MISSION_ITEM_INT_DATA, MavAutopilot, MavMessage, MavMissionResult, MavModeFlag, MavResult,
    MavState, MavType,
};

/// The fake's home altitude above mean sea level, as PX4 SIH's (489.4 m).
pub const HOME_AMSL_M: f32 = 489.4;
/// The fake's latitude and longitude (degrees × 10⁷) at its NED origin: SIH's default.
pub const ORIGIN_LAT_E7: i32 = 473_977_420;
pub const ORIGIN_LON_E7: i32 = 85_455_940;
const METRES_PER_DEG_LAT: f64 = 111_319.49;
use mavlink::{MavHeader, MavlinkReader};
use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use tacos_shared::px4_mode::Px4Mode;
use tacos_shared::{DroneId, SwarmId};

pub fn unique_swarm(tag: &str) -> SwarmId {
    static COUNTER: AtomicU32 = AtomicU32::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    let raw = format!("{tag}{}x{n}x{nanos}", std::process::id());
    SwarmId::new(raw.chars().take(32).collect::<String>()).expect("a valid swarm id")
}

pub fn drone() -> DroneId {
    DroneId::new("alfa").expect("a valid drone id")
}

/// A UDP port that was free a moment ago.
pub fn free_udp_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .map(|a| a.port())
        .expect("a free port")
}

/// Polls `probe` until it returns `Some` or `timeout` passes.
pub fn poll_until<T>(timeout: Duration, mut probe: impl FnMut() -> Option<T>) -> Option<T> {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(v) = probe() {
            return Some(v);
        }
        if Instant::now() >= deadline {
            return None;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// The real `tacos-px4` binary; killed when dropped. Its log goes to a file named in failures.
pub struct WriterProcess {
    pub child: Child,
    pub port: u16,
    pub log: PathBuf,
}

impl WriterProcess {
    /// A writer on `udpin:127.0.0.1:<port>`.
    pub fn start(swarm: &SwarmId, home: &str, port: u16, extra: &[&str]) -> WriterProcess {
        Self::start_with_link(swarm, home, &format!("udpin:127.0.0.1:{port}"), port, extra)
    }

    /// A writer on any `--mavlink` link; `port` is only what [`addr`](Self::addr) reports.
    pub fn start_with_link(
        swarm: &SwarmId,
        home: &str,
        link: &str,
        port: u16,
        extra: &[&str],
    ) -> WriterProcess {
        let log = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("tacos-px4-{swarm}.log"));
        let log_file = std::fs::File::create(&log).expect("creating the writer's log file");
        let child = Command::new(env!("CARGO_BIN_EXE_tacos-px4"))
            .args(["--swarm", swarm.as_str(), "--drone", "alfa", "--home", home])
            .args(["--mavlink", link])
            .args(extra)
            .env("RUST_LOG", "debug")
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .expect("starting tacos-px4");
        WriterProcess { child, port, log }
    }

    pub fn addr(&self) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], self.port))
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for WriterProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// How the fake autopilot answers COMMAND_LONG.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AckPolicy {
    Accept,
    Ignore,
    Answer(MavResult),
}

pub struct Received {
    pub at: Instant,
    pub header: MavHeader,
    pub msg: MavMessage,
}

pub struct ApState {
    pub received: Vec<Received>,
    pub heartbeats: bool,
    pub ack: AckPolicy,
    /// Sent as LOCAL_POSITION_NED at 10 Hz when set.
    pub position_ned: Option<[f32; 3]>,
    pub custom_mode: u32,
    pub armed: bool,
    pub decode_errors: usize,
    /// The parameter table, in index order; unknown names get no answer, as on PX4.
    pub params: Vec<(String, Param)>,
    /// False: an autopilot without the parameter protocol (PARAM_* go unanswered).
    pub param_protocol: bool,
    /// The geofence items accepted by the last complete upload.
    pub fence: Vec<MISSION_ITEM_INT_DATA>,
    /// A fence upload in progress: its count and the items so far.
    pub fence_upload: Option<(u16, Vec<MISSION_ITEM_INT_DATA>)>,
    /// The MISSION_ACK results this autopilot sent for fence uploads.
    pub fence_results: Vec<MavMissionResult>,
}

impl ApState {
    pub fn param(&self, name: &str) -> Option<Param> {
        self.params.iter().find(|(n, _)| n == name).map(|(_, v)| *v)
    }

    /// A SET_POSITION_TARGET_LOCAL_NED arrived within PX4's offboard timeout.
    pub fn setpoints_streaming(&self, now: Instant) -> bool {
        self.received
            .iter()
            .rev()
            .find(|r| matches!(r.msg, MavMessage::SET_POSITION_TARGET_LOCAL_NED(_)))
            .is_some_and(|r| now.saturating_duration_since(r.at) < Duration::from_millis(500))
    }

    /// The stored fence's vertices (lat, lon in degrees × 10⁷).
    pub fn fence_vertices(&self) -> Vec<(i32, i32)> {
        self.fence.iter().map(|i| (i.x, i.y)).collect()
    }
}

struct Inner {
    socket: UdpSocket,
    /// Our MAVLink system id (component 1).
    sysid: u8,
    /// Where the writer is: given (udpin writer) or learnt from its first packet (udpout writer).
    writer: Mutex<Option<SocketAddr>>,
    stop: AtomicBool,
    state: Mutex<ApState>,
    changed: Condvar,
}

/// A minimal PX4 (system 1 unless told otherwise, component 1) on a real UDP socket, run by a
/// background thread: heartbeats at 4 Hz (while enabled), positions at 10 Hz (when set, with
/// GLOBAL_POSITION_INT at PX4 SIH's origin and AMSL altitude), acks per policy (a mode switch
/// answered twice and applied, as PX4 does), PX4's parameter protocol over a table of PX4's
/// defaults (read by name or index, set with an echo; INT32 byte for byte), PX4's mission
/// protocol for the geofence (upload and read-back), and a log of everything the writer sent.
pub struct FakeAutopilot {
    inner: Arc<Inner>,
    thread: Option<JoinHandle<()>>,
}

impl FakeAutopilot {
    /// An autopilot that talks first, to a writer bound at `writer` (udpin).
    pub fn start(writer: SocketAddr) -> FakeAutopilot {
        Self::start_as(writer, 1)
    }

    /// [`FakeAutopilot::start`] as MAVLink system `sysid`.
    pub fn start_as(writer: SocketAddr, sysid: u8) -> FakeAutopilot {
        Self::start_configured(writer, sysid, |_| {})
    }

    /// [`FakeAutopilot::start_as`] with its state changed by `configure` before it says
    /// anything.
    pub fn start_configured(
        writer: SocketAddr,
        sysid: u8,
        configure: impl FnOnce(&mut ApState),
    ) -> FakeAutopilot {
        Self::start_inner(
            UdpSocket::bind("127.0.0.1:0").expect("binding the fake autopilot"),
            Some(writer),
            sysid,
            configure,
        )
    }

    /// An autopilot bound at `socket` that answers whoever writes to it (for a udpout writer).
    pub fn listen(socket: UdpSocket) -> FakeAutopilot {
        Self::start_inner(socket, None, 1, |_| {})
    }

    fn start_inner(
        socket: UdpSocket,
        writer: Option<SocketAddr>,
        sysid: u8,
        configure: impl FnOnce(&mut ApState),
    ) -> FakeAutopilot {
        let mut state = ApState {
            received: Vec::new(),
            heartbeats: true,
            ack: AckPolicy::Accept,
            position_ned: None,
            custom_mode: tacos_shared::px4_mode::Px4Mode::Hold.custom_mode(),
            armed: false,
            decode_errors: 0,
            params: px4_default_params(),
            param_protocol: true,
            fence: Vec::new(),
            fence_upload: None,
            fence_results: Vec::new(),
        };
        configure(&mut state);
        socket
            .set_read_timeout(Some(Duration::from_millis(10)))
            .expect("read timeout");
        let inner = Arc::new(Inner {
            socket,
            sysid,
            writer: Mutex::new(writer),
            stop: AtomicBool::new(false),
            state: Mutex::new(state),
            changed: Condvar::new(),
        });
        let thread = std::thread::spawn({
            let inner = Arc::clone(&inner);
            move || run_autopilot(&inner)
        });
        FakeAutopilot {
            inner,
            thread: Some(thread),
        }
    }

    pub fn state(&self) -> MutexGuard<'_, ApState> {
        self.inner.state.lock().expect("autopilot state")
    }

    /// Sends raw bytes to the writer (to test its handling of garbage).
    pub fn send_raw(&self, bytes: &[u8]) {
        let writer = *self.inner.writer.lock().expect("writer address");
        if let Some(w) = writer {
            self.inner.socket.send_to(bytes, w).expect("send");
        }
    }

    /// Waits (bounded) until `pred` holds on the state; returns what `pred` returned.
    pub fn wait_for<T>(
        &self,
        timeout: Duration,
        mut pred: impl FnMut(&ApState) -> Option<T>,
    ) -> Option<T> {
        let deadline = Instant::now() + timeout;
        let mut guard = self.state();
        loop {
            if let Some(v) = pred(&guard) {
                return Some(v);
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return None;
            }
            guard = self
                .inner
                .changed
                .wait_timeout(guard, left)
                .expect("autopilot state")
                .0;
        }
    }
}

impl Drop for FakeAutopilot {
    fn drop(&mut self) {
        self.inner.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn run_autopilot(inner: &Inner) {
    let mut seq = 0u8;
    let mut send = |msg: &MavMessage| {
        let header = MavHeader {
            system_id: u32::from(inner.sysid),
            component_id: 1,
            sequence: seq,
        };
        seq = seq.wrapping_add(1);
        let mut buf = Vec::new();
        let writer = *inner.writer.lock().expect("writer address");
        if let Some(w) = writer
            && mavlink::write_v2_msg(&mut buf, header, msg).is_ok()
        {
            let _ = inner.socket.send_to(&buf, w);
        }
    };
    let mut next_heartbeat = Instant::now();
    let mut next_position = Instant::now();
    let mut buf = vec![0u8; 65_536];
    let boot = Instant::now();
    while !inner.stop.load(Ordering::Relaxed) {
        let now = Instant::now();
        let (heartbeat, position, global) = {
            let s = inner.state.lock().expect("autopilot state");
            let hb = (s.heartbeats && now >= next_heartbeat).then(|| {
                let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
                if s.armed {
                    base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
                }
                MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                    custom_mode: s.custom_mode,
                    mavtype: MavType::MAV_TYPE_QUADROTOR,
                    autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
                    base_mode: base,
                    system_status: if s.armed {
                        MavState::MAV_STATE_ACTIVE
                    } else if s.custom_mode == Px4Mode::Offboard.custom_mode()
                        && !s.setpoints_streaming(now)
                    {
                        // PX4 in OFFBOARD with no setpoint stream is not ready to arm.
                        MavState::MAV_STATE_UNINIT
                    } else {
                        MavState::MAV_STATE_STANDBY
                    },
                    mavlink_version: 3,
                })
            });
            let pos = s
                .position_ned
                .filter(|_| now >= next_position)
                .map(|[x, y, z]| {
                    MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                        time_boot_ms: boot.elapsed().as_millis() as u32,
                        x,
                        y,
                        z,
                        vx: 0.0,
                        vy: 0.0,
                        vz: 0.0,
                    })
                });
            let global = s
                .position_ned
                .filter(|_| now >= next_position)
                .map(|[x, y, z]| {
                    MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                        time_boot_ms: boot.elapsed().as_millis() as u32,
                        lat: ORIGIN_LAT_E7 + (f64::from(x) / METRES_PER_DEG_LAT * 1e7) as i32,
                        lon: ORIGIN_LON_E7
                            + (f64::from(y)
                                / (METRES_PER_DEG_LAT
                                    * (f64::from(ORIGIN_LAT_E7) / 1e7).to_radians().cos())
                                * 1e7) as i32,
                        alt: ((HOME_AMSL_M - z) * 1000.0) as i32,
                        relative_alt: (-z * 1000.0) as i32,
                        hdg: 9_000,
                        ..Default::default()
                    })
                });
            (hb, pos, global)
        };
        if let Some(hb) = heartbeat {
            send(&hb);
            next_heartbeat = now + Duration::from_millis(250);
        }
        if let Some(g) = global {
            send(&g);
        }
        if let Some(p) = position {
            send(&p);
            next_position = now + Duration::from_millis(100);
        }
        let Ok((n, from)) = inner.socket.recv_from(&mut buf) else {
            continue;
        };
        inner
            .writer
            .lock()
            .expect("writer address")
            .get_or_insert(from);
        let at = Instant::now();
        let mut reader = MavlinkReader::new(&buf[..n]);
        let mut replies = Vec::new();
        {
            let mut s = inner.state.lock().expect("autopilot state");
            let mut decoded = 0;
            loop {
                match reader.read_any_message::<MavMessage>() {
                    Ok((header, msg)) => {
                        decoded += 1;
                        if let MavMessage::COMMAND_LONG(cmd) = &msg {
                            let result = match s.ack {
                                AckPolicy::Accept => Some(MavResult::MAV_RESULT_ACCEPTED),
                                AckPolicy::Ignore => None,
                                AckPolicy::Answer(r) => Some(r),
                            };
                            if let Some(result) = result {
                                let accepted = result == MavResult::MAV_RESULT_ACCEPTED;
                                if accepted && cmd.command as u32 == 400 {
                                    s.armed = cmd.param1 == 1.0;
                                }
                                let ack = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                                    command: cmd.command,
                                    result,
                                    target_system: header.system_id as u8,
                                    target_component: header.component_id,
                                    ..Default::default()
                                });
                                if cmd.command as u32 == 176 {
                                    // PX4's receiver accepts first; commander answers after.
                                    if accepted {
                                        s.custom_mode = ((cmd.param2 as u32) << 16)
                                            | ((cmd.param3 as u32) << 24);
                                    }
                                    replies.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                                        command: cmd.command,
                                        result: MavResult::MAV_RESULT_ACCEPTED,
                                        target_system: header.system_id as u8,
                                        target_component: header.component_id,
                                        ..Default::default()
                                    }));
                                }
                                replies.push(ack);
                            }
                        }
                        setup_protocols(&mut s, &header, &msg, &mut replies);
                        s.received.push(Received { at, header, msg });
                    }
                    Err(mavlink::error::MessageReadError::Parse(_)) => s.decode_errors += 1,
                    Err(_) => break,
                }
            }
            if decoded == 0 {
                s.decode_errors += 1;
            }
        }
        inner.changed.notify_all();
        for r in replies {
            send(&r);
        }
    }
}

/// The SET_POSITION_TARGET_LOCAL_NED messages received, with their arrival times.
pub fn setpoints(
    s: &ApState,
) -> Vec<(
    Instant,
    mavlink::dialects::common::SET_POSITION_TARGET_LOCAL_NED_DATA,
)> {
    s.received
        .iter()
        .filter_map(|r| match &r.msg {
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(sp) => Some((r.at, sp.clone())),
            _ => None,
        })
        .collect()
}

/// The COMMAND_LONG messages received.
pub fn command_longs(s: &ApState) -> Vec<(Instant, mavlink::dialects::common::COMMAND_LONG_DATA)> {
    s.received
        .iter()
        .filter_map(|r| match &r.msg {
            MavMessage::COMMAND_LONG(c) => Some((r.at, c.clone())),
            _ => None,
        })
        .collect()
}

/// The COMMAND_LONGs received with MAV_CMD `command`.
pub fn commands_of(
    s: &ApState,
    command: u32,
) -> Vec<(Instant, mavlink::dialects::common::COMMAND_LONG_DATA)> {
    command_longs(s)
        .into_iter()
        .filter(|(_, c)| c.command as u32 == command)
        .collect()
}

/// When the first message matching `pred` arrived.
pub fn first_at(s: &ApState, pred: impl Fn(&MavMessage) -> bool) -> Option<Instant> {
    s.received.iter().find(|r| pred(&r.msg)).map(|r| r.at)
}

/// When the last message matching `pred` arrived.
pub fn last_at(s: &ApState, pred: impl Fn(&MavMessage) -> bool) -> Option<Instant> {
    s.received.iter().rev().find(|r| pred(&r.msg)).map(|r| r.at)
}

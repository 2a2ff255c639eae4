//! The simulator as a MAVLink client sees it: real MAVLink v2 bytes over UDP on loopback, PX4's
//! ports and rules; and its zenoh side (truth, fault injection, events). Unique ports and swarm
//! ids per test; every wait has a deadline.

#[path = "px4_over_udp/parameters.rs"]
mod parameters;
#[path = "px4_over_udp/zenoh_side.rs"]
mod zenoh_side;

use mavlink::MavHeader;
use mavlink::dialects::common::{
    COMMAND_LONG_DATA, MISSION_ACK_DATA, MISSION_COUNT_DATA, MISSION_ITEM_INT_DATA,
    MISSION_REQUEST_INT_DATA, MISSION_REQUEST_LIST_DATA, MavAutopilot, MavCmd, MavFrame,
    MavMessage, MavMissionResult, MavMissionType, MavModeFlag, MavParamType, MavResult, MavState,
    MavType, PARAM_REQUEST_READ_DATA, PARAM_SET_DATA, PositionTargetTypemask,
    SET_POSITION_TARGET_LOCAL_NED_DATA,
};
use std::net::{Ipv4Addr, SocketAddr};
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;
use tacos_bus::BusArgs;
use tacos_shared::keys::Keys;
use tacos_shared::messages::{FaultRequest, SimTruth, TargetsMessage, WorldEvent};
use tacos_shared::px4_mode::{self, Px4Mode};
use tacos_shared::scenario::{FaultKind, Scenario};
use tacos_shared::{DroneId, SwarmId};
use tacos_sitl::SitlConfig;
use tokio::net::UdpSocket;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tokio::time::{Instant, timeout, timeout_at};

const GCS_SYSTEM: u32 = 255;
const GCS_COMPONENT: u8 = 190;

fn unique_swarm(tag: &str) -> SwarmId {
    static COUNTER: AtomicU32 = AtomicU32::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    SwarmId::new(format!("sitl-{tag}-{}-{n}", std::process::id())).expect("valid swarm id")
}

/// A port nobody listens on right now (the OS picks it; released for the simulator to bind).
fn free_udp_port() -> u16 {
    let probe = std::net::UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).expect("bind a probe");
    probe.local_addr().expect("probe address").port()
}

fn free_tcp_port() -> u16 {
    let probe = std::net::TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).expect("bind a probe");
    probe.local_addr().expect("probe address").port()
}

/// `n` UDP sockets on consecutive loopback ports (the writers' side: mavlink_base + i).
async fn consecutive_sockets(n: u16) -> Vec<UdpSocket> {
    for _ in 0..50 {
        let first = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))
            .await
            .expect("bind");
        let base = first.local_addr().expect("address").port();
        let mut sockets = vec![first];
        for i in 1..n {
            match base.checked_add(i) {
                Some(port) => match UdpSocket::bind((Ipv4Addr::LOCALHOST, port)).await {
                    Ok(s) => sockets.push(s),
                    Err(_) => break,
                },
                None => break,
            }
        }
        if sockets.len() == usize::from(n) {
            return sockets;
        }
    }
    panic!("no {n} consecutive free UDP ports");
}

/// A running simulator in this process.
struct Sitl {
    stop: Option<oneshot::Sender<()>>,
    task: JoinHandle<Result<(), tacos_sitl::SitlError>>,
    sitl_base_port: u16,
}

impl Sitl {
    fn start(drones: usize, mavlink_base_port: u16, bus: BusArgs) -> Sitl {
        let scenario = Scenario::builtin("lab").expect("lab is valid");
        let mut sitl_base_port = free_udp_port();
        // Keep clear of the writer's range.
        while sitl_base_port.abs_diff(mavlink_base_port) < 8 || sitl_base_port > u16::MAX - 8 {
            sitl_base_port = free_udp_port();
        }
        let config = SitlConfig {
            scenario,
            drones,
            mavlink_base_port,
            sitl_base_port,
            speed: 1.0,
            px4: Default::default(),
            observe: None,
            bus,
        };
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(tacos_sitl::run(config, async {
            let _ = stopped.await;
        }));
        Sitl {
            stop: Some(stop),
            task,
            sitl_base_port,
        }
    }

    async fn stop(mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        let result = timeout(Duration::from_secs(10), self.task)
            .await
            .expect("the simulator stops in time");
        result
            .expect("the simulator task did not panic")
            .expect("the simulator ran cleanly");
    }
}

/// A MAVLink peer of one simulated vehicle (the role `tacos-px4` plays).
struct Client {
    socket: Arc<UdpSocket>,
    vehicle: SocketAddr,
    system_id: u8,
    sequence: u8,
}

fn encode(sequence: u8, message: &MavMessage) -> Vec<u8> {
    let mut out = Vec::new();
    let header = MavHeader {
        system_id: GCS_SYSTEM,
        component_id: GCS_COMPONENT,
        sequence,
    };
    mavlink::write_v2_msg(&mut out, header, message).expect("encode");
    out
}

impl Client {
    fn new(socket: UdpSocket, vehicle_port: u16, system_id: u8) -> Client {
        Client {
            socket: Arc::new(socket),
            vehicle: SocketAddr::from((Ipv4Addr::LOCALHOST, vehicle_port)),
            system_id,
            sequence: 0,
        }
    }

    async fn send(&mut self, message: &MavMessage) {
        self.sequence = self.sequence.wrapping_add(1);
        self.socket
            .send_to(&encode(self.sequence, message), self.vehicle)
            .await
            .expect("send");
    }

    /// Waits until `pick` accepts a message from the vehicle, or panics at the deadline.
    async fn wait_for<T>(
        &self,
        within: Duration,
        what: &str,
        mut pick: impl FnMut(&MavHeader, &MavMessage) -> Option<T>,
    ) -> T {
        let deadline = Instant::now() + within;
        let mut buf = vec![0u8; 4096];
        loop {
            let received = timeout_at(deadline, self.socket.recv_from(&mut buf)).await;
            let Ok(Ok((n, _from))) = received else {
                panic!("timed out after {within:?} waiting for {what}")
            };
            let mut reader = mavlink::MavlinkReader::new(&buf[..n]);
            while let Ok((header, message)) = reader.read_any_message::<MavMessage>() {
                if let Some(found) = pick(&header, &message) {
                    return found;
                }
            }
        }
    }

    /// Sends a COMMAND_LONG and returns the results of its first `acks` COMMAND_ACKs, checking
    /// they are addressed to this client.
    async fn command_acks(
        &mut self,
        command: MavCmd,
        params: [f32; 7],
        acks: usize,
    ) -> Vec<MavResult> {
        let message = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: params[0],
            param2: params[1],
            param3: params[2],
            param4: params[3],
            param5: params[4],
            param6: params[5],
            param7: params[6],
            command,
            target_system: self.system_id,
            target_component: 1,
            confirmation: 0,
        });
        self.send(&message).await;
        let mut results = Vec::new();
        while results.len() < acks {
            let result = self
                .wait_for(
                    Duration::from_secs(3),
                    &format!("COMMAND_ACK for {command:?}"),
                    |_, m| match m {
                        MavMessage::COMMAND_ACK(ack) if ack.command == command => {
                            assert_eq!(
                                (u32::from(ack.target_system), ack.target_component),
                                (GCS_SYSTEM, GCS_COMPONENT),
                                "PX4 addresses its acks"
                            );
                            Some(ack.result)
                        }
                        _ => None,
                    },
                )
                .await;
            results.push(result);
        }
        results
    }

    async fn command(&mut self, command: MavCmd, params: [f32; 7]) -> MavResult {
        let results = self.command_acks(command, params, 1).await;
        results[0]
    }

    /// DO_SET_MODE: PX4 acks it twice (the MAVLink receiver accepts, then commander answers);
    /// the second is the real result.
    async fn set_mode(&mut self, main: u8, sub: u8) -> MavResult {
        let base = f32::from(px4_mode::BASE_MODE_CUSTOM_ENABLED);
        let results = self
            .command_acks(
                MavCmd::MAV_CMD_DO_SET_MODE,
                [base, f32::from(main), f32::from(sub), 0.0, 0.0, 0.0, 0.0],
                2,
            )
            .await;
        assert_eq!(
            results[0],
            MavResult::MAV_RESULT_ACCEPTED,
            "the receiver's ack"
        );
        results[1]
    }

    /// PARAM_SET of an INT32 (byte for byte, as PX4 takes it), confirmed by PX4's echo.
    async fn set_int_param(&mut self, name: &str, value: i32) {
        self.send(&MavMessage::PARAM_SET(PARAM_SET_DATA {
            param_value: f32::from_le_bytes(value.to_le_bytes()),
            target_system: self.system_id,
            target_component: 1,
            param_id: tacos_sitl::params::param_id(name),
            param_type: MavParamType::MAV_PARAM_TYPE_INT32,
        }))
        .await;
        let echo = self
            .wait_for(
                Duration::from_secs(2),
                &format!("the echo of {name}"),
                |_, m| param_value(m).filter(|(n, _, _)| n == name),
            )
            .await;
        assert_eq!(
            (echo.1.to_bits() as i32, echo.2),
            (value, MavParamType::MAV_PARAM_TYPE_INT32)
        );
    }

    async fn wait_for_mode(&self, mode: Px4Mode, within: Duration) {
        self.wait_for(
            within,
            &format!("a heartbeat in {mode:?}"),
            |_, m| match m {
                MavMessage::HEARTBEAT(hb) if hb.custom_mode == mode.custom_mode() => Some(()),
                _ => None,
            },
        )
        .await
    }

    /// Streams a position setpoint (local NED) at 20 Hz from the same socket until aborted.
    fn stream_setpoints(&self, ned: [f32; 3]) -> JoinHandle<()> {
        let socket = self.socket.clone();
        let vehicle = self.vehicle;
        let message =
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
                time_boot_ms: 0,
                x: ned[0],
                y: ned[1],
                z: ned[2],
                vx: 0.0,
                vy: 0.0,
                vz: 0.0,
                afx: 0.0,
                afy: 0.0,
                afz: 0.0,
                yaw: 0.0,
                yaw_rate: 0.0,
                // Position only.
                type_mask: PositionTargetTypemask::from_bits_truncate(0b0000_1101_1111_1000),
                target_system: self.system_id,
                target_component: 1,
                coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
            });
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_millis(50));
            let mut sequence = 0u8;
            loop {
                tick.tick().await;
                sequence = sequence.wrapping_add(1);
                if socket
                    .send_to(&encode(sequence, &message), vehicle)
                    .await
                    .is_err()
                {
                    return;
                }
            }
        })
    }
}

const ARM: [f32; 7] = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];

fn statustext(m: &MavMessage) -> Option<String> {
    match m {
        MavMessage::STATUSTEXT(t) => t.text.to_str().ok().map(str::to_string),
        _ => None,
    }
}

fn param_value(m: &MavMessage) -> Option<(String, f32, MavParamType)> {
    match m {
        MavMessage::PARAM_VALUE(p) => Some((
            tacos_sitl::params::name_of(&p.param_id[..]),
            p.param_value,
            p.param_type,
        )),
        _ => None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn answers_like_px4_over_udp() {
    let socket = consecutive_sockets(1).await.remove(0);
    let mavlink_port = socket.local_addr().expect("address").port();
    let bus = BusArgs::loopback(unique_swarm("udp"), Some("tcp/127.0.0.1:0".into()), vec![]);
    // PX4's default readiness delay (2 s), so that the refusal before it is seen.
    let sitl = Sitl::start(1, mavlink_port, bus);
    let mut px4 = Client::new(socket, sitl.sitl_base_port, 1);

    // Unprompted heartbeats to mavlink_base + 0, as PX4 SITL instance 0 sends to 14540.
    let (header, hb) = px4
        .wait_for(
            Duration::from_secs(10),
            "the first heartbeat",
            |h, m| match m {
                MavMessage::HEARTBEAT(hb) => Some((*h, hb.clone())),
                _ => None,
            },
        )
        .await;
    assert_eq!((header.system_id, header.component_id), (1, 1));
    assert_eq!(hb.autopilot, MavAutopilot::MAV_AUTOPILOT_PX4);
    assert_eq!(hb.mavtype, MavType::MAV_TYPE_QUADROTOR);
    assert!(
        hb.base_mode
            .contains(MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    );
    assert!(
        !hb.base_mode
            .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED)
    );
    // PX4's encoding: main mode in bits 16..24, sub mode in 24..32; AUTO.LOITER = 4 | 3 << 8.
    assert_eq!(hb.custom_mode, (4 << 16) | (3 << 24));
    assert_eq!(
        hb.system_status,
        MavState::MAV_STATE_UNINIT,
        "not ready yet"
    );

    // Not ready: ARM is refused.
    assert_eq!(
        px4.command(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, ARM).await,
        MavResult::MAV_RESULT_TEMPORARILY_REJECTED
    );
    // Ready: STANDBY, and PX4 says so.
    px4.wait_for(Duration::from_secs(5), "\"Ready for takeoff!\"", |_, m| {
        (statustext(m).as_deref() == Some("Ready for takeoff!")).then_some(())
    })
    .await;
    px4.wait_for(
        Duration::from_secs(3),
        "a STANDBY heartbeat",
        |_, m| match m {
            MavMessage::HEARTBEAT(hb) if hb.system_status == MavState::MAV_STATE_STANDBY => {
                Some(())
            }
            _ => None,
        },
    )
    .await;

    // The altitude PX4 reports is AMSL: SIH's origin, 489.4 m.
    let ground_mm = px4
        .wait_for(
            Duration::from_secs(3),
            "GLOBAL_POSITION_INT",
            |_, m| match m {
                MavMessage::GLOBAL_POSITION_INT(g) => Some(g.alt),
                _ => None,
            },
        )
        .await;
    assert_eq!(ground_mm, 489_400);

    assert_eq!(
        px4.command(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, ARM).await,
        MavResult::MAV_RESULT_ACCEPTED
    );
    px4.wait_for(
        Duration::from_secs(3),
        "an armed heartbeat",
        |_, m| match m {
            MavMessage::HEARTBEAT(hb)
                if hb
                    .base_mode
                    .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED) =>
            {
                assert_eq!(hb.system_status, MavState::MAV_STATE_ACTIVE);
                Some(())
            }
            _ => None,
        },
    )
    .await;
    // Take-off to 1.5 m above the ground: param7 is AMSL.
    let takeoff_amsl = ground_mm as f32 / 1000.0 + 1.5;
    assert_eq!(
        px4.command(
            MavCmd::MAV_CMD_NAV_TAKEOFF,
            [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, takeoff_amsl]
        )
        .await,
        MavResult::MAV_RESULT_ACCEPTED
    );
    // The altitude rises in LOCAL_POSITION_NED (z is down).
    px4.wait_for(
        Duration::from_secs(8),
        "LOCAL_POSITION_NED above 0.5 m",
        |_, m| match m {
            MavMessage::LOCAL_POSITION_NED(p) if p.z < -0.5 => Some(()),
            _ => None,
        },
    )
    .await;

    // Hold on offboard loss, as the writer sets it (PX4's default, 0, would return).
    px4.set_int_param("COM_OBL_RC_ACT", 5).await;

    // OFFBOARD without a setpoint stream: refused (by commander, after the receiver's ACCEPTED).
    assert_eq!(
        px4.set_mode(px4_mode::MAIN_OFFBOARD, 0).await,
        MavResult::MAV_RESULT_TEMPORARILY_REJECTED
    );

    // With a stream: refused during the first second, accepted after it.
    let stream = px4.stream_setpoints([0.5, 0.0, -1.5]);
    let started = Instant::now();
    let mut pace = tokio::time::interval(Duration::from_millis(250));
    let accepted_after = loop {
        pace.tick().await;
        let result = px4.set_mode(px4_mode::MAIN_OFFBOARD, 0).await;
        let elapsed = started.elapsed();
        if result == MavResult::MAV_RESULT_ACCEPTED {
            break elapsed;
        }
        assert_eq!(result, MavResult::MAV_RESULT_TEMPORARILY_REJECTED);
        assert!(
            elapsed < Duration::from_secs(4),
            "offboard still refused after {elapsed:?} of streaming"
        );
    };
    assert!(
        accepted_after >= Duration::from_millis(900),
        "offboard accepted after only {accepted_after:?}"
    );
    px4.wait_for_mode(Px4Mode::Offboard, Duration::from_secs(2))
        .await;

    // The stream stops: COM_OF_LOSS_T (1 s) later the vehicle holds. Mode changes show in the
    // 1 Hz heartbeat only, so allow for up to a second more.
    stream.abort();
    let _ = stream.await;
    let stopped = Instant::now();
    px4.wait_for_mode(Px4Mode::Hold, Duration::from_millis(2500))
        .await;
    let took = stopped.elapsed();
    assert!(
        took >= Duration::from_millis(800),
        "left offboard after only {took:?}"
    );

    // Disarming in the air is refused.
    assert_eq!(
        px4.command(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, [0.0; 7])
            .await,
        MavResult::MAV_RESULT_TEMPORARILY_REJECTED
    );

    // Stream rates: LOCAL_POSITION_NED (30 Hz by default) down to 2 Hz; HEARTBEAT stays 1 Hz.
    assert_eq!(
        px4.command(
            MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
            [32.0, 500_000.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        )
        .await,
        MavResult::MAV_RESULT_ACCEPTED
    );
    let (mut positions, mut heartbeats) = (0, 0);
    let window = Instant::now() + Duration::from_millis(3000);
    let mut buf = vec![0u8; 4096];
    while let Ok(Ok((n, _))) = timeout_at(window, px4.socket.recv_from(&mut buf)).await {
        let mut reader = mavlink::MavlinkReader::new(&buf[..n]);
        while let Ok((_, m)) = reader.read_any_message::<MavMessage>() {
            match m {
                MavMessage::LOCAL_POSITION_NED(_) => positions += 1,
                MavMessage::HEARTBEAT(_) => heartbeats += 1,
                _ => {}
            }
        }
    }
    assert!((5..=8).contains(&positions), "{positions} positions in 3 s");
    assert!(
        (2..=4).contains(&heartbeats),
        "{heartbeats} heartbeats in 3 s"
    );

    // PX4 answers its first client only: a request from another port is answered there.
    let stranger = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))
        .await
        .expect("bind");
    let request = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: 242.0,
        param2: 0.0,
        param3: 0.0,
        param4: 0.0,
        param5: 0.0,
        param6: 0.0,
        param7: 0.0,
        command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
        target_system: 1,
        target_component: 1,
        confirmation: 0,
    });
    stranger
        .send_to(&encode(1, &request), px4.vehicle)
        .await
        .expect("send");
    let home = px4
        .wait_for(
            Duration::from_secs(3),
            "the requested HOME_POSITION",
            |_, m| match m {
                MavMessage::HOME_POSITION(h) => Some(h.clone()),
                _ => None,
            },
        )
        .await;
    // Home moved to where the vehicle armed: the spawn point, 489.4 m AMSL.
    assert_eq!(home.altitude, 489_400);
    let heard = timeout(Duration::from_millis(500), stranger.recv_from(&mut buf)).await;
    assert!(heard.is_err(), "the second client was answered");
    sitl.stop().await;
}

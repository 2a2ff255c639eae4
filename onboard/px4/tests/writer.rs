//! The real `tacos-px4` binary against a minimal autopilot on a real UDP socket, with the
//! planner side played through iceoryx2. Every wait has a deadline.

mod common;
#[path = "writer/links.rs"]
mod links;
#[path = "writer/setup.rs"]
mod setup;

use common::*;
use mavlink::dialects::common::{
    MavFrame, MavMessage, MavMissionResult, MavMissionType, MavParamType, MavResult,
};
use std::process::Command;
use std::time::{Duration, Instant};
use tacos_ipc::{IpcNode, OnboardPorts};
use tacos_shared::ipc::{
    CommandKind, CommandOutcome, CommandResultSample, CommandSample, SetpointSample,
    VehicleStateSample,
};

const START_TIMEOUT: Duration = Duration::from_secs(10);

struct Rig {
    // Field order = drop order: the writer goes first.
    writer: WriterProcess,
    autopilot: FakeAutopilot,
    ports: OnboardPorts,
    _node: IpcNode,
}

impl Rig {
    /// Writer with home (100, -50, 2), a fake autopilot, and the planner's ports; returns once the
    /// writer publishes state with the link up.
    fn start(tag: &str) -> Rig {
        Self::start_with(tag, &[], |_| {})
    }

    /// [`Rig::start`] with more writer arguments and the autopilot set up by `configure`.
    fn start_with(tag: &str, extra: &[&str], configure: impl FnOnce(&mut ApState)) -> Rig {
        let swarm = unique_swarm(tag);
        let node = IpcNode::new(&swarm, &drone()).expect("iceoryx2 node");
        let ports = node.onboard_ports().expect("onboard ports");
        let writer = WriterProcess::start(&swarm, "100,-50,2", free_udp_port(), extra);
        let autopilot = FakeAutopilot::start_configured(writer.addr(), 1, configure);
        let rig = Rig {
            writer,
            autopilot,
            ports,
            _node: node,
        };
        let up = rig.wait_state(START_TIMEOUT, |s| s.link_ok == 1);
        assert!(
            up.is_some(),
            "writer never reported link_ok = 1; log:\n{}",
            rig.writer.log_text()
        );
        rig
    }

    fn wait_state(
        &self,
        timeout: Duration,
        pred: impl Fn(&VehicleStateSample) -> bool,
    ) -> Option<VehicleStateSample> {
        poll_until(timeout, || {
            self.ports.state.drain().ok()?.into_iter().find(|s| pred(s))
        })
    }

    fn wait_result(&self, timeout: Duration, seq: u64) -> Option<CommandResultSample> {
        poll_until(timeout, || {
            self.ports
                .results
                .drain()
                .ok()?
                .into_iter()
                .find(|r| r.seq == seq)
        })
    }

    fn fail(&self, what: &str) -> String {
        format!("{what}; writer log:\n{}", self.writer.log_text())
    }
}

/// 12 m east, 7 m north and 10 m up of the home (100, -50, 2); moving east-north-up.
fn setpoint(seq: u64) -> SetpointSample {
    SetpointSample {
        seq,
        stamp_ns: 0,
        position: [112.0, -43.0, 12.0],
        velocity: [1.0, 2.0, 0.5],
        acceleration: [0.0, 0.0, 0.0],
        yaw: f64::NAN,
    }
}

fn close(a: f32, b: f32) -> bool {
    (a - b).abs() < 1e-4
}

#[test]
fn setpoints_stream_in_ned_at_rate_and_hold_when_the_planner_stops() {
    let rig = Rig::start("sp");
    // The writer's heartbeat reaches the autopilot, but without a reference nothing is streamed.
    let hb = rig.autopilot.wait_for(Duration::from_secs(3), |s| {
        s.received.iter().find_map(|r| match &r.msg {
            mavlink::dialects::common::MavMessage::HEARTBEAT(h) => Some((r.header, h.clone())),
            _ => None,
        })
    });
    let (header, hb) = hb.unwrap_or_else(|| panic!("{}", rig.fail("no heartbeat from the writer")));
    // By default our system id is the autopilot's (PX4 tracks its onboard computer's heartbeat
    // only from its own system), with component 191.
    assert_eq!((header.system_id, header.component_id), (1, 191));
    assert_eq!(
        hb.mavtype,
        mavlink::dialects::common::MavType::MAV_TYPE_ONBOARD_CONTROLLER
    );
    assert!(
        setpoints(&rig.autopilot.state()).is_empty(),
        "streamed before any reference existed"
    );

    // The planner sends at 10 Hz for 1.5 s (pacing the sender, not synchronising).
    let t_start = Instant::now();
    let mut seq = 0;
    while t_start.elapsed() < Duration::from_millis(1500) {
        seq += 1;
        rig.ports
            .send_setpoint(setpoint(seq))
            .expect("send setpoint");
        std::thread::sleep(Duration::from_millis(100));
    }
    let t_stop = Instant::now();

    let live: Vec<_> = setpoints(&rig.autopilot.state())
        .into_iter()
        .filter(|(at, _)| *at >= t_start + Duration::from_millis(200) && *at < t_stop)
        .collect();
    let window = (t_stop - t_start - Duration::from_millis(200)).as_secs_f64();
    let rate = live.len() as f64 / window;
    eprintln!("measured live stream rate: {rate:.1} Hz over {window:.2} s");
    assert!(
        rate >= 20.0,
        "{}",
        rig.fail(&format!("stream rate {rate:.1} Hz"))
    );
    for (_, sp) in &live {
        // NED relative to home: +7 north, +12 east, 10 m up = -10 down.
        assert!(
            close(sp.x, 7.0) && close(sp.y, 12.0) && close(sp.z, -10.0),
            "wrong NED position {sp:?}"
        );
        assert!(
            close(sp.vx, 2.0) && close(sp.vy, 1.0) && close(sp.vz, -0.5),
            "wrong NED velocity {sp:?}"
        );
        assert_eq!(sp.coordinate_frame, MavFrame::MAV_FRAME_LOCAL_NED);
        assert_eq!((sp.target_system, sp.target_component), (1, 1));
        assert_eq!(
            sp.type_mask.bits(),
            1024 | 2048,
            "PVA used, yaw (NaN) and yaw rate ignored"
        );
    }

    // The planner goes silent: the stream continues with a hold at the last position.
    let hold_seen = rig.autopilot.wait_for(Duration::from_secs(2), |s| {
        setpoints(s)
            .into_iter()
            .find(|(at, sp)| *at > t_stop && sp.vx == 0.0 && sp.vy == 0.0 && sp.vz == 0.0)
            .map(|(at, _)| at)
    });
    let hold_at =
        hold_seen.unwrap_or_else(|| panic!("{}", rig.fail("no hold after the planner stopped")));
    let held_for = hold_at - t_stop;
    assert!(
        held_for >= Duration::from_millis(400),
        "hold came too early: {held_for:?}"
    );
    // Keep watching for another second of hold.
    let until = hold_at + Duration::from_secs(1);
    rig.autopilot.wait_for(Duration::from_secs(3), |s| {
        setpoints(s)
            .last()
            .filter(|(at, _)| *at >= until)
            .map(|_| ())
    });
    let holds: Vec<_> = setpoints(&rig.autopilot.state())
        .into_iter()
        .filter(|(at, _)| *at >= hold_at && *at < until)
        .collect();
    let hold_rate = holds.len() as f64;
    eprintln!("measured hold stream rate: {hold_rate:.1} Hz");
    assert!(
        hold_rate >= 20.0,
        "{}",
        rig.fail(&format!("hold stream rate {hold_rate} Hz"))
    );
    for (_, sp) in &holds {
        assert!(
            close(sp.x, 7.0) && close(sp.y, 12.0) && close(sp.z, -10.0),
            "hold moved: {sp:?}"
        );
        assert_eq!(
            (sp.vx, sp.vy, sp.vz, sp.afx, sp.afy, sp.afz),
            (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        );
    }
    // No gap anywhere in the stream from the first setpoint on (PX4 drops offboard after 1 s).
    let all = setpoints(&rig.autopilot.state());
    let worst = all
        .windows(2)
        .map(|w| w[1].0 - w[0].0)
        .max()
        .unwrap_or_default();
    assert!(
        worst < Duration::from_millis(200),
        "stream paused for {worst:?}"
    );

    // A non-finite setpoint is rejected: the hold stays.
    let mut bad = setpoint(1000);
    bad.position[0] = f64::NAN;
    rig.ports.send_setpoint(bad).expect("send");
    let t_bad = Instant::now();
    rig.autopilot.wait_for(Duration::from_secs(2), |s| {
        setpoints(s)
            .iter()
            .filter(|(at, _)| *at > t_bad)
            .nth(10)
            .map(|_| ())
    });
    for (_, sp) in setpoints(&rig.autopilot.state())
        .iter()
        .filter(|(at, _)| *at > t_bad)
    {
        assert!(
            sp.x.is_finite() && close(sp.x, 7.0),
            "a NaN setpoint got through: {sp:?}"
        );
    }
}

#[test]
fn commands_are_acked_retried_and_timed_out() {
    let rig = Rig::start_with("cmd", &[], |ap| {
        // On the ground at its origin: a take-off needs the vehicle's AMSL altitude.
        ap.position_ned = Some([0.0, 0.0, 0.0]);
    });

    // Accepted (once the failsafe parameters are set: the arm waits for them).
    rig.ports
        .send_command(CommandSample::new(1, CommandKind::Arm, 0.0))
        .expect("send command");
    let r = rig
        .wait_result(Duration::from_secs(3), 1)
        .unwrap_or_else(|| panic!("{}", rig.fail("no result for arm")));
    assert_eq!(
        (r.kind, r.outcome(), r.mav_result),
        (CommandKind::Arm as u32, Some(CommandOutcome::Accepted), 0)
    );
    // Already in Hold and ready (STANDBY): no mode switch first, one ARM.
    assert!(commands_of(&rig.autopilot.state(), 176).is_empty());
    let arms = commands_of(&rig.autopilot.state(), 400);
    assert_eq!(arms.len(), 1);
    let arm = &arms[0].1;
    assert_eq!(
        (
            arm.command as u32,
            arm.param1,
            arm.confirmation,
            arm.target_system,
            arm.target_component
        ),
        (400, 1.0, 0, 1, 1)
    );
    // The armed heartbeat comes back as state.
    assert!(
        rig.wait_state(Duration::from_secs(2), |s| s.armed == 1)
            .is_some(),
        "{}",
        rig.fail("armed never reported")
    );

    // Refused.
    rig.autopilot.state().ack = AckPolicy::Answer(MavResult::MAV_RESULT_DENIED);
    rig.ports
        .send_command(CommandSample::new(2, CommandKind::Offboard, 0.0))
        .expect("send command");
    let r = rig
        .wait_result(Duration::from_secs(3), 2)
        .unwrap_or_else(|| panic!("{}", rig.fail("no result for offboard")));
    assert_eq!(
        (r.outcome(), r.mav_result),
        (Some(CommandOutcome::Rejected), 2)
    );

    // Unanswered: three tries, one second apart, confirmation 0, 1, 2, then TimedOut.
    rig.autopilot.state().ack = AckPolicy::Ignore;
    let before = commands_of(&rig.autopilot.state(), 22).len();
    assert_eq!(before, 0);
    let t0 = Instant::now();
    rig.ports
        .send_command(CommandSample::new(3, CommandKind::Takeoff, 10.0))
        .expect("send command");
    let r = rig
        .wait_result(Duration::from_secs(5), 3)
        .unwrap_or_else(|| panic!("{}", rig.fail("no result for takeoff")));
    let took = t0.elapsed();
    assert_eq!(
        (r.kind, r.outcome()),
        (CommandKind::Takeoff as u32, Some(CommandOutcome::TimedOut))
    );
    assert!(
        took >= Duration::from_millis(2900) && took < Duration::from_millis(4000),
        "timed out after {took:?}"
    );
    // Nothing but the take-off was sent meanwhile (the altitude was known: no request).
    let since: Vec<_> = command_longs(&rig.autopilot.state())
        .into_iter()
        .filter(|(at, _)| *at >= t0)
        .collect();
    let tries = commands_of(&rig.autopilot.state(), 22);
    assert_eq!(since.len(), tries.len(), "{}", rig.fail("other commands"));
    assert_eq!(
        tries
            .iter()
            .map(|(_, c)| c.confirmation)
            .collect::<Vec<_>>(),
        vec![0, 1, 2]
    );
    // PX4's take-off altitude is AMSL: the vehicle's 489.4 m plus the 10 m asked for.
    for (_, c) in &tries {
        assert!(
            (c.param7 - (HOME_AMSL_M + 10.0)).abs() < 0.01,
            "take-off param7 {}",
            c.param7
        );
    }
    for w in tries.windows(2) {
        let gap = w[1].0 - w[0].0;
        assert!(
            gap >= Duration::from_millis(900) && gap < Duration::from_millis(1300),
            "retry gap {gap:?}"
        );
    }

    // Queued commands run in order once the autopilot answers again.
    rig.autopilot.state().ack = AckPolicy::Accept;
    rig.ports
        .send_command(CommandSample::new(4, CommandKind::Hold, 0.0))
        .expect("send command");
    rig.ports
        .send_command(CommandSample::new(5, CommandKind::Land, 0.0))
        .expect("send command");
    let r4 = rig
        .wait_result(Duration::from_secs(3), 4)
        .map(|r| r.outcome());
    let r5 = rig
        .wait_result(Duration::from_secs(3), 5)
        .map(|r| r.outcome());
    assert_eq!(
        (r4, r5),
        (
            Some(Some(CommandOutcome::Accepted)),
            Some(Some(CommandOutcome::Accepted))
        ),
        "{}",
        rig.fail("hold/land")
    );
    let hold = command_longs(&rig.autopilot.state())
        .into_iter()
        .find(|(_, c)| c.command as u32 == 176 && c.param2 == 4.0);
    assert_eq!(
        hold.map(|(_, c)| (c.param1, c.param2, c.param3)),
        Some((1.0, 4.0, 3.0))
    );
}

#[test]
fn link_loss_position_and_garbage() {
    let rig = Rig::start("link");

    // LOCAL_POSITION_NED 10 m north, 5 m east, 8 m up of home (100, -50, 2) → ENU (105, -40, 10).
    rig.autopilot.state().position_ned = Some([10.0, 5.0, -8.0]);
    let s = rig.wait_state(Duration::from_secs(3), |s| {
        s.position == [105.0, -40.0, 10.0]
    });
    let s = s.unwrap_or_else(|| panic!("{}", rig.fail("position never reported in ENU")));
    assert_eq!((s.landed, s.link_ok), (0, 1));
    // No setpoint ever came, so the writer now streams a hold where the vehicle is (in NED).
    let hold = rig.autopilot.wait_for(Duration::from_secs(2), |s| {
        setpoints(s)
            .into_iter()
            .find(|(_, sp)| (sp.x, sp.y, sp.z) == (10.0, 5.0, -8.0))
            .map(|(_, sp)| sp)
    });
    let hold = hold.unwrap_or_else(|| panic!("{}", rig.fail("no hold at the vehicle's position")));
    assert_eq!((hold.vx, hold.vy, hold.vz), (0.0, 0.0, 0.0));

    // Garbage is counted, not fatal.
    rig.autopilot.send_raw(b"definitely not mavlink");
    rig.autopilot
        .send_raw(&[0xFD, 9, 0, 0, 0, 1, 1, 0, 0, 0, 1, 2, 3]);

    // Heartbeats stop: link_ok 0 within ~3.5 s (and not long before 3 s).
    {
        let mut s = rig.autopilot.state();
        s.heartbeats = false;
        s.position_ned = None;
    }
    let t0 = Instant::now();
    let lost = rig.wait_state(Duration::from_millis(4500), |s| s.link_ok == 0);
    let took = t0.elapsed();
    let lost = lost.unwrap_or_else(|| panic!("{}", rig.fail("link loss never reported")));
    assert!(
        took <= Duration::from_millis(3600),
        "link loss reported after {took:?}"
    );
    assert!(
        took >= Duration::from_millis(2500),
        "link loss reported too early: {took:?}"
    );
    assert!(lost.heartbeat_age_ms >= 2900, "{lost:?}");

    // With no link a command ends at once as LinkLost.
    let t1 = Instant::now();
    rig.ports
        .send_command(CommandSample::new(9, CommandKind::Land, 0.0))
        .expect("send");
    let r = rig
        .wait_result(Duration::from_secs(2), 9)
        .unwrap_or_else(|| panic!("{}", rig.fail("no LinkLost result")));
    assert_eq!(r.outcome(), Some(CommandOutcome::LinkLost));
    assert!(t1.elapsed() < Duration::from_millis(500));

    // State keeps coming at ≥ 5 Hz while nothing arrives.
    let t2 = Instant::now();
    let mut count = 0;
    poll_until(Duration::from_secs(3), || {
        count += rig.ports.state.drain().ok()?.len();
        (t2.elapsed() >= Duration::from_secs(1)).then_some(())
    });
    assert!(
        count >= 4,
        "only {count} state samples in 1 s without position"
    );

    // Heartbeats return: link up again.
    rig.autopilot.state().heartbeats = true;
    assert!(
        rig.wait_state(Duration::from_secs(2), |s| s.link_ok == 1)
            .is_some(),
        "{}",
        rig.fail("link never came back")
    );
    assert!(
        rig.writer.log_text().contains("malformed MAVLink datagram"),
        "{}",
        rig.fail("garbage not logged")
    );
}

#[test]
fn bad_arguments_and_a_port_in_use_fail_clearly() {
    let bin = env!("CARGO_BIN_EXE_tacos-px4");
    let run = |args: &[&str]| {
        Command::new(bin)
            .args(args)
            .env("RUST_LOG", "error")
            .output()
            .expect("running tacos-px4")
    };

    let out = run(&["--swarm", "s", "--drone", "alfa", "--home", "1,2"]);
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("--home"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let out = run(&[
        "--swarm",
        "s",
        "--drone",
        "alfa",
        "--home",
        "0,0,0",
        "--mavlink",
        "tcp:1.2.3.4:5",
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--mavlink"));

    let out = run(&[
        "--swarm",
        "s",
        "--drone",
        "alfa",
        "--home",
        "0,0,0",
        "--stream-rate-hz",
        "5",
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("stream-rate-hz"));

    let taken = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
    let port = taken.local_addr().expect("addr").port();
    let swarm = unique_swarm("busy");
    let out = run(&[
        "--swarm",
        swarm.as_str(),
        "--drone",
        "alfa",
        "--home",
        "0,0,0",
        "--mavlink",
        &format!("udpin:127.0.0.1:{port}"),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot bind UDP"), "{err}");
}

#[test]
fn sigterm_stops_the_writer_cleanly() {
    let swarm = unique_swarm("sig");
    let mut writer = WriterProcess::start(&swarm, "0,0,0", free_udp_port(), &[]);
    // Up = it answers on its port with a heartbeat once an autopilot talks to it.
    let autopilot = FakeAutopilot::start(writer.addr());
    let up = autopilot.wait_for(START_TIMEOUT, |s| (!s.received.is_empty()).then_some(()));
    assert!(
        up.is_some(),
        "writer never talked; log:\n{}",
        writer.log_text()
    );
    let pid = writer.child.id().to_string();
    let killed = Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .expect("kill");
    assert!(killed.success());
    let exited = poll_until(Duration::from_secs(3), || {
        writer.child.try_wait().ok().flatten()
    });
    let status = exited.unwrap_or_else(|| {
        panic!(
            "writer did not stop on SIGTERM; log:\n{}",
            writer.log_text()
        )
    });
    assert!(
        status.success(),
        "exit status {status:?}; log:\n{}",
        writer.log_text()
    );
    assert!(writer.log_text().contains("stopped"));
}

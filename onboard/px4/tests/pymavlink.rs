//! MAVLink checked by code that is not ours: `tests/python/fake_px4.py` (pymavlink) plays the
//! autopilot for the real `tacos-px4` binary, decodes every byte it sends with pymavlink's strict
//! parser, and checks the setpoint stream; the planner side is played here through iceoryx2.
//!
//! Needs the venv: run `tests/python/setup.sh` once (it creates `<repo>/.venv`).

mod common;

use common::*;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use tacos_ipc::IpcNode;
use tacos_shared::ipc::{CommandKind, CommandOutcome, CommandSample, SetpointSample};

fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

#[test]
fn pymavlink_autopilot_accepts_everything_the_writer_sends() {
    let root = repo_root();
    let python = root.join(".venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run tests/python/setup.sh (it creates the venv with pymavlink) and re-run this test",
        python.display()
    );
    let script = root.join("tests/python/fake_px4.py");

    let swarm = unique_swarm("pym");
    let node = IpcNode::new(&swarm, &drone()).expect("iceoryx2 node");
    let ports = node.onboard_ports().expect("onboard ports");
    // With the scenario's box as the geofence, as the launcher runs it: the pymavlink autopilot
    // checks the parameter and mission protocols too.
    let writer = WriterProcess::start(
        &swarm,
        "100,-50,2",
        free_udp_port(),
        &["--geofence=-100,-100,0,300,100,62"],
    );
    let mut fake = Command::new(&python)
        .arg(&script)
        .args(["--writer", &format!("127.0.0.1:{}", writer.port)])
        .args([
            "--home",
            "100,-50,2",
            "--setpoint-enu",
            "112,-43,12",
            "--velocity-enu",
            "1,2,0.5",
        ])
        .args([
            "--duration",
            "3",
            "--timeout",
            "20",
            "--min-rate",
            "20",
            "--expect-command",
            "400",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("starting fake_px4.py");
    // Kill the script on any early exit of this test.
    struct KillOnDrop(Option<std::process::Child>);
    impl Drop for KillOnDrop {
        fn drop(&mut self) {
            if let Some(c) = self.0.as_mut() {
                let _ = c.kill();
                let _ = c.wait();
            }
        }
    }
    let stdout = fake.stdout.take();
    let stderr = fake.stderr.take();
    let mut fake = KillOnDrop(Some(fake));

    // The link is up once the pymavlink autopilot's heartbeats reach the writer.
    let up = poll_until(Duration::from_secs(15), || {
        ports
            .state
            .drain()
            .ok()?
            .into_iter()
            .find(|s| s.link_ok == 1)
    });
    assert!(
        up.is_some(),
        "writer never saw the pymavlink autopilot; writer log:\n{}",
        writer.log_text()
    );

    // Play the planner: setpoints at 10 Hz and one arm command, until the script is done.
    let setpoint = |seq| SetpointSample {
        seq,
        stamp_ns: 0,
        position: [112.0, -43.0, 12.0],
        velocity: [1.0, 2.0, 0.5],
        acceleration: [0.0; 3],
        yaw: f64::NAN,
    };
    let deadline = Instant::now() + Duration::from_secs(25);
    let mut seq = 0;
    let mut arm_result = None;
    let mut exit = None;
    while Instant::now() < deadline {
        seq += 1;
        ports.send_setpoint(setpoint(seq)).expect("send setpoint");
        if seq == 3 {
            ports
                .send_command(CommandSample::new(77, CommandKind::Arm, 0.0))
                .expect("send command");
        }
        if let Ok(results) = ports.results.drain() {
            arm_result = arm_result.or(results.into_iter().find(|r| r.seq == 77));
        }
        if let Some(child) = fake.0.as_mut()
            && let Ok(Some(status)) = child.try_wait()
        {
            exit = Some(status);
            break;
        }
        std::thread::sleep(Duration::from_millis(100)); // the planner's pace, not a synchronisation
    }
    let status = exit.unwrap_or_else(|| {
        panic!(
            "fake_px4.py did not finish; writer log:\n{}",
            writer.log_text()
        )
    });
    let read = |pipe: Option<Box<dyn std::io::Read>>| {
        let mut s = String::new();
        if let Some(mut p) = pipe {
            let _ = p.read_to_string(&mut s);
        }
        s
    };
    let out = read(stdout.map(|p| Box::new(p) as Box<dyn std::io::Read>));
    let err = read(stderr.map(|p| Box::new(p) as Box<dyn std::io::Read>));
    eprintln!("fake_px4.py summary: {out}");
    let summary: serde_json::Value = serde_json::from_str(out.trim()).unwrap_or_else(|e| {
        panic!("fake_px4.py printed no JSON summary ({e}); stdout:\n{out}\nstderr:\n{err}")
    });

    assert_eq!(
        summary["ok"],
        serde_json::Value::Bool(true),
        "pymavlink found problems: {}\nstderr:\n{err}",
        summary["problems"]
    );
    assert!(
        status.success(),
        "fake_px4.py exit {status:?}; stderr:\n{err}"
    );
    let rate = summary["setpoint_rate_hz"].as_f64().unwrap_or(0.0);
    assert!(rate >= 20.0, "setpoint rate {rate} Hz");
    assert_eq!(
        summary["setpoint_frames"],
        serde_json::json!(["MAV_FRAME_LOCAL_NED"])
    );
    assert_eq!(summary["pymavlink_receive_errors"], serde_json::json!(0));
    // Our system id is the autopilot's by default.
    assert_eq!(summary["writer_ids"], serde_json::json!([[1, 191]]));
    // The failsafe parameters and the fence's limit (the box's 60 m above home, plus the default
    // 1 m margin) and action, as PX4 holds them (integers as integers: they travelled byte for
    // byte).
    assert_eq!(
        summary["params"],
        serde_json::json!({
            "COM_OBL_RC_ACT": 5, "COM_OF_LOSS_T": 1.0, "NAV_DLL_ACT": 0, "COM_RCL_EXCEPT": 4,
            "NAV_RCL_ACT": 2, "COM_RC_IN_MODE": 1, "GF_ACTION": 2, "GF_MAX_VER_DIST": 61.0,
        })
    );
    assert_eq!(
        summary["param_sets"],
        serde_json::json!(["COM_OBL_RC_ACT", "COM_RCL_EXCEPT", "GF_MAX_VER_DIST"])
    );
    assert_eq!(summary["unknown_params"], serde_json::json!([]));
    assert_eq!(
        summary["fence_results"],
        serde_json::json!([0]),
        "fence accepted once"
    );
    assert_eq!(summary["fence"].as_array().map(Vec::len), Some(4));
    assert_eq!(summary["fence_read_back"], serde_json::Value::Bool(true));
    assert!(
        summary["messages"]["SET_POSITION_TARGET_LOCAL_NED"]
            .as_u64()
            .unwrap_or(0)
            >= 60
    );
    assert!(summary["messages"]["HEARTBEAT"].as_u64().unwrap_or(0) >= 2);
    let ned = &summary["last_setpoint"]["ned"];
    assert_eq!(
        ned,
        &serde_json::json!([7.0, 12.0, -10.0]),
        "NED with the home offset"
    );
    assert_eq!(summary["armed"], serde_json::Value::Bool(true));
    let arm = poll_until(Duration::from_secs(2), || {
        arm_result.or_else(|| {
            ports
                .results
                .drain()
                .ok()?
                .into_iter()
                .find(|r| r.seq == 77)
        })
    });
    assert_eq!(
        arm.and_then(|r| r.outcome()),
        Some(CommandOutcome::Accepted),
        "arm result over iceoryx2"
    );
}

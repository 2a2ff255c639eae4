//! `tacos-ground demo` as a user runs it: Ctrl-C, a dying child, or the ground itself being
//! killed must leave no TACOS process behind.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn ground_binary() -> std::path::PathBuf {
    tacos_ground::launch::bin_dir().join("tacos-ground")
}

/// Pids of processes whose command line mentions `needle` (the demo's swarm id).
fn processes_mentioning(needle: &str) -> Vec<i32> {
    let mut pids = Vec::new();
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return pids;
    };
    for entry in entries.flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        if let Ok(cmdline) = std::fs::read(entry.path().join("cmdline")) {
            let text = String::from_utf8_lossy(&cmdline).replace('\0', " ");
            if text.contains(needle) {
                pids.push(pid);
            }
        }
    }
    pids
}

fn wait_until(limit: Duration, mut ok: impl FnMut() -> bool) -> bool {
    let deadline = Instant::now() + limit;
    while Instant::now() < deadline {
        if ok() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    ok()
}

/// `tacos-ground demo ARGS` with its stdout and stderr piped to the test.
fn spawn_demo(
    args: &[&str],
) -> anyhow::Result<(Child, std::process::ChildStdout, std::process::ChildStderr)> {
    let mut child = Command::new(ground_binary())
        .arg("demo")
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()?;
    let stdout = child
        .stdout
        .take()
        .ok_or_else(|| anyhow::anyhow!("no stdout"))?;
    let stderr = child
        .stderr
        .take()
        .ok_or_else(|| anyhow::anyhow!("no stderr"))?;
    Ok((child, stdout, stderr))
}

/// Starts the demo and returns it once its drones are up and it has started flying.
fn start_demo() -> anyhow::Result<(Child, String, std::sync::mpsc::Receiver<String>)> {
    let (mut child, stdout, stderr) = spawn_demo(&["--drones", "2", "--no-llm"])?;
    let swarm = format!("demo{}", child.id());
    let (tx, rx) = std::sync::mpsc::channel();
    let tx2 = tx.clone();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx2.send(line);
        }
    });
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(line) if line.contains("take off: sending") => break,
            Ok(_) => {}
            Err(_) => {
                let _ = child.kill();
                anyhow::bail!("the demo never started flying");
            }
        }
    }
    // Every child is up: sitl, and a writer and an onboard per drone.
    anyhow::ensure!(
        wait_until(Duration::from_secs(5), || processes_mentioning(&swarm)
            .len()
            >= 4),
        "expected the demo's children to be running"
    );
    Ok((child, swarm, rx))
}

fn wait_exit(child: &mut Child, limit: Duration) -> anyhow::Result<std::process::ExitStatus> {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait()? {
            return Ok(status);
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            anyhow::bail!("the demo did not exit within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn signal(pid: i32, sig: i32) {
    // SAFETY: kill(2) on a pid this test found or started.
    unsafe { libc::kill(pid, sig) };
}

#[test]
fn ctrl_c_shuts_every_child_down() -> anyhow::Result<()> {
    let (mut demo, swarm, _out) = start_demo()?;
    signal(demo.id() as i32, libc::SIGINT);
    let status = wait_exit(&mut demo, Duration::from_secs(15))?;
    assert!(
        !status.success(),
        "an interrupted demo must not report success"
    );
    assert!(
        wait_until(Duration::from_secs(5), || processes_mentioning(&swarm)
            .is_empty()),
        "orphans left: {:?}",
        processes_mentioning(&swarm)
    );
    Ok(())
}

#[test]
fn a_dying_child_stops_the_demo_with_an_error() -> anyhow::Result<()> {
    let (mut demo, swarm, out) = start_demo()?;
    let ground_pid = demo.id() as i32;
    let victim = processes_mentioning(&swarm)
        .into_iter()
        .find(|pid| {
            *pid != ground_pid
                && std::fs::read(format!("/proc/{pid}/cmdline"))
                    .is_ok_and(|c| String::from_utf8_lossy(&c).contains("tacos-onboard"))
        })
        .ok_or_else(|| anyhow::anyhow!("no tacos-onboard child found"))?;
    signal(victim, libc::SIGKILL);
    let status = wait_exit(&mut demo, Duration::from_secs(15))?;
    assert!(!status.success(), "a demo whose child died must fail");
    let said: Vec<String> = out.try_iter().collect();
    assert!(
        said.iter().any(|l| l.contains("exited unexpectedly")),
        "no reason given: {said:?}"
    );
    assert!(
        wait_until(Duration::from_secs(5), || processes_mentioning(&swarm)
            .is_empty()),
        "orphans left: {:?}",
        processes_mentioning(&swarm)
    );
    Ok(())
}

#[test]
fn killing_the_ground_station_takes_its_children_with_it() -> anyhow::Result<()> {
    let (mut demo, swarm, _out) = start_demo()?;
    signal(demo.id() as i32, libc::SIGKILL);
    wait_exit(&mut demo, Duration::from_secs(5))?;
    assert!(
        wait_until(Duration::from_secs(5), || processes_mentioning(&swarm)
            .is_empty()),
        "orphans left: {:?}",
        processes_mentioning(&swarm)
    );
    Ok(())
}

/// The paper's lab map: three drones 1 m apart with a 0.6 m safety distance fly the fixed
/// pattern and land. (Planner margins sized for the city once pushed them apart for as long as
/// they flew, and the pattern's first goto timed out.)
#[test]
fn the_lab_swarm_flies_the_fixed_pattern() -> anyhow::Result<()> {
    let (mut child, stdout, stderr) = spawn_demo(&["--map", "lab", "--no-llm"])?;
    // Both pipes are drained as the demo runs, so neither can fill up and stall it.
    let collect = |pipe: Box<dyn std::io::Read + Send>| {
        std::thread::spawn(move || {
            BufReader::new(pipe)
                .lines()
                .map_while(Result::ok)
                .collect::<Vec<String>>()
        })
    };
    let reader = collect(Box::new(stdout));
    let errors = collect(Box::new(stderr));
    let mut status = None;
    wait_until(Duration::from_secs(120), || {
        status = child.try_wait().ok().flatten();
        status.is_some()
    });
    let Some(status) = status else {
        let _ = child.kill();
        anyhow::bail!("the lab demo did not finish within 120 s");
    };
    let lines = reader
        .join()
        .map_err(|_| anyhow::anyhow!("stdout reader panicked"))?;
    let errors = errors
        .join()
        .map_err(|_| anyhow::anyhow!("stderr reader panicked"))?;
    assert!(status.success(), "exit {status}: {lines:#?} {errors:#?}");
    let done = lines
        .iter()
        .find(|l| l.contains("done: min pair distance"))
        .ok_or_else(|| anyhow::anyhow!("no summary: {lines:#?}"))?;
    assert!(
        done.contains("separation breaches 0, obstacle breaches 0"),
        "{done}"
    );
    Ok(())
}

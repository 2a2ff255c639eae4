//! The one thread every child process is forked from.
//!
//! `PR_SET_PDEATHSIG` fires when the *thread* that forked the child ends, not the process.
//! tokio's threads come and go: a worker that enters `block_in_place` (zenoh does, closing a
//! session) finishes as a blocking-pool thread and exits after 10 s idle. Children forked on it
//! then got SIGTERM with their parent alive: in `eval --jobs 2`, the end of one run stopped every
//! process of the run beside it. Forked here, on a thread that lives as long as the process,
//! children still die with the ground station and only with it.

use std::sync::mpsc;
use std::sync::{Mutex, OnceLock};
use tokio::process::{Child, Command};

type Reply = mpsc::Sender<std::io::Result<Child>>;

struct Job {
    command: Command,
    runtime: tokio::runtime::Handle,
    reply: Reply,
}

fn launcher() -> std::io::Result<&'static Mutex<mpsc::Sender<Job>>> {
    static LAUNCHER: OnceLock<Mutex<mpsc::Sender<Job>>> = OnceLock::new();
    if let Some(sender) = LAUNCHER.get() {
        return Ok(sender);
    }
    let (tx, rx) = mpsc::channel::<Job>();
    std::thread::Builder::new()
        .name("tacos-forker".into())
        .spawn(move || {
            for mut job in rx {
                // tokio's child reaping needs the runtime the caller lives in.
                let _in_runtime = job.runtime.enter();
                let _ = job.reply.send(job.command.spawn());
            }
        })?;
    // Two callers racing here start two threads; the loser's ends with its unused sender.
    Ok(LAUNCHER.get_or_init(|| Mutex::new(tx)))
}

/// Spawns `command` from the forker thread. Must be called inside a tokio runtime, whose
/// reaper then owns the child.
pub fn spawn(command: Command) -> std::io::Result<Child> {
    let runtime = tokio::runtime::Handle::try_current()
        .map_err(|e| std::io::Error::other(format!("no tokio runtime to spawn into: {e}")))?;
    let (reply, answer) = mpsc::channel();
    launcher()?
        .lock()
        .map_err(|_| std::io::Error::other("the forker's lock is poisoned"))?
        .send(Job {
            command,
            runtime,
            reply,
        })
        .map_err(|_| std::io::Error::other("the forker thread is gone"))?;
    answer
        .recv()
        .map_err(|_| std::io::Error::other("the forker thread gave no answer"))?
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sleeper() -> Command {
        let mut command = Command::new("sleep");
        command.arg("30").kill_on_drop(true);
        // SAFETY: prctl is async-signal-safe.
        unsafe {
            command.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                Ok(())
            });
        }
        command
    }

    /// A child forked with the parent-death signal on a thread that then ends gets the signal;
    /// one forked through the forker for that same thread lives on.
    #[test]
    fn a_child_outlives_the_thread_that_asked_for_it() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .expect("runtime");
        let asker = std::thread::spawn(move || {
            let (direct, forked) = runtime.block_on(async {
                (
                    sleeper().spawn().expect("spawned here"),
                    spawn(sleeper()).expect("spawned by the forker"),
                )
            });
            (runtime, direct, forked)
        });
        // The asking thread has ended here.
        let (runtime, mut direct, mut forked) = asker.join().expect("asker");
        runtime.block_on(async {
            let died = tokio::time::timeout(std::time::Duration::from_secs(5), direct.wait())
                .await
                .expect("the child forked on the ended thread still runs")
                .expect("wait");
            assert!(!died.success(), "{died}");
            assert!(
                forked.try_wait().expect("try_wait").is_none(),
                "the forker's child died with the thread that asked for it"
            );
            forked.kill().await.expect("kill");
        });
    }
}

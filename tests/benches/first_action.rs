//! How much sooner a Supervisor cycle's first action flies when calls are sent as the reply is
//! written (`mission::driver::early`) than when the whole reply is awaited: a program that prints
//! figures, asserting no speed.
//!
//! For the two Supervisor requests of the model benchmark (`tacos_tests::probes`: the six
//! take-offs of "all drones take off", none started; then three running), each backend streams
//! its reply and the bench notes when the first call is complete in it, read as the engine reads
//! it (`tacos_prompts::partial::partial_reply`), and when the reply is whole. The engine sends
//! that call once the checks and the gate pass it (microseconds to a millisecond), so `saved`
//! is the time to the first action saved. llama.cpp's server streams every token; the embedded
//! model tells its text every 200 ms, so its first-call time is late by up to that.
//!
//! Needs the venv of `bash tests/python/setup.sh` (xllamacpp) and the model file (fetched on
//! first use). Run alone on the machine:
//!
//! `cargo bench -p tacos-tests --bench first_action [-- --model qwen2.5-coder-1.5b|qwen2.5-coder-0.5b|smollm2-135m --threads 2]`

use std::sync::Mutex;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use tacos_embedded::{EmbeddedBackend, EmbeddedModel, EmbeddedOptions};
use tacos_llm::{LlmBackend, OpenAiBackend, OpenAiConfig, Streamed};
use tacos_prompts::partial::partial_reply;
use tacos_tests::llama_server::{self, LlamaServer, LlamaServerConfig};
use tacos_tests::probes::{Probe, mission_probes};

const USAGE: &str = "usage: cargo bench -p tacos-tests --bench first_action [-- --model NAME] \
[--threads N]\n  NAME: qwen2.5-coder-1.5b (default), qwen2.5-coder-0.5b, smollm2-135m";

/// When the first call was complete, and which it was.
#[derive(Default)]
struct FirstCall {
    at: Option<(Duration, String)>,
}

fn parse_args() -> anyhow::Result<(EmbeddedModel, u32)> {
    let mut model = EmbeddedModel::default();
    let mut threads = 2;
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--model" => {
                let name = args.next().context(USAGE)?;
                model = name.parse().map_err(|e| anyhow::anyhow!("{e}\n{USAGE}"))?;
            }
            "--threads" => {
                threads = args
                    .next()
                    .and_then(|t| t.parse().ok())
                    .filter(|t| *t > 0)
                    .context(USAGE)?;
            }
            // cargo bench passes --bench.
            "--bench" => {}
            other => bail!("unknown argument {other}\n{USAGE}"),
        }
    }
    Ok((model, threads))
}

/// Streams `probe` through `backend`, printing when its first call was complete and when the
/// reply was whole.
fn measure(
    runtime: &tokio::runtime::Runtime,
    backend: &dyn LlmBackend,
    label: &str,
    probe: &Probe,
) -> anyhow::Result<()> {
    let first = Mutex::new(FirstCall::default());
    let start = Instant::now();
    let progress = |so_far: Streamed<'_>| {
        let mut first = first.lock().unwrap_or_else(|e| e.into_inner());
        if first.at.is_none()
            && let Some(call) = partial_reply(so_far.content).calls.first()
        {
            first.at = Some((start.elapsed(), call.to_string()));
        }
    };
    let reply = runtime
        .block_on(backend.chat_streamed(&probe.request, &progress))
        .with_context(|| format!("{label}: {}", probe.name))?;
    let whole = start.elapsed();
    let first = first.into_inner().unwrap_or_else(|e| e.into_inner());
    match first.at {
        Some((at, call)) => println!(
            "first_action backend={label} probe=\"{}\" first_call_s={:.2} reply_s={:.2} saved_s={:.2} completion_tokens={} first_call=\"{call}\"",
            probe.name,
            at.as_secs_f64(),
            whole.as_secs_f64(),
            (whole - at).as_secs_f64(),
            reply.usage.completion_tokens,
        ),
        None => println!(
            "first_action backend={label} probe=\"{}\" first_call_s=none reply_s={:.2} completion_tokens={} (no call in the reply: {})",
            probe.name,
            whole.as_secs_f64(),
            reply.usage.completion_tokens,
            reply.content
        ),
    }
    Ok(())
}

fn run() -> anyhow::Result<()> {
    let (model, threads) = parse_args()?;
    // Before any thread starts (candle reads these when its pools are first used).
    // SAFETY: no other thread runs yet in this process.
    unsafe {
        std::env::set_var("CANDLE_NUM_THREADS", threads.to_string());
        std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
    }
    let Some(python) = llama_server::llama_python_or_skip("first_action bench") else {
        bail!(
            "llama.cpp's server is needed: run bash tests/python/setup.sh (it installs xllamacpp into {})",
            llama_server::venv_python().display()
        );
    };
    let gguf = llama_server::embedded_model(model)?;
    let probes: Vec<Probe> = mission_probes()?
        .into_iter()
        .filter(|p| p.name.starts_with("supervisor"))
        .collect();
    println!(
        "first_action bench: {} ({}), threads {threads}",
        model.display_name(),
        gguf.display()
    );
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;

    let config = LlamaServerConfig::new(&python, &gguf, model.name())
        .n_ctx(8192)
        .threads(threads)
        .n_parallel(1);
    let server = LlamaServer::start(&config)?;
    let llama = OpenAiBackend::new(
        OpenAiConfig::new(server.url().to_owned(), server.model())
            .with_timeout(Duration::from_secs(900))
            .with_retries(0, Duration::from_millis(100)),
    )
    .context("the OpenAI backend for llama.cpp's server")?;
    for probe in &probes {
        measure(&runtime, &llama, "llama.cpp", probe)?;
    }
    drop(server);

    let embedded = EmbeddedBackend::load(EmbeddedOptions {
        model,
        ..EmbeddedOptions::from_env()
    })
    .with_context(|| format!("loading the embedded {}", model.display_name()))?;
    for probe in &probes {
        measure(&runtime, &embedded, "embedded", probe)?;
    }
    Ok(())
}

fn main() {
    if let Err(e) = run() {
        eprintln!("first_action bench: {e:#}");
        std::process::exit(1);
    }
}

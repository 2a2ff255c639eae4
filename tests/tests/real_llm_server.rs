//! `tacos_llm::OpenAiBackend` against llama.cpp's own OpenAI-compatible server (xllamacpp, from
//! `tests/python/setup.sh`), serving SmolLM2-135M-Instruct, the embedded model's GGUF: what a
//! pilot who points TACOS at a llama.cpp server gets, for each thing that can go right or wrong
//! there. The loopback stand-in (`tacos_tests::chat_server`) stays for what a real server cannot
//! do on demand (429s, 503s, prose replies); this file holds the backend to the real thing.
//!
//! Each test starts its own server on a free port (about half a second) and stops it on drop.
//! Without the venv or xllamacpp the tests say how to get them and return (fail with `CI=true`).
//! The model is fetched into the model cache on first use (98 MB, pinned sha256).
//!
//! What the server answered, measured with xllamacpp 2026.10.11549 (n_ctx as given):
//! - a prompt longer than the context: HTTP 400, `{"error":{"code":400,"message":"request (1830
//!   tokens) exceeds the available context size (512 tokens), try increasing it",
//!   "type":"exceed_context_size_error","n_prompt_tokens":1830,"n_ctx":512}}`, in milliseconds;
//! - a reply cut at `max_tokens`: 200 with `finish_reason: "length"`, `completion_tokens` equal to
//!   the limit;
//! - a reply that runs into the end of the context: 200 with `finish_reason: "length"` too, and
//!   fewer tokens than the limit (prompt + reply = n_ctx);
//! - killed mid-generation: the connection closes with no reply; then connections are refused.

use serde_json::{Value, json};
use std::time::{Duration, Instant};
use tacos_llm::{
    ChatMessage, ChatReply, ChatRequest, LlmBackend, LlmError, OpenAiBackend, OpenAiConfig,
    ResponseSchema,
};
use tacos_tests::llama_server::{
    LlamaServer, LlamaServerConfig, llama_python_or_skip, smollm2_model,
};
use tacos_tests::within;

/// The model name the servers report.
const ALIAS: &str = "smollm2-135m-instruct";

/// llama.cpp's server for `test` with an `n_ctx`-token context, or `None` when skipped.
fn server_or_skip(test: &str, n_ctx: u32) -> anyhow::Result<Option<LlamaServer>> {
    let Some(python) = llama_python_or_skip(test) else {
        return Ok(None);
    };
    let model = smollm2_model()?;
    // One thread: llama.cpp's threads wait for each other at every step, and on this 2-core
    // machine with another process busy (a build, a benchmark) two of them were 13 times slower
    // than one (Qwen2.5-Coder-1.5B, a 33-token json_schema reply: 37.6 s on 2 threads, 2.9 s
    // on 1).
    let config = LlamaServerConfig::new(python, model, ALIAS)
        .n_ctx(n_ctx)
        .threads(1);
    let server = LlamaServer::start(&config)?;
    eprintln!(
        "{test}: llama.cpp's server at {} ready in {:.2} s (n_ctx {n_ctx}, pid {})",
        server.url(),
        server.startup().as_secs_f64(),
        server.pid()
    );
    Ok(Some(server))
}

/// The backend as a pilot configures it for this server: the default retries and backoff, and a
/// per-attempt timeout that no test here comes near.
fn config(server: &LlamaServer) -> OpenAiConfig {
    OpenAiConfig::new(server.url(), server.model()).with_timeout(Duration::from_secs(120))
}

fn backend(config: OpenAiConfig) -> anyhow::Result<OpenAiBackend> {
    Ok(OpenAiBackend::new(config)?)
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?)
}

/// A request as the ground sends one (a system prompt, the pilot's words, a schema, a seed,
/// `reasoning_effort: low`), greedy so the runs repeat.
fn request(system: &str, user: &str, schema: Option<Value>, max_tokens: u32) -> ChatRequest {
    ChatRequest {
        messages: vec![ChatMessage::system(system), ChatMessage::user(user)],
        schema: schema.map(|schema| ResponseSchema {
            name: "test_reply".into(),
            schema,
        }),
        max_tokens,
        temperature: 0.0,
        seed: Some(7),
        reasoning_effort: Some("low".into()),
    }
}

/// The longest `minLength` llama.cpp takes: its JSON-schema grammar repeats a character
/// `minLength` times, and a repetition over 2000 is refused with HTTP 400 "Failed to initialize
/// samplers: failed to parse grammar" (the reason, "number of repetitions exceeds sane
/// defaults", is in its log only).
const MAX_MIN_LENGTH: u32 = 2000;

/// A JSON object with one string of at least `min_chars` characters: the grammar lets the model
/// neither stop early nor leave the string, so the reply's length is the test's, not the
/// model's choice.
fn long_text_schema(min_chars: u32) -> Value {
    json!({
        "type": "object",
        "properties": { "story": { "type": "string", "minLength": min_chars } },
        "required": ["story"],
        "additionalProperties": false
    })
}

fn report(test: &str, what: &str, reply: &ChatReply) {
    eprintln!(
        "{test}: {what}: {:.2} s, {} prompt + {} completion tokens, model {:?}: {}",
        reply.latency.as_secs_f64(),
        reply.usage.prompt_tokens,
        reply.usage.completion_tokens,
        reply.model,
        reply.content
    );
}

/// `words` words of mission-briefing filler: about one token per word for this tokenizer.
fn filler(words: usize) -> String {
    const TEXT: &str = "alfa holds north of the tower while bravo scans the river bank and charlie \
        waits by the depot for the van to pass the bridge";
    TEXT.split_whitespace()
        .cycle()
        .take(words)
        .collect::<Vec<_>>()
        .join(" ")
}

#[test]
fn a_json_schema_reply_parses_and_follows_the_schema() -> anyhow::Result<()> {
    const TEST: &str = "a_json_schema_reply_parses_and_follows_the_schema";
    let Some(server) = server_or_skip(TEST, 2048)? else {
        return Ok(());
    };
    let schema = json!({
        "type": "object",
        "properties": {
            "drone": { "type": "string", "enum": ["alfa", "bravo", "charlie"] },
            "action": { "type": "string", "enum": ["arm_takeoff", "land", "hold"] },
            "altitude_m": { "type": "integer", "minimum": 2, "maximum": 30 }
        },
        "required": ["drone", "action", "altitude_m"],
        "additionalProperties": false
    });
    let backend = backend(config(&server))?;
    let request = request(
        "You command a drone swarm. Answer with one JSON object.",
        "Bravo, take off to 10 metres.",
        Some(schema),
        200,
    );
    let reply = runtime()?.block_on(within(
        "a json_schema reply",
        Duration::from_secs(60),
        backend.chat(&request),
    ))??;
    report(TEST, "reply", &reply);

    let value: Value = serde_json::from_str(&reply.content)
        .map_err(|e| anyhow::anyhow!("the reply is not JSON ({e}): {}", reply.content))?;
    let object = value
        .as_object()
        .ok_or_else(|| anyhow::anyhow!("not an object: {value}"))?;
    let mut keys: Vec<&str> = object.keys().map(String::as_str).collect();
    keys.sort_unstable();
    assert_eq!(
        keys,
        ["action", "altitude_m", "drone"],
        "every required key and no other: {value}"
    );
    assert!(
        ["alfa", "bravo", "charlie"].contains(&object["drone"].as_str().unwrap_or("")),
        "drone outside its enum: {value}"
    );
    assert!(
        ["arm_takeoff", "land", "hold"].contains(&object["action"].as_str().unwrap_or("")),
        "action outside its enum: {value}"
    );
    let altitude = object["altitude_m"]
        .as_i64()
        .ok_or_else(|| anyhow::anyhow!("altitude_m is not an integer: {value}"))?;
    assert!(
        (2..=30).contains(&altitude),
        "altitude_m out of range: {value}"
    );
    assert_eq!(reply.model, ALIAS, "the model name the server reports");
    Ok(())
}

#[test]
fn usage_counts_prompt_and_completion_tokens() -> anyhow::Result<()> {
    const TEST: &str = "usage_counts_prompt_and_completion_tokens";
    let Some(server) = server_or_skip(TEST, 2048)? else {
        return Ok(());
    };
    let schema = json!({
        "type": "object",
        "properties": { "ready": { "type": "boolean" } },
        "required": ["ready"],
        "additionalProperties": false
    });
    let backend = backend(config(&server))?;
    let system = "You command a drone swarm. Answer with one JSON object.";
    let short = request(system, "Are you ready?", Some(schema.clone()), 64);
    let briefing = format!("Briefing: {}. Are you ready?", filler(300));
    let long = request(system, &briefing, Some(schema), 64);
    let (short_reply, long_reply) = runtime()?.block_on(async {
        let short = within(
            "the short request",
            Duration::from_secs(60),
            backend.chat(&short),
        );
        let short = short.await??;
        let long = within(
            "the long request",
            Duration::from_secs(60),
            backend.chat(&long),
        );
        anyhow::Ok((short, long.await??))
    })?;
    report(TEST, "short prompt", &short_reply);
    report(TEST, "long prompt", &long_reply);

    for reply in [&short_reply, &long_reply] {
        assert!(reply.usage.prompt_tokens > 0, "{:?}", reply.usage);
        assert!(reply.usage.completion_tokens > 0, "{:?}", reply.usage);
    }
    // 300 more words of briefing: well over 200 more prompt tokens.
    assert!(
        long_reply.usage.prompt_tokens >= short_reply.usage.prompt_tokens + 200,
        "short {:?}, long {:?}",
        short_reply.usage,
        long_reply.usage
    );
    Ok(())
}

#[test]
fn a_prompt_longer_than_the_context_is_a_clear_error_at_once() -> anyhow::Result<()> {
    const TEST: &str = "a_prompt_longer_than_the_context_is_a_clear_error_at_once";
    let Some(server) = server_or_skip(TEST, 512)? else {
        return Ok(());
    };
    // A first backoff of 2 s: a retry would show as a call of a second or more.
    let backend = backend(config(&server).with_retries(2, Duration::from_secs(2)))?;
    let too_long = request(
        "You command a drone swarm. Answer with one JSON object.",
        &format!("Briefing: {}. Are you ready?", filler(1500)),
        Some(long_text_schema(1)),
        64,
    );
    let runtime = runtime()?;
    let started = Instant::now();
    let outcome = runtime.block_on(within(
        "the over-long request",
        Duration::from_secs(60),
        backend.chat(&too_long),
    ))?;
    let took = started.elapsed();
    eprintln!("{TEST}: over-long prompt: {took:?}: {outcome:?}");
    match &outcome {
        Err(error @ LlmError::Http { status: 400, body }) => {
            // What the pilot reads, in the server's words.
            let shown = error.to_string();
            eprintln!("{TEST}: the pilot reads: {shown}");
            assert!(
                body.contains("exceeds the available context size (512 tokens)"),
                "{shown}"
            );
        }
        other => panic!("expected HTTP 400 for a prompt over the context, got {other:?}"),
    }
    assert!(
        took < Duration::from_secs(1),
        "a 400 is not retried, so the call is one exchange: {took:?}"
    );

    // The server is none the worse: the next request that fits is answered.
    let fits = request(
        "You command a drone swarm. Answer with one JSON object.",
        "Are you ready?",
        Some(json!({
            "type": "object",
            "properties": { "ready": { "type": "boolean" } },
            "required": ["ready"],
            "additionalProperties": false
        })),
        64,
    );
    let reply = runtime.block_on(within(
        "a request that fits, after the over-long one",
        Duration::from_secs(60),
        backend.chat(&fits),
    ))??;
    report(TEST, "the next request", &reply);
    Ok(())
}

#[test]
fn a_reply_cut_by_the_token_limit_is_truncated() -> anyhow::Result<()> {
    const TEST: &str = "a_reply_cut_by_the_token_limit_is_truncated";
    let Some(server) = server_or_skip(TEST, 2048)? else {
        return Ok(());
    };
    let backend = backend(config(&server))?;
    let system = "You are a storyteller.";
    let runtime = runtime()?;
    // With a schema (as the ground always asks) the grammar holds the model in a long string;
    // without one, a story takes more than 8 tokens.
    for (what, schema) in [
        ("json_schema", Some(long_text_schema(400))),
        ("free text", None),
    ] {
        let cut = request(system, "Tell a long story about a drone.", schema, 8);
        let started = Instant::now();
        let outcome = runtime.block_on(within(
            "a reply over max_tokens",
            Duration::from_secs(60),
            backend.chat(&cut),
        ))?;
        eprintln!(
            "{TEST}: {what}, max_tokens 8: {:?}: {outcome:?}",
            started.elapsed()
        );
        assert_eq!(outcome, Err(LlmError::Truncated(8)), "{what}");
    }
    Ok(())
}

/// The prompt fits, the reply does not: llama.cpp stops at the end of the context with
/// `finish_reason: "length"`, short of `max_tokens`. The pilot must read that the context is
/// full, not that the reply hit its token limit.
#[test]
fn a_reply_that_fills_the_context_says_the_context_is_full() -> anyhow::Result<()> {
    const TEST: &str = "a_reply_that_fills_the_context_says_the_context_is_full";
    let Some(server) = server_or_skip(TEST, 512)? else {
        return Ok(());
    };
    let backend = backend(config(&server))?;
    // About 480 prompt tokens, leaving about 30 of the 512; the grammar asks for 2,000
    // characters (several hundred tokens) and max_tokens allows 400.
    let fills = request(
        "You are a storyteller.",
        &format!("Notes: {}. Tell a long story about a drone.", filler(400)),
        Some(long_text_schema(MAX_MIN_LENGTH)),
        400,
    );
    let started = Instant::now();
    let outcome = runtime()?.block_on(within(
        "a reply that fills the context",
        Duration::from_secs(120),
        backend.chat(&fills),
    ))?;
    eprintln!("{TEST}: {:?}: {outcome:?}", started.elapsed());
    match outcome {
        Err(LlmError::Generation(message)) => {
            assert!(message.contains("context is full"), "{message}");
            assert!(message.contains("= 512 tokens"), "{message}");
        }
        other => panic!("expected a full-context error, got {other:?}"),
    }
    Ok(())
}

#[test]
fn the_server_going_away_mid_call_is_a_clear_error_soon() -> anyhow::Result<()> {
    const TEST: &str = "the_server_going_away_mid_call_is_a_clear_error_soon";
    let Some(mut server) = server_or_skip(TEST, 4096)? else {
        return Ok(());
    };
    // The defaults a pilot has: 2 retries from 500 ms, and a 120 s timeout per attempt.
    let config = config(&server);
    let timeout = config.timeout;
    let backend = std::sync::Arc::new(backend(config)?);
    // Hundreds of tokens of forced story: seconds of generation, unless interrupted.
    let long = request(
        "You are a storyteller.",
        "Tell a long story about a drone.",
        Some(long_text_schema(MAX_MIN_LENGTH)),
        4000,
    );
    let runtime = runtime()?;
    let log_mark = server.log_lines_seen();
    let call = {
        let backend = backend.clone();
        runtime.spawn(async move { backend.chat(&long).await })
    };
    // The generation is under way once the server has taken the task.
    server.wait_for_log(log_mark, "processing task", Duration::from_secs(30))?;
    let running = Instant::now();
    server.kill()?;
    let killed = Instant::now();
    eprintln!(
        "{TEST}: killed the server {:?} into the generation",
        killed - running
    );
    let outcome = runtime.block_on(within(
        "the call to end after the server was killed",
        Duration::from_secs(30),
        call,
    ))??;
    let took = killed.elapsed();
    eprintln!("{TEST}: the call ended {took:?} after the kill: {outcome:?}");
    match &outcome {
        Err(error @ LlmError::Connect(message)) => {
            eprintln!("{TEST}: the pilot reads: {error}");
            assert!(
                message.to_lowercase().contains("refused"),
                "the last attempt finds no server: {message}"
            );
        }
        other => panic!("expected a connection error, got {other:?}"),
    }
    // Two retries with backoff (0.25–0.5 s, then 0.5–1 s), each refused at once.
    assert!(
        took < Duration::from_secs(5),
        "the error comes within the backoff, not the {timeout:?} timeout: {took:?}"
    );
    Ok(())
}

/// The helper's own failure: a file that is not a model. The error names the command and shows
/// llama.cpp's reason from its log, at once rather than at the ready timeout.
#[test]
fn a_server_that_cannot_start_says_why() -> anyhow::Result<()> {
    const TEST: &str = "a_server_that_cannot_start_says_why";
    let Some(python) = llama_python_or_skip(TEST) else {
        return Ok(());
    };
    let not_a_model =
        std::env::temp_dir().join(format!("{}.gguf", tacos_tests::unique_swarm("notgguf")));
    std::fs::write(&not_a_model, b"not a GGUF file")?;
    let started = Instant::now();
    let outcome = LlamaServer::start(&LlamaServerConfig::new(python, &not_a_model, ALIAS));
    let took = started.elapsed();
    let _ = std::fs::remove_file(&not_a_model);
    let Err(error) = outcome else {
        panic!("a server started on a file that is not a model");
    };
    let message = format!("{error:#}");
    eprintln!("{TEST}: {took:?}: {message}");
    assert!(
        message.contains("llama_server.py"),
        "names the command: {message}"
    );
    assert!(
        message.contains("failed to load model"),
        "llama.cpp's reason: {message}"
    );
    assert!(took < Duration::from_secs(30), "{took:?}");
    Ok(())
}

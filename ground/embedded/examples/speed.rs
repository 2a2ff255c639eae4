//! Speed of the embedded model on this machine.
//!
//! `cargo run -p tacos-embedded --example speed [-- MODEL [q4_1|q8_0|f32]]`
//! (MODEL: qwen2.5-coder-1.5b, qwen2.5-coder-0.5b or smollm2-135m; default from
//! `$TACOS_EMBEDDED_MODEL`, else qwen2.5-coder-1.5b)
//!
//! Prints the load time, tokens/second of a ~200-token JSON generation constrained by a schema,
//! and the time of one call whose prompt is ~1500 tokens.

use std::time::Instant;

use serde_json::json;
use tacos_embedded::{EmbeddedBackend, EmbeddedOptions, WeightFormat};
use tacos_llm::{ChatMessage, ChatRequest, LlmBackend, ResponseSchema};

fn main() {
    if let Err(e) = run() {
        eprintln!("speed: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let mut opts = EmbeddedOptions::from_env();
    if let Some(m) = std::env::args().nth(1) {
        opts.model = m.parse()?;
    }
    if let Some(w) = std::env::args().nth(2) {
        opts.weights = WeightFormat::parse(&w).ok_or(format!("unknown weight format {w}"))?;
    }
    let path = opts.ensure_model()?;
    let t = Instant::now();
    let backend = EmbeddedBackend::load(opts)?;
    println!("model      {}", path.display());
    println!("backend    {}", backend.describe());
    println!("load       {:.2} s", t.elapsed().as_secs_f64());

    // 1. A ~200-token constrained generation.
    let schema = json!({
        "type": "object",
        "properties": {
            "reasoning": {"type": "string", "minLength": 500, "maxLength": 700},
            "plan": {
                "type": "array", "minItems": 4, "maxItems": 6,
                "items": {
                    "type": "object",
                    "properties": {
                        "drone": {"type": "string", "enum": ["alfa", "bravo", "charlie"]},
                        "action": {"type": "string", "enum": ["takeoff", "land", "hold", "goto"]}
                    },
                    "required": ["drone", "action"],
                    "additionalProperties": false
                }
            }
        },
        "required": ["reasoning", "plan"],
        "additionalProperties": false
    });
    let req = ChatRequest {
        messages: vec![
            ChatMessage::system(
                "You command drones alfa, bravo and charlie. Explain your reasoning in detail, then give the plan as JSON.",
            ),
            ChatMessage::user(
                "Survey the north field with alfa and bravo, then bring everyone home; charlie stays as a relay.",
            ),
        ],
        schema: Some(ResponseSchema {
            name: "plan".into(),
            schema: schema.clone(),
        }),
        max_tokens: 400,
        temperature: 0.0,
        seed: Some(1),
        reasoning_effort: None,
    };
    let (reply, stats) = backend.chat_blocking(&req)?;
    let n = reply.usage.completion_tokens;
    let sampled = n - stats.forced_tokens;
    println!(
        "generate   {} prompt + {} completion tokens ({} forced by the grammar) in {:.2} s: \
         prefill {:.2} s, decode {:.2} s = {:.1} tokens/s ({:.1} sampled tokens/s)",
        reply.usage.prompt_tokens,
        n,
        stats.forced_tokens,
        reply.latency.as_secs_f64(),
        stats.prefill.as_secs_f64(),
        stats.decode.as_secs_f64(),
        n as f64 / stats.decode.as_secs_f64(),
        sampled as f64 / stats.decode.as_secs_f64(),
    );
    println!("           {}", reply.content);

    // 2. One call with a ~1500-token prompt (a mission history), a short constrained answer.
    let mut history = String::new();
    let mut i = 0;
    let mut long = req.clone();
    long.schema = Some(ResponseSchema {
        name: "plan".into(),
        schema: json!({
            "type": "object",
            "properties": {
                "reasoning": {"type": "string", "maxLength": 200},
                "plan": schema["properties"]["plan"].clone()
            },
            "required": ["reasoning", "plan"],
            "additionalProperties": false
        }),
    });
    loop {
        history.push_str(&format!(
            "t={i}s: alfa at ({}.0, {}.5, -10.0) battery {}%, bravo holding at waypoint {}, charlie on the ground.\n",
            i * 3 % 97,
            i * 7 % 53,
            100 - i % 60,
            i % 9
        ));
        i += 1;
        long.messages[0] = ChatMessage::system(format!(
            "You command drones alfa, bravo and charlie. Mission log so far:\n{history}"
        ));
        if backend.count_prompt_tokens(&long)? >= 1500 {
            break;
        }
    }
    for label in ["long call ", "again     "] {
        // The second time, the prompt's cache is kept: only the generation prompt is fed again.
        let (reply, stats) = backend.chat_blocking(&long)?;
        let computed = reply.usage.prompt_tokens - stats.reused_tokens;
        println!(
            "{label} {} prompt ({} from the kept cache) + {} completion tokens in {:.2} s: \
             prefill {:.2} s ({:.0} tokens/s), decode {:.2} s",
            reply.usage.prompt_tokens,
            stats.reused_tokens,
            reply.usage.completion_tokens,
            reply.latency.as_secs_f64(),
            stats.prefill.as_secs_f64(),
            computed as f64 / stats.prefill.as_secs_f64(),
            stats.decode.as_secs_f64(),
        );
        println!("           {}", reply.content);
    }

    // The async path, for completeness: one short call through the trait.
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let mut short = req.clone();
    short.schema = long.schema.clone();
    let reply = rt.block_on(backend.chat(&short))?;
    println!(
        "short call {} prompt + {} completion tokens in {:.2} s (through LlmBackend::chat)",
        reply.usage.prompt_tokens,
        reply.usage.completion_tokens,
        reply.latency.as_secs_f64()
    );
    Ok(())
}

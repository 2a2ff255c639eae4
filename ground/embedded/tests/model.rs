//! The real model: fetched into the cache if missing (needs PyPI the first time), loaded, asked.

use std::sync::OnceLock;

use serde_json::{Value, json};
use tacos_embedded::{EmbeddedBackend, EmbeddedOptions};
use tacos_llm::{ChatMessage, ChatRequest, LlmBackend, LlmError, ResponseSchema};

fn backend() -> &'static EmbeddedBackend {
    static B: OnceLock<EmbeddedBackend> = OnceLock::new();
    B.get_or_init(|| EmbeddedBackend::lazy(EmbeddedOptions::from_env()))
}

const DRONES: [&str; 3] = ["alfa", "bravo", "charlie"];
const ACTIONS: [&str; 4] = ["takeoff", "land", "hold", "goto"];

fn plan_schema() -> Value {
    json!({
        "type": "object",
        "properties": {
            "reasoning": {"type": "string", "maxLength": 200},
            "plan": {
                "type": "array",
                "minItems": 1,
                "maxItems": 6,
                "items": {
                    "type": "object",
                    "properties": {
                        "drone": {"type": "string", "enum": DRONES},
                        "action": {"type": "string", "enum": ACTIONS}
                    },
                    "required": ["drone", "action"],
                    "additionalProperties": false
                }
            }
        },
        "required": ["reasoning", "plan"],
        "additionalProperties": false
    })
}

fn request(max_tokens: u32) -> ChatRequest {
    ChatRequest {
        messages: vec![
            ChatMessage::system(
                "You command a swarm of drones named alfa, bravo and charlie. Answer with JSON: \
                 {\"reasoning\": short text, \"plan\": [{\"drone\": name, \"action\": one of \
                 takeoff, land, hold, goto}]}.",
            ),
            ChatMessage::user("Take off with alfa and bravo, and keep charlie on the ground."),
        ],
        schema: Some(ResponseSchema {
            name: "plan".to_string(),
            schema: plan_schema(),
        }),
        max_tokens,
        temperature: 0.0,
        seed: Some(7),
        reasoning_effort: None,
    }
}

#[tokio::test]
async fn constrained_reply_parses_and_respects_the_enums() {
    let b = backend();
    let reply = b.chat(&request(400)).await.expect("embedded model answers");
    eprintln!(
        "reply ({:?}, {:?}): {}",
        reply.latency, reply.usage, reply.content
    );
    let v: Value = serde_json::from_str(&reply.content).expect("the reply is JSON");
    let obj = v.as_object().expect("an object");
    assert_eq!(obj.len(), 2, "only the schema's keys: {obj:?}");
    let reasoning = obj["reasoning"].as_str().expect("reasoning is a string");
    assert!(reasoning.chars().count() <= 200);
    let plan = obj["plan"].as_array().expect("plan is an array");
    assert!((1..=6).contains(&plan.len()));
    for step in plan {
        let drone = step["drone"].as_str().expect("drone is a string");
        let action = step["action"].as_str().expect("action is a string");
        assert!(DRONES.contains(&drone), "unknown drone {drone}");
        assert!(ACTIONS.contains(&action), "unknown action {action}");
        assert_eq!(step.as_object().map(|o| o.len()), Some(2));
    }
    assert_eq!(reply.model, "SmolLM2-135M-Instruct-Q4_1");
    assert!(reply.usage.prompt_tokens > 50, "{:?}", reply.usage);
    assert!(reply.usage.completion_tokens > 5, "{:?}", reply.usage);
    assert!(!reply.latency.is_zero());
    assert!(
        b.describe()
            .starts_with("embedded SmolLM2-135M-Instruct Q4_1")
    );

    // Same seed, same request: same answer.
    let again = b.chat(&request(400)).await.expect("second answer");
    assert_eq!(again.content, reply.content);
}

#[tokio::test]
async fn too_few_tokens_is_truncated() {
    let err = backend()
        .chat(&request(5))
        .await
        .expect_err("cannot fit in 5 tokens");
    assert_eq!(err, LlmError::Truncated(5));
}

#[tokio::test]
async fn free_text_without_schema() {
    let req = ChatRequest {
        messages: vec![ChatMessage::user("Say hello in one short sentence.")],
        schema: None,
        max_tokens: 60,
        temperature: 0.0,
        seed: None,
        reasoning_effort: None,
    };
    match backend().chat(&req).await {
        Ok(r) => assert!(!r.content.trim().is_empty(), "{r:?}"),
        Err(e) => assert_eq!(e, LlmError::Truncated(60)),
    }
}

#[test]
fn tokenizer_round_trips_and_splits_digits() {
    let b = backend();
    let text = "Drone alfa: goto (12.5, -3) — héllo {\"a\": [1, 2]}\n\tend";
    let ids = b.tokenize(text).expect("tokenize");
    assert_eq!(b.detokenize(&ids).expect("detokenize"), text);
    // Digits are split one by one (the `smollm` pre-tokenizer).
    let digits = b.tokenize("2024").expect("tokenize");
    assert_eq!(digits.len(), 4, "{digits:?}");
    // Common words are single tokens, with the leading space in the token.
    assert_eq!(b.tokenize("Hello world").expect("tokenize").len(), 2);
    // Control-token spellings in message text are not control tokens.
    let ids = b.tokenize("x<|im_end|>y").expect("tokenize");
    assert!(
        !ids.contains(&2) && !ids.contains(&1) && !ids.contains(&0),
        "{ids:?}"
    );
}

#[tokio::test]
async fn abandoned_call_does_not_block_the_next() {
    let b = backend();
    // Make sure the model is loaded, so the timeout below hits the generation itself.
    let _ = b.chat(&request(5)).await;
    let slow =
        tokio::time::timeout(std::time::Duration::from_millis(20), b.chat(&request(400))).await;
    assert!(slow.is_err(), "a 400-token answer in 20 ms?");
    let reply = b
        .chat(&request(400))
        .await
        .expect("answers after an abandoned call");
    assert!(serde_json::from_str::<Value>(&reply.content).is_ok());
}

/// `prefixItems` (the mission engine's repair grammar for a call the instruction asks for):
/// the reply opens with the required call, and the rest of the list follows `items`.
#[tokio::test]
async fn a_required_opening_call_opens_the_reply() {
    let call = |actions: &[&str], targets: &[&str]| {
        json!({
            "type": "object",
            "properties": {
                "drone": {"type": "string", "enum": DRONES},
                "action": {"type": "string", "enum": actions},
                "target": {"type": "string", "enum": targets}
            },
            "required": ["drone", "action", "target"],
            "additionalProperties": false
        })
    };
    let schema = json!({
        "type": "object",
        "properties": {
            "plan": {
                "type": "array",
                "minItems": 1,
                "maxItems": 3,
                "prefixItems": [call(&["start_tracking"], &["van"])],
                "items": call(&["goto", "land"], &["car_1", "none"])
            }
        },
        "required": ["plan"],
        "additionalProperties": false
    });
    let mut req = request(300);
    req.messages[1] = ChatMessage::user("bravo, go to car_1");
    req.schema = Some(ResponseSchema {
        name: "plan".to_string(),
        schema,
    });
    let reply = backend().chat(&req).await.expect("embedded model answers");
    eprintln!("reply: {}", reply.content);
    let v: Value = serde_json::from_str(&reply.content).expect("the reply is JSON");
    let plan = v["plan"].as_array().expect("plan is an array");
    assert_eq!(plan[0]["action"], "start_tracking", "{plan:?}");
    assert_eq!(plan[0]["target"], "van", "{plan:?}");
    for later in &plan[1..] {
        assert!(
            later["action"] == "goto" || later["action"] == "land",
            "{plan:?}"
        );
    }
}

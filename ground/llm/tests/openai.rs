//! `OpenAiBackend` against a replay server, one test per server shape and failure mode.

mod support;

use std::time::{Duration, Instant};

use serde_json::json;
use support::{Canned, ReplayServer};
use tacos_llm::{
    ChatMessage, ChatRequest, LlmBackend, LlmError, OpenAiBackend, OpenAiConfig, ResponseSchema,
    TokenLimitField, Usage,
};

const PLAN: &str =
    r#"{"reasoning":"alfa is closest","plan":[{"drone":"alfa","action":"takeoff"}]}"#;

fn config(server: &ReplayServer) -> OpenAiConfig {
    OpenAiConfig::new(server.base_url(), "test-model")
        .with_timeout(Duration::from_secs(5))
        .with_retries(2, Duration::from_millis(10))
}

fn backend(config: OpenAiConfig) -> OpenAiBackend {
    OpenAiBackend::new(config).expect("backend")
}

fn request() -> ChatRequest {
    ChatRequest {
        messages: vec![
            ChatMessage::system("You plan missions."),
            ChatMessage::user("alfa take off"),
        ],
        schema: Some(ResponseSchema {
            name: "coordinator_plan".into(),
            schema: json!({
                "type": "object",
                "properties": {"reasoning": {"type": "string"}, "plan": {"type": "array"}},
                "required": ["reasoning", "plan"],
                "additionalProperties": false
            }),
        }),
        max_tokens: 512,
        temperature: 0.2,
        seed: Some(42),
        reasoning_effort: Some("low".into()),
    }
}

/// OpenAI's shape (gpt-oss on OpenAI-style servers puts the chain of thought in `reasoning`).
fn openai_reply(content: &str, finish_reason: &str) -> serde_json::Value {
    json!({
        "id": "chatcmpl-1", "object": "chat.completion", "created": 1_760_000_000, "model": "gpt-oss-20b",
        "choices": [{
            "index": 0,
            "message": {"role": "assistant", "content": content, "refusal": null,
                        "reasoning": "The pilot wants alfa up; alfa is closest."},
            "logprobs": null,
            "finish_reason": finish_reason
        }],
        "usage": {"prompt_tokens": 120, "completion_tokens": 45, "total_tokens": 165}
    })
}

#[tokio::test]
async fn openai_reply_with_reasoning_field() {
    let server = ReplayServer::start([Canned::json(200, openai_reply(PLAN, "stop"))]).await;
    let reply = backend(config(&server))
        .chat(&request())
        .await
        .expect("reply");
    assert_eq!(reply.content, PLAN);
    assert_eq!(
        reply.reasoning.as_deref(),
        Some("The pilot wants alfa up; alfa is closest.")
    );
    assert_eq!(
        reply.usage,
        Usage {
            prompt_tokens: 120,
            completion_tokens: 45
        }
    );
    assert_eq!(reply.model, "gpt-oss-20b");
    assert_eq!(server.request_count(), 1);
}

#[tokio::test]
async fn vllm_reply_with_reasoning_content() {
    let body = json!({
        "id": "chatcmpl-9f2", "object": "chat.completion", "created": 1_760_000_000,
        "model": "Qwen/Qwen3-8B",
        "choices": [{
            "index": 0,
            "message": {"role": "assistant", "reasoning_content": "Bravo is busy, so alfa.",
                        "content": PLAN, "tool_calls": []},
            "logprobs": null, "finish_reason": "stop", "stop_reason": null
        }],
        "usage": {"prompt_tokens": 200, "total_tokens": 260, "completion_tokens": 60,
                  "prompt_tokens_details": null},
        "prompt_logprobs": null
    });
    let server = ReplayServer::start([Canned::json(200, body)]).await;
    let reply = backend(config(&server))
        .chat(&request())
        .await
        .expect("reply");
    assert_eq!(reply.content, PLAN);
    assert_eq!(reply.reasoning.as_deref(), Some("Bravo is busy, so alfa."));
    assert_eq!(
        reply.usage,
        Usage {
            prompt_tokens: 200,
            completion_tokens: 60
        }
    );
    assert_eq!(reply.model, "Qwen/Qwen3-8B");
}

#[tokio::test]
async fn ollama_reply_with_thinking() {
    let body = json!({
        "id": "chatcmpl-123", "object": "chat.completion", "created": 1_760_000_000,
        "model": "qwen3:8b", "system_fingerprint": "fp_ollama",
        "choices": [{
            "index": 0,
            "message": {"role": "assistant", "content": PLAN, "thinking": "Take off first."},
            "finish_reason": "stop"
        }],
        "usage": {"prompt_tokens": 90, "completion_tokens": 30, "total_tokens": 120}
    });
    let server = ReplayServer::start([Canned::json(200, body)]).await;
    let reply = backend(config(&server))
        .chat(&request())
        .await
        .expect("reply");
    assert_eq!(reply.content, PLAN);
    assert_eq!(reply.reasoning.as_deref(), Some("Take off first."));
    assert_eq!(
        reply.usage,
        Usage {
            prompt_tokens: 90,
            completion_tokens: 30
        }
    );
}

#[tokio::test]
async fn llamacpp_think_tags_in_content() {
    let body = json!({
        "choices": [{
            "finish_reason": "stop", "index": 0,
            "message": {"role": "assistant",
                        "content": format!("<think>\nThe pilot said alfa.\n</think>\n\n{PLAN}")}
        }],
        "created": 1_760_000_000, "model": "gpt-3.5-turbo", "system_fingerprint": "b6000-abc",
        "object": "chat.completion",
        "usage": {"completion_tokens": 70, "prompt_tokens": 150, "total_tokens": 220},
        "id": "chatcmpl-xyz",
        "timings": {"prompt_n": 150, "predicted_n": 70}
    });
    let server = ReplayServer::start([Canned::json(200, body)]).await;
    let reply = backend(config(&server))
        .chat(&request())
        .await
        .expect("reply");
    assert_eq!(reply.content, PLAN);
    assert_eq!(reply.reasoning.as_deref(), Some("The pilot said alfa."));
    assert_eq!(
        reply.usage,
        Usage {
            prompt_tokens: 150,
            completion_tokens: 70
        }
    );
}

#[tokio::test]
async fn request_carries_schema_seed_model_and_key() {
    let server = ReplayServer::start([Canned::json(200, openai_reply(PLAN, "stop"))]).await;
    let backend = backend(config(&server).with_api_key("sk-test-123"));
    backend.chat(&request()).await.expect("reply");

    let requests = server.requests();
    assert_eq!(requests.len(), 1);
    let sent = &requests[0];
    assert_eq!(sent.method, "POST");
    assert_eq!(sent.path, "/v1/chat/completions");
    assert_eq!(sent.header("authorization"), Some("Bearer sk-test-123"));
    assert_eq!(sent.header("content-type"), Some("application/json"));
    let body = sent.json();
    assert_eq!(body["model"], "test-model");
    assert_eq!(body["seed"], 42);
    assert_eq!(body["max_tokens"], 512);
    assert!(body.get("max_completion_tokens").is_none());
    assert_eq!(body["temperature"], 0.2);
    assert_eq!(body["reasoning_effort"], "low");
    assert_eq!(body["stream"], false);
    assert_eq!(
        body["messages"],
        json!([{"role": "system", "content": "You plan missions."},
               {"role": "user", "content": "alfa take off"}])
    );
    let format = &body["response_format"];
    assert_eq!(format["type"], "json_schema");
    assert_eq!(format["json_schema"]["name"], "coordinator_plan");
    assert_eq!(format["json_schema"]["strict"], true);
    assert_eq!(
        format["json_schema"]["schema"],
        request().schema.expect("schema").schema
    );
}

#[tokio::test]
async fn request_without_key_schema_or_seed() {
    let server = ReplayServer::start([Canned::json(200, openai_reply("free text", "stop"))]).await;
    let mut config = config(&server);
    config.token_limit_field = TokenLimitField::MaxCompletionTokens;
    let plain = ChatRequest {
        schema: None,
        seed: None,
        reasoning_effort: None,
        ..request()
    };
    let reply = backend(config).chat(&plain).await.expect("reply");
    assert_eq!(reply.content, "free text");

    let sent = &server.requests()[0];
    assert_eq!(sent.header("authorization"), None);
    let body = sent.json();
    for absent in ["response_format", "seed", "reasoning_effort", "max_tokens"] {
        assert!(body.get(absent).is_none(), "{absent} in {body}");
    }
    assert_eq!(body["max_completion_tokens"], 512);
}

#[tokio::test]
async fn rate_limited_429_honours_retry_after_then_succeeds() {
    let server = ReplayServer::start([
        Canned::json(
            429,
            json!({"error": {"message": "Rate limit reached", "type": "requests",
                                           "param": null, "code": "rate_limit_exceeded"}}),
        )
        .header("Retry-After", "1"),
        Canned::json(200, openai_reply(PLAN, "stop")),
    ])
    .await;
    let started = Instant::now();
    let reply = backend(config(&server))
        .chat(&request())
        .await
        .expect("reply after retry");
    assert_eq!(reply.content, PLAN);
    assert_eq!(server.request_count(), 2, "the 429 was retried once");
    assert!(
        started.elapsed() >= Duration::from_secs(1),
        "waited {:?}",
        started.elapsed()
    );
    assert!(
        reply.latency >= Duration::from_secs(1),
        "latency counts the whole call"
    );
}

#[tokio::test]
async fn retry_after_beyond_max_backoff_gives_up_at_once() {
    let server = ReplayServer::start([
        Canned::json(429, json!({"error": "too many requests"})).header("Retry-After", "3600"),
        Canned::json(200, openai_reply(PLAN, "stop")),
    ])
    .await;
    let err = backend(config(&server)).chat(&request()).await;
    assert_eq!(
        err,
        Err(LlmError::Http {
            status: 429,
            body: "too many requests".into()
        })
    );
    assert_eq!(server.request_count(), 1);
}

#[tokio::test]
async fn unavailable_503_is_retried_with_backoff() {
    let server = ReplayServer::start([
        Canned::json(503, json!({"error": {"code": 503, "message": "Loading model", "type": "unavailable_error"}})),
        Canned::json(200, openai_reply(PLAN, "stop")),
    ])
    .await;
    let reply = backend(config(&server))
        .chat(&request())
        .await
        .expect("reply");
    assert_eq!(reply.content, PLAN);
    assert_eq!(server.request_count(), 2);
}

#[tokio::test]
async fn server_errors_exhaust_retries() {
    let error = || {
        Canned::json(
            500,
            json!({"object": "error", "message": "CUDA out of memory",
                                 "type": "InternalServerError", "param": null, "code": 500}),
        )
    };
    let server = ReplayServer::start([
        error(),
        error(),
        error(),
        Canned::json(200, openai_reply(PLAN, "stop")),
    ])
    .await;
    let config = config(&server);
    let attempts = config.max_retries as usize + 1;
    let err = backend(config).chat(&request()).await;
    assert_eq!(
        err,
        Err(LlmError::Http {
            status: 500,
            body: "CUDA out of memory".into()
        })
    );
    assert_eq!(server.request_count(), attempts);
}

#[tokio::test]
async fn bad_request_is_not_retried() {
    let server = ReplayServer::start([
        Canned::json(
            400,
            json!({"error": "model \"nope\" not found, try pulling it first"}),
        ),
        Canned::json(200, openai_reply(PLAN, "stop")),
    ])
    .await;
    let err = backend(config(&server)).chat(&request()).await;
    assert_eq!(
        err,
        Err(LlmError::Http {
            status: 400,
            body: "model \"nope\" not found, try pulling it first".into()
        })
    );
    assert_eq!(server.request_count(), 1);
}

#[tokio::test]
async fn slow_server_times_out_after_retries() {
    let slow = || Canned::json(200, openai_reply(PLAN, "stop")).delay(Duration::from_secs(2));
    let server = ReplayServer::start([slow(), slow(), slow()]).await;
    let timeout = Duration::from_millis(200);
    let config = config(&server)
        .with_timeout(timeout)
        .with_retries(1, Duration::from_millis(10));
    let started = Instant::now();
    let err = backend(config).chat(&request()).await;
    assert_eq!(err, Err(LlmError::Timeout(timeout)));
    assert_eq!(server.request_count(), 2);
    assert!(
        started.elapsed() < Duration::from_secs(2),
        "took {:?}",
        started.elapsed()
    );
}

#[tokio::test]
async fn unreachable_server_is_connect_after_retries() {
    let port = {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
        listener.local_addr().expect("addr").port()
    };
    let config = OpenAiConfig::new(format!("http://127.0.0.1:{port}/v1"), "m")
        .with_retries(1, Duration::from_millis(10));
    match backend(config).chat(&request()).await {
        Err(LlmError::Connect(message)) => {
            assert!(message.to_lowercase().contains("refused"), "{message}")
        }
        other => panic!("expected Connect, got {other:?}"),
    }
}

#[tokio::test]
async fn length_finish_is_truncated() {
    let mut body = openai_reply(r#"{"reasoning":"alfa is"#, "length");
    body["usage"]["completion_tokens"] = json!(512);
    let server = ReplayServer::start([Canned::json(200, body)]).await;
    let err = backend(config(&server)).chat(&request()).await;
    assert_eq!(err, Err(LlmError::Truncated(512)));
    assert_eq!(server.request_count(), 1);
}

/// llama.cpp's answer when the reply ran into the end of the context (n_ctx 512): `length` with
/// fewer tokens than the request's limit. Not "cut off at the token limit (512 tokens)".
#[tokio::test]
async fn length_finish_short_of_the_limit_is_a_full_context() {
    let mut body = openai_reply(r#"{"reasoning":"alfa is"#, "length");
    body["usage"] = json!({"completion_tokens": 26, "prompt_tokens": 486, "total_tokens": 512});
    let server = ReplayServer::start([Canned::json(200, body)]).await;
    let err = backend(config(&server)).chat(&request()).await;
    match err {
        Err(LlmError::Generation(message)) => {
            assert!(message.contains("context is full"), "{message}")
        }
        other => panic!("expected Generation, got {other:?}"),
    }
    assert_eq!(server.request_count(), 1);
}

#[tokio::test]
async fn refusal_is_refused() {
    let body = json!({
        "model": "gpt-4o", "object": "chat.completion",
        "choices": [{"index": 0, "finish_reason": "stop",
                     "message": {"role": "assistant", "content": null,
                                 "refusal": "I can't help with that."}}]
    });
    let server = ReplayServer::start([Canned::json(200, body)]).await;
    let err = backend(config(&server)).chat(&request()).await;
    assert_eq!(
        err,
        Err(LlmError::Refused("I can't help with that.".into()))
    );
}

#[tokio::test]
async fn non_json_body_is_bad_response() {
    let server = ReplayServer::start([Canned::text(200, "<html>proxy login</html>")]).await;
    match backend(config(&server)).chat(&request()).await {
        Err(LlmError::BadResponse(message)) => {
            assert!(
                message.contains("not JSON") && message.contains("proxy login"),
                "{message}"
            )
        }
        other => panic!("expected BadResponse, got {other:?}"),
    }
    assert_eq!(server.request_count(), 1, "a bad 2xx body is not retried");
}

#[tokio::test]
async fn missing_choices_or_content_is_bad_response() {
    let server = ReplayServer::start([
        Canned::json(200, json!({"object": "chat.completion", "choices": []})),
        Canned::json(200, json!({"error": {"message": "upstream exploded"}})),
        Canned::json(
            200,
            json!({"choices": [{"finish_reason": "stop",
                                              "message": {"role": "assistant", "content": null}}]}),
        ),
        Canned::json(200, json!({"choices": [{"finish_reason": "stop"}]})),
        Canned::json(200, json!({"choices": "many"})),
    ])
    .await;
    let backend = backend(config(&server));
    let mut messages = Vec::new();
    for _ in 0..5 {
        match backend.chat(&request()).await {
            Err(LlmError::BadResponse(message)) => messages.push(message),
            other => panic!("expected BadResponse, got {other:?}"),
        }
    }
    assert!(messages[0].contains("no choices"), "{}", messages[0]);
    assert!(messages[1].contains("upstream exploded"), "{}", messages[1]);
    assert!(messages[2].contains("no content"), "{}", messages[2]);
    assert!(messages[3].contains("no message"), "{}", messages[3]);
    assert!(
        messages[4].contains("not a chat completion"),
        "{}",
        messages[4]
    );
}

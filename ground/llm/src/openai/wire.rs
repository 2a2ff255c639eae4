//! What goes over the wire: the request and response bodies, and reading a failure.

use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::{OpenAiConfig, TokenLimitField};
use crate::{ChatMessage, ChatRequest, LlmError};

/// A failed attempt.
pub(super) struct Failure {
    pub(super) error: LlmError,
    pub(super) retryable: bool,
    /// The server's `Retry-After`, for retryable statuses.
    pub(super) retry_after: Option<Duration>,
}

impl Failure {
    pub(super) fn retry(error: LlmError) -> Self {
        Failure {
            error,
            retryable: true,
            retry_after: None,
        }
    }

    pub(super) fn from_reqwest(error: &reqwest::Error, timeout: Duration) -> Self {
        if error.is_timeout() {
            return Failure::retry(LlmError::Timeout(timeout));
        }
        let message = error_chain(error);
        // A request we could not even build, or a redirect loop, will not get better by trying
        // again; anything else (refused, reset, closed mid-body) may.
        let retryable = !(error.is_builder() || error.is_redirect());
        Failure {
            error: LlmError::Connect(message),
            retryable,
            retry_after: None,
        }
    }
}

/// `error: source: source…`: reqwest's own message hides the cause (e.g. "connection refused").
pub(super) fn error_chain(error: &dyn std::error::Error) -> String {
    let mut message = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        let text = cause.to_string();
        if !message.contains(&text) {
            message.push_str(": ");
            message.push_str(&text);
        }
        source = cause.source();
    }
    message
}

/// `Retry-After` in seconds. The HTTP-date form is not used by model servers and is ignored
/// (the ordinary backoff applies).
pub(super) fn retry_after(headers: &reqwest::header::HeaderMap) -> Option<Duration> {
    let value = headers.get(reqwest::header::RETRY_AFTER)?.to_str().ok()?;
    let secs: f64 = value.trim().parse().ok()?;
    Duration::try_from_secs_f64(secs).ok()
}

/// A readable message from an error body, whichever server shape it has:
/// OpenAI `{"error":{"message":…,"type":…}}`, llama.cpp `{"error":{"code":…,"message":…}}`,
/// Ollama `{"error":"…"}`, vLLM `{"object":"error","message":…}`, FastAPI `{"detail":…}`;
/// otherwise the body itself, shortened.
pub fn error_message(body: &[u8]) -> String {
    let parsed = serde_json::from_slice::<serde_json::Value>(body).ok();
    let found = parsed.as_ref().and_then(|value| {
        value
            .get("error")
            .and_then(error_value_message)
            .or_else(|| value.get("message").and_then(text_of))
            .or_else(|| value.get("detail").and_then(error_value_message))
    });
    match found {
        Some(message) => message,
        None if body.iter().all(u8::is_ascii_whitespace) => "(empty body)".into(),
        None => snippet(body),
    }
}

/// The message inside an `error` (or `detail`) value: a string, or an object with `message`
/// (or a list of such, as FastAPI validation errors are).
pub(super) fn error_value_message(value: &serde_json::Value) -> Option<String> {
    match value {
        serde_json::Value::String(text) if !text.trim().is_empty() => Some(text.clone()),
        serde_json::Value::Object(object) => object
            .get("message")
            .or_else(|| object.get("msg"))
            .and_then(text_of),
        serde_json::Value::Array(items) => {
            let parts: Vec<String> = items.iter().filter_map(error_value_message).collect();
            (!parts.is_empty()).then(|| parts.join("; "))
        }
        _ => None,
    }
}

/// Text from a string, or from an array of `{"type":"text","text":…}` parts.
pub(super) fn text_of(value: &serde_json::Value) -> Option<String> {
    match value {
        serde_json::Value::String(text) => Some(text.clone()),
        serde_json::Value::Array(parts) => {
            let texts: Vec<&str> = parts
                .iter()
                .filter_map(|part| part.get("text").and_then(serde_json::Value::as_str))
                .collect();
            (!texts.is_empty()).then(|| texts.concat())
        }
        _ => None,
    }
}

/// The start of a body for an error message.
pub(super) fn snippet(body: &[u8]) -> String {
    const MAX: usize = 300;
    let text = String::from_utf8_lossy(body);
    let text = text.trim();
    match text.char_indices().nth(MAX) {
        Some((cut, _)) => format!("{}… ({} bytes)", &text[..cut], body.len()),
        None if text.is_empty() => "(empty body)".into(),
        None => text.to_string(),
    }
}

/// The error for a reply that ended with `finish_reason: "length"`.
///
/// When the reply used the request's whole limit, it was cut at that limit:
/// [`LlmError::Truncated`], which a caller may answer by asking for a shorter reply. When it
/// stopped short of the limit, something else ended it: the server's context filled up (llama.cpp
/// and vLLM report that as `length` too, with the prompt and the reply filling the context) or the
/// server caps replies below the request's limit. Asking for a shorter answer with a longer prompt
/// cannot help then, and "cut off at the token limit (N tokens)" would send the pilot after the
/// wrong number, so it is a [`LlmError::Generation`] that says what happened.
pub(super) fn cut_off(max_tokens: u32, usage: &WireUsage) -> LlmError {
    match usage.completion_tokens {
        Some(reply) if reply < u64::from(max_tokens) => {
            let prompt = usage.prompt_tokens.unwrap_or(0);
            LlmError::Generation(format!(
                "the server cut the reply off at {reply} tokens, short of the request's limit of \
                 {max_tokens}: its context is full (prompt {prompt} + reply {reply} = {} tokens; \
                 give the server a larger context or shorten the prompt) or it caps replies lower",
                prompt.saturating_add(reply)
            ))
        }
        _ => LlmError::Truncated(max_tokens),
    }
}

pub(super) fn saturate(tokens: Option<u64>) -> u32 {
    tokens.map_or(0, |t| u32::try_from(t).unwrap_or(u32::MAX))
}

#[derive(Serialize)]
pub(super) struct WireRequest<'a> {
    pub(super) model: &'a str,
    pub(super) messages: &'a [ChatMessage],
    pub(super) temperature: f32,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) max_tokens: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) max_completion_tokens: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) seed: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) reasoning_effort: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) response_format: Option<WireResponseFormat<'a>>,
    pub(super) stream: bool,
    /// With `stream`: ask for the token counts in the last chunk.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) stream_options: Option<WireStreamOptions>,
}

#[derive(Serialize)]
pub(super) struct WireStreamOptions {
    pub(super) include_usage: bool,
}

impl<'a> WireRequest<'a> {
    pub(super) fn new(config: &'a OpenAiConfig, request: &'a ChatRequest) -> Self {
        let (max_tokens, max_completion_tokens) = match config.token_limit_field {
            TokenLimitField::MaxTokens => (Some(request.max_tokens), None),
            TokenLimitField::MaxCompletionTokens => (None, Some(request.max_tokens)),
        };
        WireRequest {
            model: &config.model,
            messages: &request.messages,
            temperature: request.temperature,
            max_tokens,
            max_completion_tokens,
            seed: request.seed,
            reasoning_effort: request.reasoning_effort.as_deref(),
            response_format: request.schema.as_ref().map(|schema| WireResponseFormat {
                kind: "json_schema",
                json_schema: WireJsonSchema {
                    name: &schema.name,
                    schema: &schema.schema,
                    strict: true,
                },
            }),
            stream: false,
            stream_options: None,
        }
    }

    /// The same request, streamed (`stream: true`, the usage in the last chunk).
    pub(super) fn streamed(self) -> Self {
        WireRequest {
            stream: true,
            stream_options: Some(WireStreamOptions {
                include_usage: true,
            }),
            ..self
        }
    }
}

#[derive(Serialize)]
pub(super) struct WireResponseFormat<'a> {
    #[serde(rename = "type")]
    pub(super) kind: &'static str,
    pub(super) json_schema: WireJsonSchema<'a>,
}

#[derive(Serialize)]
pub(super) struct WireJsonSchema<'a> {
    pub(super) name: &'a str,
    pub(super) schema: &'a serde_json::Value,
    pub(super) strict: bool,
}

/// Only what we read; every field optional so each server's shape gets a precise error.
#[derive(Deserialize)]
pub(super) struct WireResponse {
    #[serde(default)]
    pub(super) choices: Option<Vec<WireChoice>>,
    #[serde(default)]
    pub(super) usage: Option<WireUsage>,
    #[serde(default)]
    pub(super) model: Option<String>,
    #[serde(default)]
    pub(super) error: Option<serde_json::Value>,
}

#[derive(Deserialize)]
pub(super) struct WireChoice {
    #[serde(default)]
    pub(super) message: Option<WireMessage>,
    #[serde(default)]
    pub(super) finish_reason: Option<String>,
}

/// Text fields are kept as JSON values: servers disagree on their types (a string, parts, null).
#[derive(Deserialize)]
pub(super) struct WireMessage {
    #[serde(default)]
    pub(super) content: Option<serde_json::Value>,
    #[serde(default)]
    pub(super) refusal: Option<serde_json::Value>,
    #[serde(default)]
    pub(super) reasoning: Option<serde_json::Value>,
    #[serde(default)]
    pub(super) reasoning_content: Option<serde_json::Value>,
    #[serde(default)]
    pub(super) thinking: Option<serde_json::Value>,
}

#[derive(Deserialize, Default)]
pub(super) struct WireUsage {
    #[serde(default)]
    pub(super) prompt_tokens: Option<u64>,
    #[serde(default)]
    pub(super) completion_tokens: Option<u64>,
}

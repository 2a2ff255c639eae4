//! Any OpenAI-compatible chat-completions server over HTTP: Ollama, vLLM, llama.cpp's server, or a
//! cloud API (with the `rustls` feature for `https`).
//!
//! One request is `POST {base_url}/chat/completions` with:
//!
//! - `model`, `messages`, `temperature`, `stream: false`;
//! - the token limit as `max_tokens` by default. Ollama's, vLLM's and llama.cpp's OpenAI endpoints
//!   all read `max_tokens`; OpenAI's own reasoning models (o-series, gpt-5) refuse it and want
//!   `max_completion_tokens`, which vLLM also reads but older Ollama builds ignore. Pick with
//!   [`OpenAiConfig::token_limit_field`];
//! - `seed` and `reasoning_effort` when the request has them;
//! - `response_format: {type: "json_schema", json_schema: {name, schema, strict: true}}` when the
//!   request has a schema.
//!
//! Each attempt has its own timeout ([`OpenAiConfig::timeout`], covering connect, headers and
//! body). HTTP 429, 408 and 5xx, timeouts and connection failures are retried up to
//! [`OpenAiConfig::max_retries`] times with exponential backoff and jitter, or after the server's
//! `Retry-After` (in seconds) when it sends one; a `Retry-After` longer than
//! [`OpenAiConfig::max_backoff`] ends the call at once (a drone mission does not wait minutes for
//! a rate limit). Other 4xx are not retried. A 2xx reply that does not parse is not retried either.
//! A prompt longer than the server's context is a 400 (llama.cpp: "request (N tokens) exceeds the
//! available context size (M tokens), try increasing it"), so [`LlmError::Http`] in the server's
//! words, at once.
//!
//! `finish_reason: "length"` is [`LlmError::Truncated`] when the reply used the request's whole
//! token limit; short of it (the server's context filled up during the reply, as llama.cpp and vLLM
//! report it) it is [`LlmError::Generation`], saying so.
//!
//! The chain of thought is read from whichever of `message.reasoning` (OpenAI-style, Ollama ≥ 0.12
//! for gpt-oss), `message.reasoning_content` (vLLM, llama.cpp with `--reasoning-format`) or
//! `message.thinking` (Ollama) the server fills, plus a `<think>…</think>` block at the start of the
//! content (llama.cpp without a reasoning parser), which is stripped off the answer. It is
//! returned in [`ChatReply::reasoning`] and logged at debug level, never acted on.
//!
//! [`ChatReply::latency`] is the whole call as the caller waited for it, retries included; the
//! model name is the one the server reports (falling back to the configured one).

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::{BoxFuture, ChatMessage, ChatReply, ChatRequest, LlmBackend, LlmError, Usage};

/// Base URL of the server, up to and including `/v1` (e.g. `http://127.0.0.1:8000/v1`).
pub const ENV_URL: &str = "TACOS_LLM_URL";
/// The model name the server knows (e.g. `gpt-oss:20b`).
pub const ENV_MODEL: &str = "TACOS_LLM_MODEL";
/// Bearer token; when unset or empty, [`ENV_OPENAI_API_KEY`] is used.
pub const ENV_API_KEY: &str = "TACOS_LLM_API_KEY";
pub const ENV_OPENAI_API_KEY: &str = "OPENAI_API_KEY";
/// Optional: per-attempt timeout in seconds (decimals allowed).
pub const ENV_TIMEOUT: &str = "TACOS_LLM_TIMEOUT_SECS";
/// Optional: how many times a failed attempt is retried.
pub const ENV_MAX_RETRIES: &str = "TACOS_LLM_MAX_RETRIES";

/// Ollama's OpenAI-compatible endpoint on this machine: the URL used when `TACOS_LLM_URL` is unset.
pub const DEFAULT_BASE_URL: &str = "http://127.0.0.1:11434/v1";
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(120);
pub const DEFAULT_MAX_RETRIES: u32 = 2;
pub const DEFAULT_INITIAL_BACKOFF: Duration = Duration::from_millis(500);
pub const DEFAULT_MAX_BACKOFF: Duration = Duration::from_secs(30);

/// The request field that carries [`ChatRequest::max_tokens`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TokenLimitField {
    /// `max_tokens`: read by Ollama, vLLM, llama.cpp and OpenAI's non-reasoning models.
    #[default]
    MaxTokens,
    /// `max_completion_tokens`: required by OpenAI's reasoning models; read by vLLM.
    MaxCompletionTokens,
}

/// How to reach an OpenAI-compatible server.
///
/// In a file (TOML, JSON…), durations are seconds (`timeout = 90`, `initial_backoff = 0.25`);
/// only `base_url` and `model` are required, and unknown keys are an error.
#[derive(Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpenAiConfig {
    /// Up to and including the API version, e.g. `http://127.0.0.1:11434/v1`.
    pub base_url: String,
    pub model: String,
    /// Sent as `Authorization: Bearer …` when set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub api_key: Option<String>,
    /// Per attempt: connect, send, and read the whole reply.
    #[serde(default = "default_timeout", with = "seconds")]
    pub timeout: Duration,
    /// Retries after the first attempt (0 = try once).
    #[serde(default = "default_max_retries")]
    pub max_retries: u32,
    /// The first backoff; it doubles on each retry, with jitter, up to `max_backoff`.
    #[serde(default = "default_initial_backoff", with = "seconds")]
    pub initial_backoff: Duration,
    /// The longest wait between attempts; a longer `Retry-After` ends the call.
    #[serde(default = "default_max_backoff", with = "seconds")]
    pub max_backoff: Duration,
    #[serde(default)]
    pub token_limit_field: TokenLimitField,
}

fn default_timeout() -> Duration {
    DEFAULT_TIMEOUT
}
fn default_max_retries() -> u32 {
    DEFAULT_MAX_RETRIES
}
fn default_initial_backoff() -> Duration {
    DEFAULT_INITIAL_BACKOFF
}
fn default_max_backoff() -> Duration {
    DEFAULT_MAX_BACKOFF
}

/// The API key never reaches a log.
impl fmt::Debug for OpenAiConfig {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("OpenAiConfig")
            .field("base_url", &self.base_url)
            .field("model", &self.model)
            .field("api_key", &self.api_key.as_ref().map(|_| "<redacted>"))
            .field("timeout", &self.timeout)
            .field("max_retries", &self.max_retries)
            .field("initial_backoff", &self.initial_backoff)
            .field("max_backoff", &self.max_backoff)
            .field("token_limit_field", &self.token_limit_field)
            .finish()
    }
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConfigError {
    #[error("{0} is not set")]
    Missing(&'static str),
    #[error("{name}={value:?}: {reason}")]
    Invalid {
        name: &'static str,
        value: String,
        reason: String,
    },
    #[error("base URL {url:?}: {reason}")]
    BadUrl { url: String, reason: String },
    #[error(
        "base URL {0:?} needs TLS, which this build leaves out: build tacos-llm with its `rustls` feature"
    )]
    TlsDisabled(String),
    #[error("cannot build the HTTP client: {0}")]
    Client(String),
}

impl OpenAiConfig {
    /// A server and model, with the default timeout, retries and backoff and no API key.
    pub fn new(base_url: impl Into<String>, model: impl Into<String>) -> Self {
        OpenAiConfig {
            base_url: base_url.into(),
            model: model.into(),
            api_key: None,
            timeout: DEFAULT_TIMEOUT,
            max_retries: DEFAULT_MAX_RETRIES,
            initial_backoff: DEFAULT_INITIAL_BACKOFF,
            max_backoff: DEFAULT_MAX_BACKOFF,
            token_limit_field: TokenLimitField::MaxTokens,
        }
    }

    pub fn with_api_key(mut self, key: impl Into<String>) -> Self {
        self.api_key = Some(key.into());
        self
    }

    pub fn with_timeout(mut self, timeout: Duration) -> Self {
        self.timeout = timeout;
        self
    }

    pub fn with_retries(mut self, max_retries: u32, initial_backoff: Duration) -> Self {
        self.max_retries = max_retries;
        self.initial_backoff = initial_backoff;
        self
    }

    /// From the process environment: `TACOS_LLM_URL` (default [`DEFAULT_BASE_URL`]),
    /// `TACOS_LLM_MODEL` (required), `TACOS_LLM_API_KEY` or else `OPENAI_API_KEY`, and optionally
    /// `TACOS_LLM_TIMEOUT_SECS` and `TACOS_LLM_MAX_RETRIES`. Empty values count as unset.
    pub fn from_env() -> Result<Self, ConfigError> {
        Self::from_lookup(|name| std::env::var(name).ok())
    }

    /// [`Self::from_env`] with another source of variables (tests, a config layer).
    pub fn from_lookup(lookup: impl Fn(&str) -> Option<String>) -> Result<Self, ConfigError> {
        let get = |name: &str| {
            lookup(name)
                .map(|v| v.trim().to_string())
                .filter(|v| !v.is_empty())
        };
        let model = get(ENV_MODEL).ok_or(ConfigError::Missing(ENV_MODEL))?;
        let base_url = get(ENV_URL).unwrap_or_else(|| DEFAULT_BASE_URL.to_string());
        let mut config = OpenAiConfig::new(base_url, model);
        config.api_key = get(ENV_API_KEY).or_else(|| get(ENV_OPENAI_API_KEY));
        if let Some(value) = get(ENV_TIMEOUT) {
            config.timeout = parse_seconds(&value).map_err(|reason| ConfigError::Invalid {
                name: ENV_TIMEOUT,
                value: value.clone(),
                reason,
            })?;
        }
        if let Some(value) = get(ENV_MAX_RETRIES) {
            config.max_retries = value.parse().map_err(|e| ConfigError::Invalid {
                name: ENV_MAX_RETRIES,
                value: value.clone(),
                reason: format!("{e}"),
            })?;
        }
        Ok(config)
    }

    /// `{base_url}/chat/completions`, checked.
    fn endpoint(&self) -> Result<reqwest::Url, ConfigError> {
        let bad = |reason: String| ConfigError::BadUrl {
            url: self.base_url.clone(),
            reason,
        };
        let joined = format!(
            "{}/chat/completions",
            self.base_url.trim().trim_end_matches('/')
        );
        let url = reqwest::Url::parse(&joined).map_err(|e| bad(e.to_string()))?;
        match url.scheme() {
            "http" => {}
            "https" if cfg!(feature = "rustls") => {}
            "https" => return Err(ConfigError::TlsDisabled(self.base_url.clone())),
            other => return Err(bad(format!("scheme {other:?} is not http or https"))),
        }
        if url.host_str().is_none_or(str::is_empty) {
            return Err(bad("no host".into()));
        }
        Ok(url)
    }
}

fn parse_seconds(text: &str) -> Result<Duration, String> {
    let secs: f64 = text
        .trim()
        .parse()
        .map_err(|e| format!("not a number of seconds: {e}"))?;
    Duration::try_from_secs_f64(secs).map_err(|e| format!("not a duration: {e}"))
}

/// Durations in config files: seconds, integer or decimal.
mod seconds {
    use std::time::Duration;

    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(value: &Duration, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_f64(value.as_secs_f64())
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Duration, D::Error> {
        let secs = f64::deserialize(deserializer)?;
        Duration::try_from_secs_f64(secs)
            .map_err(|e| serde::de::Error::custom(format!("{secs} s is not a duration: {e}")))
    }
}

/// An OpenAI-compatible server. Cheap to share (`Arc`); requests may run concurrently.
pub struct OpenAiBackend {
    config: OpenAiConfig,
    endpoint: reqwest::Url,
    client: reqwest::Client,
    /// State of the jitter generator (splitmix64): deterministic, no `rand`.
    jitter: AtomicU64,
}

impl fmt::Debug for OpenAiBackend {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("OpenAiBackend")
            .field("config", &self.config)
            .field("endpoint", &self.endpoint.as_str())
            .finish_non_exhaustive()
    }
}

impl OpenAiBackend {
    pub fn new(config: OpenAiConfig) -> Result<Self, ConfigError> {
        let endpoint = config.endpoint()?;
        if config.timeout.is_zero() {
            return Err(ConfigError::Invalid {
                name: "timeout",
                value: "0".into(),
                reason: "must be positive".into(),
            });
        }
        let client = reqwest::Client::builder()
            .user_agent(concat!("tacos-llm/", env!("CARGO_PKG_VERSION")))
            .connect_timeout(config.timeout)
            .build()
            .map_err(|e| ConfigError::Client(error_chain(&e)))?;
        Ok(OpenAiBackend {
            config,
            endpoint,
            client,
            jitter: AtomicU64::new(0x7AC0_5EED),
        })
    }

    /// [`OpenAiConfig::from_env`], then [`Self::new`].
    pub fn from_env() -> Result<Self, ConfigError> {
        Self::new(OpenAiConfig::from_env()?)
    }

    pub fn config(&self) -> &OpenAiConfig {
        &self.config
    }

    /// The URL every request is posted to.
    pub fn endpoint(&self) -> &str {
        self.endpoint.as_str()
    }

    async fn chat_with_retries(&self, request: &ChatRequest) -> Result<ChatReply, LlmError> {
        let wire = WireRequest::new(&self.config, request);
        let started = Instant::now();
        let mut attempt: u32 = 0;
        loop {
            attempt = attempt.saturating_add(1);
            let failure = match self.attempt(&wire).await {
                Ok(body) => return self.parse_reply(&body, request, started.elapsed()),
                Err(failure) => failure,
            };
            if !failure.retryable || attempt > self.config.max_retries {
                tracing::warn!(attempt, error = %failure.error, "model request failed");
                return Err(failure.error);
            }
            let wait = match failure.retry_after {
                Some(wait) if wait > self.config.max_backoff => {
                    tracing::warn!(?wait, error = %failure.error, "model server asks to wait longer than max_backoff; giving up");
                    return Err(failure.error);
                }
                Some(wait) => wait,
                None => self.backoff(attempt),
            };
            tracing::warn!(attempt, ?wait, error = %failure.error, "model request failed; retrying");
            tokio::time::sleep(wait).await;
        }
    }

    /// One HTTP exchange: the body of a 2xx reply, or what went wrong and whether to retry.
    async fn attempt(&self, wire: &WireRequest<'_>) -> Result<Vec<u8>, Failure> {
        let mut builder = self.client.post(self.endpoint.clone()).json(wire);
        if let Some(key) = &self.config.api_key {
            builder = builder.bearer_auth(key);
        }
        let exchange = async {
            let response = builder.send().await?;
            let status = response.status();
            let retry_after = retry_after(response.headers());
            let body = response.bytes().await?;
            Ok::<_, reqwest::Error>((status, retry_after, body))
        };
        let (status, retry_after, body) = match tokio::time::timeout(self.config.timeout, exchange)
            .await
        {
            Err(_elapsed) => return Err(Failure::retry(LlmError::Timeout(self.config.timeout))),
            Ok(Err(e)) => return Err(Failure::from_reqwest(&e, self.config.timeout)),
            Ok(Ok(exchange)) => exchange,
        };
        if status.is_success() {
            return Ok(body.to_vec());
        }
        let code = status.as_u16();
        let error = LlmError::Http {
            status: code,
            body: error_message(&body),
        };
        if code == 429 || code == 408 || status.is_server_error() {
            Err(Failure {
                error,
                retryable: true,
                retry_after,
            })
        } else {
            Err(Failure {
                error,
                retryable: false,
                retry_after: None,
            })
        }
    }

    /// Exponential backoff before retry number `attempt` (1-based), with "equal jitter": a
    /// uniform wait in [base/2, base].
    fn backoff(&self, attempt: u32) -> Duration {
        let doublings = attempt.saturating_sub(1).min(30);
        let base = self
            .config
            .initial_backoff
            .checked_mul(1u32 << doublings)
            .unwrap_or(self.config.max_backoff)
            .min(self.config.max_backoff);
        let unit = self.next_jitter();
        base / 2 + base.mul_f64(unit / 2.0)
    }

    /// A number in [0, 1) from splitmix64.
    fn next_jitter(&self) -> f64 {
        const GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut z = self
            .jitter
            .fetch_add(GAMMA, Ordering::Relaxed)
            .wrapping_add(GAMMA);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }

    fn parse_reply(
        &self,
        body: &[u8],
        request: &ChatRequest,
        latency: Duration,
    ) -> Result<ChatReply, LlmError> {
        let value: serde_json::Value = serde_json::from_slice(body).map_err(|e| {
            LlmError::BadResponse(format!("the body is not JSON ({e}): {}", snippet(body)))
        })?;
        let wire: WireResponse = serde_json::from_value(value).map_err(|e| {
            LlmError::BadResponse(format!("not a chat completion ({e}): {}", snippet(body)))
        })?;
        let Some(choice) = wire.choices.unwrap_or_default().into_iter().next() else {
            return Err(LlmError::BadResponse(
                match wire.error.as_ref().and_then(error_value_message) {
                    Some(message) => format!("no choices; the server reported: {message}"),
                    None => format!("no choices in the reply: {}", snippet(body)),
                },
            ));
        };
        let Some(message) = choice.message else {
            return Err(LlmError::BadResponse(
                "the first choice has no message".into(),
            ));
        };

        let mut reasoning = [
            &message.reasoning,
            &message.reasoning_content,
            &message.thinking,
        ]
        .into_iter()
        .filter_map(|field| field.as_ref().and_then(text_of))
        .find(|text| !text.trim().is_empty());
        let content = message.content.as_ref().and_then(text_of);
        let answer = match content {
            Some(content) => {
                let (thought, answer) = crate::split_think_tags(&content);
                if let Some(thought) = thought {
                    reasoning = Some(match reasoning {
                        Some(field) => format!("{field}\n{thought}"),
                        None => thought,
                    });
                }
                answer
            }
            None => String::new(),
        };
        let model = wire
            .model
            .filter(|m| !m.is_empty())
            .unwrap_or_else(|| self.config.model.clone());
        if let Some(reasoning) = &reasoning {
            tracing::debug!(%model, reasoning = %reasoning, "model chain of thought (logged, not acted on)");
        }

        if let Some(refusal) = message
            .refusal
            .as_ref()
            .and_then(text_of)
            .filter(|r| !r.trim().is_empty())
        {
            return Err(LlmError::Refused(refusal));
        }
        let usage = wire.usage.unwrap_or_default();
        match choice.finish_reason.as_deref() {
            Some("length") => return Err(cut_off(request.max_tokens, &usage)),
            Some("content_filter") => {
                return Err(LlmError::Refused(
                    "stopped by the server's content filter".into(),
                ));
            }
            _ => {}
        }
        if answer.trim().is_empty() {
            return Err(LlmError::BadResponse(match message.content {
                None | Some(serde_json::Value::Null) => "the reply has no content".into(),
                Some(_) => "the reply's content is empty".into(),
            }));
        }

        Ok(ChatReply {
            content: answer,
            reasoning,
            usage: Usage {
                prompt_tokens: saturate(usage.prompt_tokens),
                completion_tokens: saturate(usage.completion_tokens),
            },
            latency,
            model,
        })
    }
}

impl LlmBackend for OpenAiBackend {
    fn chat<'a>(&'a self, request: &'a ChatRequest) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        Box::pin(self.chat_with_retries(request))
    }

    fn describe(&self) -> String {
        format!(
            "openai {} {}",
            self.config.base_url.trim_end_matches('/'),
            self.config.model
        )
    }
}

/// A failed attempt.
struct Failure {
    error: LlmError,
    retryable: bool,
    /// The server's `Retry-After`, for retryable statuses.
    retry_after: Option<Duration>,
}

impl Failure {
    fn retry(error: LlmError) -> Self {
        Failure {
            error,
            retryable: true,
            retry_after: None,
        }
    }

    fn from_reqwest(error: &reqwest::Error, timeout: Duration) -> Self {
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
fn error_chain(error: &dyn std::error::Error) -> String {
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
fn retry_after(headers: &reqwest::header::HeaderMap) -> Option<Duration> {
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
fn error_value_message(value: &serde_json::Value) -> Option<String> {
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
fn text_of(value: &serde_json::Value) -> Option<String> {
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
fn snippet(body: &[u8]) -> String {
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
fn cut_off(max_tokens: u32, usage: &WireUsage) -> LlmError {
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

fn saturate(tokens: Option<u64>) -> u32 {
    tokens.map_or(0, |t| u32::try_from(t).unwrap_or(u32::MAX))
}

#[derive(Serialize)]
struct WireRequest<'a> {
    model: &'a str,
    messages: &'a [ChatMessage],
    temperature: f32,
    #[serde(skip_serializing_if = "Option::is_none")]
    max_tokens: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    max_completion_tokens: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    seed: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    reasoning_effort: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    response_format: Option<WireResponseFormat<'a>>,
    stream: bool,
}

impl<'a> WireRequest<'a> {
    fn new(config: &'a OpenAiConfig, request: &'a ChatRequest) -> Self {
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
        }
    }
}

#[derive(Serialize)]
struct WireResponseFormat<'a> {
    #[serde(rename = "type")]
    kind: &'static str,
    json_schema: WireJsonSchema<'a>,
}

#[derive(Serialize)]
struct WireJsonSchema<'a> {
    name: &'a str,
    schema: &'a serde_json::Value,
    strict: bool,
}

/// Only what we read; every field optional so each server's shape gets a precise error.
#[derive(Deserialize)]
struct WireResponse {
    #[serde(default)]
    choices: Option<Vec<WireChoice>>,
    #[serde(default)]
    usage: Option<WireUsage>,
    #[serde(default)]
    model: Option<String>,
    #[serde(default)]
    error: Option<serde_json::Value>,
}

#[derive(Deserialize)]
struct WireChoice {
    #[serde(default)]
    message: Option<WireMessage>,
    #[serde(default)]
    finish_reason: Option<String>,
}

/// Text fields are kept as JSON values: servers disagree on their types (a string, parts, null).
#[derive(Deserialize)]
struct WireMessage {
    #[serde(default)]
    content: Option<serde_json::Value>,
    #[serde(default)]
    refusal: Option<serde_json::Value>,
    #[serde(default)]
    reasoning: Option<serde_json::Value>,
    #[serde(default)]
    reasoning_content: Option<serde_json::Value>,
    #[serde(default)]
    thinking: Option<serde_json::Value>,
}

#[derive(Deserialize, Default)]
struct WireUsage {
    #[serde(default)]
    prompt_tokens: Option<u64>,
    #[serde(default)]
    completion_tokens: Option<u64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lookup<'a>(vars: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |name| {
            vars.iter()
                .find(|(k, _)| *k == name)
                .map(|(_, v)| v.to_string())
        }
    }

    #[test]
    fn config_from_env_with_defaults() {
        let config = OpenAiConfig::from_lookup(lookup(&[("TACOS_LLM_MODEL", "gpt-oss:20b")]))
            .expect("config");
        assert_eq!(config.base_url, DEFAULT_BASE_URL);
        assert_eq!(config.model, "gpt-oss:20b");
        assert_eq!(config.api_key, None);
        assert_eq!(config.timeout, DEFAULT_TIMEOUT);
        assert_eq!(config.max_retries, DEFAULT_MAX_RETRIES);
    }

    #[test]
    fn config_from_env_reads_everything() {
        let config = OpenAiConfig::from_lookup(lookup(&[
            ("TACOS_LLM_MODEL", "qwen3"),
            ("TACOS_LLM_URL", "http://gpu:8000/v1/"),
            ("TACOS_LLM_API_KEY", " "),
            ("OPENAI_API_KEY", "sk-fallback"),
            ("TACOS_LLM_TIMEOUT_SECS", "2.5"),
            ("TACOS_LLM_MAX_RETRIES", "0"),
        ]))
        .expect("config");
        assert_eq!(config.base_url, "http://gpu:8000/v1/");
        assert_eq!(config.api_key.as_deref(), Some("sk-fallback"));
        assert_eq!(config.timeout, Duration::from_millis(2500));
        assert_eq!(config.max_retries, 0);
        let backend = OpenAiBackend::new(config).expect("backend");
        assert_eq!(backend.endpoint(), "http://gpu:8000/v1/chat/completions");
        assert_eq!(backend.describe(), "openai http://gpu:8000/v1 qwen3");

        let own_key = OpenAiConfig::from_lookup(lookup(&[
            ("TACOS_LLM_MODEL", "m"),
            ("TACOS_LLM_API_KEY", "tacos-key"),
            ("OPENAI_API_KEY", "sk-fallback"),
        ]))
        .expect("config");
        assert_eq!(own_key.api_key.as_deref(), Some("tacos-key"));
    }

    #[test]
    fn config_from_env_errors() {
        assert_eq!(
            OpenAiConfig::from_lookup(lookup(&[])),
            Err(ConfigError::Missing("TACOS_LLM_MODEL"))
        );
        let err = OpenAiConfig::from_lookup(lookup(&[
            ("TACOS_LLM_MODEL", "m"),
            ("TACOS_LLM_TIMEOUT_SECS", "-1"),
        ]));
        assert!(matches!(
            err,
            Err(ConfigError::Invalid {
                name: "TACOS_LLM_TIMEOUT_SECS",
                ..
            })
        ));
        let err = OpenAiConfig::from_lookup(lookup(&[
            ("TACOS_LLM_MODEL", "m"),
            ("TACOS_LLM_MAX_RETRIES", "x"),
        ]));
        assert!(matches!(
            err,
            Err(ConfigError::Invalid {
                name: "TACOS_LLM_MAX_RETRIES",
                ..
            })
        ));
    }

    #[test]
    fn bad_urls_are_refused_when_built() {
        for url in ["not a url", "ftp://host/v1", "file:///tmp"] {
            let err = OpenAiBackend::new(OpenAiConfig::new(url, "m")).map(|_| ());
            assert!(
                matches!(err, Err(ConfigError::BadUrl { .. })),
                "{url}: {err:?}"
            );
        }
        let https = OpenAiBackend::new(OpenAiConfig::new("https://api.openai.com/v1", "m"));
        if cfg!(feature = "rustls") {
            assert!(https.is_ok());
        } else {
            assert!(matches!(https, Err(ConfigError::TlsDisabled(_))));
        }
        let zero = OpenAiConfig::new("http://127.0.0.1:1/v1", "m").with_timeout(Duration::ZERO);
        assert!(matches!(
            OpenAiBackend::new(zero),
            Err(ConfigError::Invalid { .. })
        ));
    }

    #[test]
    fn config_file_uses_seconds_and_rejects_unknown_keys() {
        let config: OpenAiConfig = serde_json::from_str(
            r#"{"base_url":"http://127.0.0.1:8080/v1","model":"m","timeout":90,"initial_backoff":0.25,
                "token_limit_field":"max_completion_tokens"}"#,
        )
        .expect("config");
        assert_eq!(config.timeout, Duration::from_secs(90));
        assert_eq!(config.initial_backoff, Duration::from_millis(250));
        assert_eq!(config.max_retries, DEFAULT_MAX_RETRIES);
        assert_eq!(
            config.token_limit_field,
            TokenLimitField::MaxCompletionTokens
        );
        let round: OpenAiConfig =
            serde_json::from_str(&serde_json::to_string(&config).expect("ser")).expect("de");
        assert_eq!(round, config);

        let unknown =
            serde_json::from_str::<OpenAiConfig>(r#"{"base_url":"u","model":"m","timout":3}"#);
        assert!(unknown.is_err_and(|e| e.to_string().contains("unknown field")));
        let negative =
            serde_json::from_str::<OpenAiConfig>(r#"{"base_url":"u","model":"m","timeout":-3}"#);
        assert!(negative.is_err());
    }

    #[test]
    fn debug_hides_the_api_key() {
        let config = OpenAiConfig::new("http://h/v1", "m").with_api_key("sk-secret");
        let text = format!("{config:?}");
        assert!(!text.contains("sk-secret"), "{text}");
        assert!(text.contains("redacted"));
    }

    #[test]
    fn error_bodies_of_every_server_shape() {
        let cases: [(&str, &str); 7] = [
            (
                r#"{"error":{"message":"Rate limit reached","type":"requests","param":null,"code":"rate_limit_exceeded"}}"#,
                "Rate limit reached",
            ),
            (
                r#"{"error":"model \"llama9\" not found, try pulling it first"}"#,
                "model \"llama9\" not found, try pulling it first",
            ),
            (
                r#"{"object":"error","message":"This model's maximum context length is 8192 tokens","type":"BadRequestError","param":null,"code":400}"#,
                "This model's maximum context length is 8192 tokens",
            ),
            (
                r#"{"error":{"code":400,"message":"the request exceeds the available context size","type":"invalid_request_error"}}"#,
                "the request exceeds the available context size",
            ),
            (
                r#"{"detail":[{"loc":["body","messages"],"msg":"field required"}]}"#,
                "field required",
            ),
            (
                "<html>502 Bad Gateway</html>",
                "<html>502 Bad Gateway</html>",
            ),
            ("  ", "(empty body)"),
        ];
        for (body, expected) in cases {
            assert_eq!(error_message(body.as_bytes()), expected, "{body}");
        }
        let long = "x".repeat(1000);
        let short = error_message(long.as_bytes());
        assert!(
            short.len() < 400 && short.ends_with("(1000 bytes)"),
            "{short}"
        );
    }

    #[test]
    fn backoff_doubles_with_jitter_and_caps() {
        let config =
            OpenAiConfig::new("http://h/v1", "m").with_retries(10, Duration::from_millis(100));
        let backend = OpenAiBackend::new(config).expect("backend");
        for attempt in 1..=12 {
            let base = Duration::from_millis(100)
                .saturating_mul(1 << (attempt - 1))
                .min(DEFAULT_MAX_BACKOFF);
            let wait = backend.backoff(attempt);
            assert!(
                wait >= base / 2 && wait <= base,
                "attempt {attempt}: {wait:?} vs {base:?}"
            );
        }
        assert!(backend.backoff(u32::MAX) <= DEFAULT_MAX_BACKOFF);
        let samples: Vec<f64> = (0..100).map(|_| backend.next_jitter()).collect();
        assert!(samples.iter().all(|u| (0.0..1.0).contains(u)));
        assert!(samples.windows(2).any(|w| w[0] != w[1]));
    }

    #[test]
    fn a_length_finish_short_of_the_limit_is_a_full_context_not_the_token_limit() {
        let usage = |prompt, reply| WireUsage {
            prompt_tokens: Some(prompt),
            completion_tokens: Some(reply),
        };
        // The limit reached: truncated at it (what llama.cpp answers with max_tokens 5).
        assert_eq!(cut_off(5, &usage(36, 5)), LlmError::Truncated(5));
        // No usage: nothing says otherwise.
        assert_eq!(
            cut_off(400, &WireUsage::default()),
            LlmError::Truncated(400)
        );
        // llama.cpp with n_ctx 512, a 486-token prompt and max_tokens 400: 26 tokens, "length".
        match cut_off(400, &usage(486, 26)) {
            LlmError::Generation(message) => {
                for part in [
                    "26 tokens",
                    "limit of 400",
                    "context is full",
                    "486 + reply 26 = 512",
                ] {
                    assert!(message.contains(part), "{part:?} not in {message}");
                }
            }
            other => panic!("expected Generation, got {other:?}"),
        }
    }

    #[test]
    fn retry_after_seconds() {
        let mut headers = reqwest::header::HeaderMap::new();
        assert_eq!(retry_after(&headers), None);
        headers.insert(
            reqwest::header::RETRY_AFTER,
            reqwest::header::HeaderValue::from_static("2"),
        );
        assert_eq!(retry_after(&headers), Some(Duration::from_secs(2)));
        headers.insert(
            reqwest::header::RETRY_AFTER,
            reqwest::header::HeaderValue::from_static("Wed, 21 Oct 2015 07:28:00 GMT"),
        );
        assert_eq!(retry_after(&headers), None);
    }
}

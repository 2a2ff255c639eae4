//! Any OpenAI-compatible chat-completions server over HTTP: Ollama, vLLM, llama.cpp's server, or a
//! cloud API (with the `rustls` feature for `https`).
//!
//! One request is `POST {base_url}/chat/completions` with:
//!
//! - `model`, `messages`, `temperature`, `stream: false` (`true` for
//!   [`LlmBackend::chat_streamed`]: server-sent events assembled by [`SseAssembler`] into the same
//!   reply, so one parser judges both);
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

use crate::{BoxFuture, ChatReply, ChatRequest, LlmBackend, LlmError, Progress, Streamed, Usage};

mod config;
mod stream;
mod wire;

pub use stream::SseAssembler;

pub use config::*;
use wire::*;

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
            // A connection per call: calls are seconds apart and seconds long, and llama.cpp's
            // server closes a connection after a streamed reply, so a pooled one failed the
            // next call ("connection closed before message completed"; the first_action bench).
            .pool_max_idle_per_host(0)
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

    /// One call with its retries; streamed when `progress` is given (a retry starts the
    /// progress over).
    async fn chat_with_retries(
        &self,
        request: &ChatRequest,
        progress: Option<Progress<'_>>,
    ) -> Result<ChatReply, LlmError> {
        let mut wire = WireRequest::new(&self.config, request);
        if progress.is_some() {
            wire = wire.streamed();
        }
        let started = Instant::now();
        let mut attempt: u32 = 0;
        loop {
            attempt = attempt.saturating_add(1);
            let failure = match self.attempt(&wire, progress).await {
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

    /// One HTTP exchange: the body of a 2xx reply (a streamed one assembled into the same shape:
    /// `stream`), or what went wrong and whether to retry.
    async fn attempt(
        &self,
        wire: &WireRequest<'_>,
        progress: Option<Progress<'_>>,
    ) -> Result<Vec<u8>, Failure> {
        let mut builder = self.client.post(self.endpoint.clone()).json(wire);
        if let Some(key) = &self.config.api_key {
            builder = builder.bearer_auth(key);
        }
        let exchange = async {
            let mut response = builder.send().await?;
            let status = response.status();
            let retry_after = retry_after(response.headers());
            let body = match progress {
                // A server that ignores `stream` answers with one JSON body: read as such.
                Some(progress) if status.is_success() && is_event_stream(response.headers()) => {
                    let mut sse = SseAssembler::default();
                    let mut broken = None;
                    while let Some(bytes) = response.chunk().await? {
                        match sse.push(&bytes) {
                            Ok(true) => progress(Streamed {
                                reasoning: sse.reasoning(),
                                content: sse.content(),
                            }),
                            Ok(false) => {}
                            Err(e) => {
                                broken = Some(e);
                                break;
                            }
                        }
                    }
                    match broken {
                        Some(e) => Err(e),
                        None => sse.finish(),
                    }
                }
                _ => Ok(response.bytes().await?.to_vec()),
            };
            Ok::<_, reqwest::Error>((status, retry_after, body))
        };
        let (status, retry_after, body) = match tokio::time::timeout(self.config.timeout, exchange)
            .await
        {
            Err(_elapsed) => return Err(Failure::retry(LlmError::Timeout(self.config.timeout))),
            Ok(Err(e)) => return Err(Failure::from_reqwest(&e, self.config.timeout)),
            Ok(Ok(exchange)) => exchange,
        };
        // A stream that broke off is not retried: the server answered, as a bad body is.
        let body = body.map_err(|error| Failure {
            error,
            retryable: false,
            retry_after: None,
        })?;
        if status.is_success() {
            return Ok(body);
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

/// Whether a response is server-sent events (`text/event-stream`).
fn is_event_stream(headers: &reqwest::header::HeaderMap) -> bool {
    headers
        .get(reqwest::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.trim_start().starts_with("text/event-stream"))
}

impl LlmBackend for OpenAiBackend {
    fn chat<'a>(&'a self, request: &'a ChatRequest) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        Box::pin(self.chat_with_retries(request, None))
    }

    fn chat_streamed<'a>(
        &'a self,
        request: &'a ChatRequest,
        progress: Progress<'a>,
    ) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        Box::pin(self.chat_with_retries(request, Some(progress)))
    }

    fn describe(&self) -> String {
        format!(
            "openai {} {}",
            self.config.base_url.trim_end_matches('/'),
            self.config.model
        )
    }
}

#[cfg(test)]
mod tests;

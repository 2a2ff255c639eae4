//! Recorded replies played in order, for tests that need a model without a server.
//!
//! It behaves like a real backend where callers can tell: every reply takes time (a base latency
//! plus any scripted delay, on tokio's clock, so tests with paused time run instantly), usage is
//! counted (roughly: whitespace-separated words), a reply longer than the request's `max_tokens`
//! is [`LlmError::Truncated`], a `<think>…</think>` block at the start of the content becomes
//! [`ChatReply::reasoning`], and scripted errors come back as they are. Every request is recorded
//! for assertions. When the script runs out, each further request gets
//! [`LlmError::ScriptExhausted`].

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use crate::{BoxFuture, ChatReply, ChatRequest, LlmBackend, LlmError, Usage, rough_token_count};

/// One step of the script.
#[derive(Debug, Clone, PartialEq)]
pub enum ScriptedReply {
    /// Answer with this content (JSON text, usually) after the base latency.
    Content(String),
    /// Fail with this error after the base latency.
    Error(LlmError),
    /// Answer after the base latency plus `delay`.
    Delayed { delay: Duration, content: String },
    /// Fail after the base latency plus `delay` (a `Timeout` that really took its time).
    DelayedError { delay: Duration, error: LlmError },
}

impl ScriptedReply {
    pub fn content(content: impl Into<String>) -> Self {
        ScriptedReply::Content(content.into())
    }

    /// The JSON text of `value`.
    pub fn json(value: &serde_json::Value) -> Self {
        ScriptedReply::Content(value.to_string())
    }

    pub fn error(error: LlmError) -> Self {
        ScriptedReply::Error(error)
    }

    pub fn delayed(delay: Duration, content: impl Into<String>) -> Self {
        ScriptedReply::Delayed {
            delay,
            content: content.into(),
        }
    }

    pub fn delayed_error(delay: Duration, error: LlmError) -> Self {
        ScriptedReply::DelayedError { delay, error }
    }
}

impl From<&str> for ScriptedReply {
    fn from(content: &str) -> Self {
        ScriptedReply::content(content)
    }
}

impl From<String> for ScriptedReply {
    fn from(content: String) -> Self {
        ScriptedReply::Content(content)
    }
}

impl From<LlmError> for ScriptedReply {
    fn from(error: LlmError) -> Self {
        ScriptedReply::Error(error)
    }
}

#[derive(Debug, Default)]
struct State {
    script: VecDeque<ScriptedReply>,
    requests: Vec<ChatRequest>,
}

/// A backend that plays a script. Clones share the script and the request log, so a test can
/// hand one clone to the code under test (as `Arc<dyn LlmBackend>`) and inspect the other.
#[derive(Debug, Clone)]
pub struct ScriptedBackend {
    model: String,
    latency: Duration,
    state: Arc<Mutex<State>>,
}

/// The base latency of every reply unless [`ScriptedBackend::with_latency`] says otherwise: small,
/// but never zero, so nothing can depend on an answer arriving in the same instant.
pub const DEFAULT_SCRIPTED_LATENCY: Duration = Duration::from_millis(1);

impl ScriptedBackend {
    pub fn new<R: Into<ScriptedReply>>(replies: impl IntoIterator<Item = R>) -> Self {
        ScriptedBackend {
            model: "scripted".into(),
            latency: DEFAULT_SCRIPTED_LATENCY,
            state: Arc::new(Mutex::new(State {
                script: replies.into_iter().map(Into::into).collect(),
                requests: Vec::new(),
            })),
        }
    }

    /// The model name in replies and in [`LlmBackend::describe`].
    pub fn with_model(mut self, model: impl Into<String>) -> Self {
        self.model = model.into();
        self
    }

    /// Time every reply (and every scripted error) takes before the scripted delay.
    pub fn with_latency(mut self, latency: Duration) -> Self {
        self.latency = latency;
        self
    }

    /// Appends to the script (shared with every clone).
    pub fn push(&self, reply: impl Into<ScriptedReply>) {
        self.state().script.push_back(reply.into());
    }

    /// Every request received so far, in order.
    pub fn requests(&self) -> Vec<ChatRequest> {
        self.state().requests.clone()
    }

    pub fn request_count(&self) -> usize {
        self.state().requests.len()
    }

    pub fn last_request(&self) -> Option<ChatRequest> {
        self.state().requests.last().cloned()
    }

    /// Replies not played yet.
    pub fn remaining(&self) -> usize {
        self.state().script.len()
    }

    fn state(&self) -> MutexGuard<'_, State> {
        // A test that panicked while holding the lock left consistent data: a Vec and a VecDeque.
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    async fn play(&self, request: &ChatRequest) -> Result<ChatReply, LlmError> {
        let started = tokio::time::Instant::now();
        let next = {
            let mut state = self.state();
            state.requests.push(request.clone());
            state.script.pop_front()
        };
        let (delay, outcome) = match next {
            None => return Err(LlmError::ScriptExhausted),
            Some(ScriptedReply::Content(content)) => (Duration::ZERO, Ok(content)),
            Some(ScriptedReply::Error(error)) => (Duration::ZERO, Err(error)),
            Some(ScriptedReply::Delayed { delay, content }) => (delay, Ok(content)),
            Some(ScriptedReply::DelayedError { delay, error }) => (delay, Err(error)),
        };
        tokio::time::sleep(self.latency.saturating_add(delay)).await;
        let raw = outcome?;

        let completion_tokens = rough_token_count(&raw);
        if completion_tokens > request.max_tokens {
            return Err(LlmError::Truncated(request.max_tokens));
        }
        let prompt_tokens = request
            .messages
            .iter()
            .map(|m| rough_token_count(&m.content))
            .fold(0u32, u32::saturating_add);
        let (reasoning, content) = crate::split_think_tags(&raw);
        if let Some(reasoning) = &reasoning {
            tracing::debug!(model = %self.model, reasoning = %reasoning, "scripted chain of thought");
        }
        Ok(ChatReply {
            content,
            reasoning,
            usage: Usage {
                prompt_tokens,
                completion_tokens,
            },
            latency: started.elapsed(),
            model: self.model.clone(),
        })
    }
}

impl LlmBackend for ScriptedBackend {
    fn chat<'a>(&'a self, request: &'a ChatRequest) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        Box::pin(self.play(request))
    }

    fn describe(&self) -> String {
        format!("scripted {}", self.model)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ChatMessage;

    fn request(max_tokens: u32) -> ChatRequest {
        ChatRequest {
            messages: vec![
                ChatMessage::system("you plan drone missions"),
                ChatMessage::user("alfa take off"),
            ],
            schema: None,
            max_tokens,
            temperature: 0.0,
            seed: Some(7),
            reasoning_effort: None,
        }
    }

    #[tokio::test]
    async fn plays_in_order_records_and_runs_out() {
        let backend =
            ScriptedBackend::new(["{\"plan\": []}", "<think>alfa first</think>{\"plan\": [1]}"])
                .with_model("fake-7b");
        let observer = backend.clone();
        let first = backend.chat(&request(100)).await.expect("first");
        assert_eq!(first.content, "{\"plan\": []}");
        assert_eq!(first.reasoning, None);
        assert_eq!(
            first.usage,
            Usage {
                prompt_tokens: 7,
                completion_tokens: 2
            }
        );
        assert_eq!(first.model, "fake-7b");
        assert!(first.latency >= DEFAULT_SCRIPTED_LATENCY);

        let second = backend.chat(&request(100)).await.expect("second");
        assert_eq!(second.content, "{\"plan\": [1]}");
        assert_eq!(second.reasoning.as_deref(), Some("alfa first"));

        assert_eq!(
            backend.chat(&request(100)).await,
            Err(LlmError::ScriptExhausted)
        );
        assert_eq!(observer.request_count(), 3);
        assert_eq!(observer.requests()[0], request(100));
        assert_eq!(observer.remaining(), 0);
        assert_eq!(backend.describe(), "scripted fake-7b");
    }

    #[tokio::test]
    async fn delays_errors_and_truncation() {
        let backend = ScriptedBackend::new(vec![
            ScriptedReply::delayed(Duration::from_millis(50), "{}"),
            ScriptedReply::delayed_error(
                Duration::from_millis(100),
                LlmError::Timeout(Duration::from_secs(30)),
            ),
            ScriptedReply::error(LlmError::Http {
                status: 503,
                body: "loading model".into(),
            }),
            ScriptedReply::content("one two three four five"),
        ])
        .with_latency(Duration::from_millis(20));

        let start = tokio::time::Instant::now();
        let reply = backend.chat(&request(100)).await.expect("delayed");
        assert!(
            reply.latency >= Duration::from_millis(70),
            "{:?}",
            reply.latency
        );

        let err = backend.chat(&request(100)).await;
        assert_eq!(err, Err(LlmError::Timeout(Duration::from_secs(30))));
        assert!(start.elapsed() >= Duration::from_millis(70 + 120));

        let err = backend.chat(&request(100)).await;
        assert!(matches!(err, Err(LlmError::Http { status: 503, .. })));

        assert_eq!(backend.chat(&request(4)).await, Err(LlmError::Truncated(4)));
        backend.push("late addition");
        assert_eq!(
            backend.chat(&request(4)).await.map(|r| r.content),
            Ok("late addition".into())
        );
        assert_eq!(backend.request_count(), 5);
    }
}

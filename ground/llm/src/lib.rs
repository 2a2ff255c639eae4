//! Language-model backends behind one trait.
//!
//! Every backend takes a [`ChatRequest`] (messages plus, usually, the JSON schema the reply must
//! follow) and returns a [`ChatReply`] or a typed [`LlmError`]. Chain-of-thought text that a
//! server returns is kept in `ChatReply::reasoning` for the mission log and never acted on.
//!
//! - [`openai::OpenAiBackend`]: any OpenAI-compatible server (Ollama, vLLM, llama.cpp server, a
//!   cloud API) over HTTP, configured by [`openai::OpenAiConfig`] (explicit, from a file, or from
//!   `TACOS_LLM_URL` / `TACOS_LLM_MODEL` / `TACOS_LLM_API_KEY`).
//! - [`scripted::ScriptedBackend`]: recorded replies played in order, for tests.

pub mod openai;
pub mod scripted;

pub use openai::{ConfigError, OpenAiBackend, OpenAiConfig, TokenLimitField};
pub use scripted::{ScriptedBackend, ScriptedReply};

use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    System,
    User,
    Assistant,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ChatMessage {
    pub role: Role,
    pub content: String,
}

impl ChatMessage {
    pub fn system(content: impl Into<String>) -> Self {
        ChatMessage {
            role: Role::System,
            content: content.into(),
        }
    }
    pub fn user(content: impl Into<String>) -> Self {
        ChatMessage {
            role: Role::User,
            content: content.into(),
        }
    }
    pub fn assistant(content: impl Into<String>) -> Self {
        ChatMessage {
            role: Role::Assistant,
            content: content.into(),
        }
    }
}

/// What every later request of a kind begins with: whole messages (a layer's system prompt and
/// few-shot turns), then the opening of the next user message that stays the same between
/// calls (the map), possibly empty.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PromptBeginning {
    pub messages: Vec<ChatMessage>,
    pub user_opening: String,
}

/// The JSON schema a reply must follow (OpenAI's `response_format: {type: json_schema}`).
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseSchema {
    /// A short identifier, `[a-zA-Z0-9_-]`.
    pub name: String,
    pub schema: serde_json::Value,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ChatRequest {
    pub messages: Vec<ChatMessage>,
    pub schema: Option<ResponseSchema>,
    pub max_tokens: u32,
    pub temperature: f32,
    pub seed: Option<u64>,
    /// `low` / `medium` / `high` for servers that support it.
    pub reasoning_effort: Option<String>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub struct Usage {
    pub prompt_tokens: u32,
    pub completion_tokens: u32,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ChatReply {
    /// The answer (JSON text when a schema was given).
    pub content: String,
    /// Chain of thought, when the server returned one (`reasoning`, `reasoning_content` or
    /// `thinking`): logged, never acted on.
    pub reasoning: Option<String>,
    pub usage: Usage,
    pub latency: Duration,
    pub model: String,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LlmError {
    #[error("model server answered HTTP {status}: {body}")]
    Http { status: u16, body: String },
    #[error("no answer from the model server within {0:?}")]
    Timeout(Duration),
    #[error("cannot reach the model server: {0}")]
    Connect(String),
    #[error("the reply was cut off at the token limit ({0} tokens)")]
    Truncated(u32),
    #[error("the model server's answer is not what the API promises: {0}")]
    BadResponse(String),
    #[error("the model refused: {0}")]
    Refused(String),
    #[error("the embedded model is unavailable: {0}")]
    ModelUnavailable(String),
    #[error("generation failed: {0}")]
    Generation(String),
    #[error("no scripted reply left")]
    ScriptExhausted,
}

pub type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// A reply as it is being generated: the text so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Streamed<'a> {
    /// The chain of thought so far, from servers that send it apart.
    pub reasoning: &'a str,
    /// The answer so far (JSON text being written, when a schema was given); a `<think>` block
    /// a server sends inline is still in it.
    pub content: &'a str,
}

/// Told the reply so far each time it grows.
pub type Progress<'a> = &'a (dyn Fn(Streamed<'_>) + Send + Sync);

/// A language model that answers chat requests.
pub trait LlmBackend: Send + Sync {
    fn chat<'a>(&'a self, request: &'a ChatRequest) -> BoxFuture<'a, Result<ChatReply, LlmError>>;

    /// As [`Self::chat`], telling `progress` the reply so far each time it grows, so that a pilot
    /// sees the reasoning while it is written. A backend that cannot stream tells nothing and
    /// answers as `chat`.
    fn chat_streamed<'a>(
        &'a self,
        request: &'a ChatRequest,
        progress: Progress<'a>,
    ) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        let _ = progress;
        self.chat(request)
    }

    /// Backend and model, for the status bar and the mission log (e.g. `openai http://…/v1 gpt-oss:20b`).
    fn describe(&self) -> String;

    /// Computes ahead of time what `beginning` costs, so that a later request beginning with it
    /// (the fixed part of every call of a layer) answers sooner. Backends without a prompt cache
    /// of their own do nothing.
    fn warm_up<'a>(
        &'a self,
        beginning: &'a PromptBeginning,
    ) -> BoxFuture<'a, Result<(), LlmError>> {
        let _ = beginning;
        Box::pin(async { Ok(()) })
    }
}

/// Splits a `<think>…</think>` block off the start of `content` (what llama.cpp's server and some
/// chat templates do with reasoning models): returns `(reasoning, answer)`.
///
/// Also accepts a reply whose opening tag was in the prompt (the template opened the block, so the
/// content is `reasoning…</think>answer`). An unterminated `<think>` is all reasoning: the answer is
/// then empty. Content without tags comes back unchanged with no reasoning.
pub fn split_think_tags(content: &str) -> (Option<String>, String) {
    const OPEN: &str = "<think>";
    const CLOSE: &str = "</think>";
    let non_empty = |text: &str| {
        let text = text.trim();
        (!text.is_empty()).then(|| text.to_string())
    };
    let start = content.trim_start();
    if let Some(rest) = start.strip_prefix(OPEN) {
        return match rest.split_once(CLOSE) {
            Some((thought, answer)) => (non_empty(thought), answer.trim().to_string()),
            None => (non_empty(rest), String::new()),
        };
    }
    if !content.contains(OPEN)
        && let Some((thought, answer)) = content.split_once(CLOSE)
        && !answer.trim().is_empty()
    {
        return (non_empty(thought), answer.trim().to_string());
    }
    (None, content.to_string())
}

/// A rough token count: whitespace-separated words (what [`ScriptedBackend`] reports as usage).
pub fn rough_token_count(text: &str) -> u32 {
    u32::try_from(text.split_whitespace().count()).unwrap_or(u32::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn think_tags_at_the_start_become_reasoning() {
        let (reasoning, answer) =
            split_think_tags("  <think>\nfly north first\n</think>\n{\"plan\":[]}");
        assert_eq!(reasoning.as_deref(), Some("fly north first"));
        assert_eq!(answer, "{\"plan\":[]}");
    }

    #[test]
    fn closing_tag_only_splits_too() {
        let (reasoning, answer) = split_think_tags("hmm, alfa is closer</think>{\"a\":1}");
        assert_eq!(reasoning.as_deref(), Some("hmm, alfa is closer"));
        assert_eq!(answer, "{\"a\":1}");
    }

    #[test]
    fn unterminated_think_is_all_reasoning() {
        let (reasoning, answer) = split_think_tags("<think>still thinking");
        assert_eq!(reasoning.as_deref(), Some("still thinking"));
        assert_eq!(answer, "");
    }

    #[test]
    fn plain_content_is_unchanged() {
        let (reasoning, answer) = split_think_tags(" {\"x\": \"<think> inside\"} ");
        assert_eq!(reasoning, None);
        assert_eq!(answer, " {\"x\": \"<think> inside\"} ");
        let (reasoning, answer) = split_think_tags("<think></think>{}");
        assert_eq!(reasoning, None);
        assert_eq!(answer, "{}");
    }

    #[test]
    fn rough_tokens_are_words() {
        assert_eq!(rough_token_count(""), 0);
        assert_eq!(rough_token_count(" take off\n alfa  "), 3);
    }
}

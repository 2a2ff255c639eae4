//! Language-model backends behind one trait.
//!
//! Every backend takes a [`ChatRequest`] (messages plus, usually, the JSON schema the reply must
//! follow) and returns a [`ChatReply`] or a typed [`LlmError`]. Chain-of-thought text that a
//! server returns is kept in `ChatReply::reasoning` for the mission log and never acted on.

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
        ChatMessage { role: Role::System, content: content.into() }
    }
    pub fn user(content: impl Into<String>) -> Self {
        ChatMessage { role: Role::User, content: content.into() }
    }
    pub fn assistant(content: impl Into<String>) -> Self {
        ChatMessage { role: Role::Assistant, content: content.into() }
    }
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

/// A language model that answers chat requests.
pub trait LlmBackend: Send + Sync {
    fn chat<'a>(&'a self, request: &'a ChatRequest) -> BoxFuture<'a, Result<ChatReply, LlmError>>;

    /// Backend and model, for the status bar and the mission log (e.g. `openai http://…/v1 gpt-oss:20b`).
    fn describe(&self) -> String;
}

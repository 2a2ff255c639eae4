//! The backend's configuration: explicit, from a file, or from the environment.

use std::fmt;
use std::time::Duration;

use serde::{Deserialize, Serialize};

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

pub(super) fn default_timeout() -> Duration {
    DEFAULT_TIMEOUT
}
pub(super) fn default_max_retries() -> u32 {
    DEFAULT_MAX_RETRIES
}
pub(super) fn default_initial_backoff() -> Duration {
    DEFAULT_INITIAL_BACKOFF
}
pub(super) fn default_max_backoff() -> Duration {
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
    pub(super) fn endpoint(&self) -> Result<reqwest::Url, ConfigError> {
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

pub(super) fn parse_seconds(text: &str) -> Result<Duration, String> {
    let secs: f64 = text
        .trim()
        .parse()
        .map_err(|e| format!("not a number of seconds: {e}"))?;
    Duration::try_from_secs_f64(secs).map_err(|e| format!("not a duration: {e}"))
}

/// Durations in config files: seconds, integer or decimal.
pub(super) mod seconds {
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

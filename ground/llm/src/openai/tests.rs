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
    let config =
        OpenAiConfig::from_lookup(lookup(&[("TACOS_LLM_MODEL", "gpt-oss:20b")])).expect("config");
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
    let config = OpenAiConfig::new("http://h/v1", "m").with_retries(10, Duration::from_millis(100));
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

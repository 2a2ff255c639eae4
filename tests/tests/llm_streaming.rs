//! Streaming against llama.cpp's own server (xllamacpp, SmolLM2-135M's GGUF): the OpenAI
//! backend's `chat_streamed` (`stream: true`, server-sent events) tells the reply as it grows
//! and ends with the very reply an unstreamed call gets, token counts included. Skipped, saying
//! how to get the server, without the venv (failing with `CI=true`).

use serde_json::json;
use std::sync::Mutex;
use std::time::Duration;
use tacos_llm::{
    ChatMessage, ChatRequest, LlmBackend, OpenAiBackend, OpenAiConfig, ResponseSchema, Streamed,
};
use tacos_tests::llama_server::{
    LlamaServer, LlamaServerConfig, llama_python_or_skip, smollm2_model,
};
use tacos_tests::within;

#[test]
fn a_streamed_reply_grows_to_the_reply_an_unstreamed_call_gets() -> anyhow::Result<()> {
    const TEST: &str = "a_streamed_reply_grows_to_the_reply_an_unstreamed_call_gets";
    let Some(python) = llama_python_or_skip(TEST) else {
        return Ok(());
    };
    let config = LlamaServerConfig::new(python, smollm2_model()?, "smollm2-135m-instruct")
        .n_ctx(2048)
        .threads(1);
    let server = LlamaServer::start(&config)?;
    let backend = OpenAiBackend::new(
        OpenAiConfig::new(server.url(), server.model()).with_timeout(Duration::from_secs(120)),
    )?;
    // A reply of a known length: the grammar holds the model in one string of 200 characters
    // or more, so it is written in many pieces.
    let request = ChatRequest {
        messages: vec![
            ChatMessage::system("You command a drone swarm. Answer with one JSON object."),
            ChatMessage::user("Explain how alfa should search the park."),
        ],
        schema: Some(ResponseSchema {
            name: "plan_text".into(),
            schema: json!({
                "type": "object",
                "properties": { "reasoning": { "type": "string", "minLength": 200, "maxLength": 260 } },
                "required": ["reasoning"],
                "additionalProperties": false
            }),
        }),
        max_tokens: 300,
        temperature: 0.0,
        seed: Some(7),
        reasoning_effort: Some("low".into()),
    };
    let told = Mutex::new(Vec::<String>::new());
    let progress = |so_far: Streamed<'_>| {
        told.lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(so_far.content.to_owned());
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let streamed = runtime.block_on(within(
        "a streamed reply",
        Duration::from_secs(90),
        backend.chat_streamed(&request, &progress),
    ))??;
    let whole = runtime.block_on(within(
        "an unstreamed reply",
        Duration::from_secs(90),
        backend.chat(&request),
    ))??;
    let told = told.into_inner().unwrap_or_else(|e| e.into_inner());
    eprintln!(
        "{TEST}: {} pieces told for {} tokens in {:.2} s; unstreamed {:.2} s",
        told.len(),
        streamed.usage.completion_tokens,
        streamed.latency.as_secs_f64(),
        whole.latency.as_secs_f64()
    );
    assert!(
        told.len() >= 10,
        "only {} pieces told for a reply of {} tokens",
        told.len(),
        streamed.usage.completion_tokens
    );
    for pair in told.windows(2) {
        assert!(
            pair[1].starts_with(&pair[0]),
            "the text so far shrank: {pair:?}"
        );
    }
    assert_eq!(
        told.last(),
        Some(&streamed.content),
        "the last piece is the reply"
    );
    assert_eq!(
        streamed.content, whole.content,
        "streaming changed the reply"
    );
    assert_eq!(
        streamed.usage, whole.usage,
        "the token counts come with the stream"
    );
    assert_eq!(streamed.model, whole.model);
    Ok(())
}

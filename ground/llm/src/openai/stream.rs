//! A streamed reply (`stream: true`): server-sent events, each `data: {chunk}` with a `delta` of
//! the first choice, until `data: [DONE]`. [`SseAssembler`] takes the body's bytes as they come,
//! keeps the text so far for the caller's progress, and at the end assembles the whole reply in
//! the non-streamed shape, so that one parser (`OpenAiBackend::parse_reply`) judges both.
//!
//! llama.cpp's server, vLLM, Ollama and OpenAI put the text in `choices[0].delta.content`, the
//! chain of thought in `delta.reasoning_content` (or `reasoning`, `thinking`), `finish_reason`
//! in the last chunk with a choice, and `usage` (asked for with
//! `stream_options.include_usage`) in a last chunk whose `choices` is empty. An error in the
//! middle of a stream comes as a chunk with `error`.

use super::wire::{snippet, text_of};
use crate::LlmError;
use serde_json::{Value, json};

/// The reply so far, assembled from the events of one streamed response.
#[derive(Debug, Default)]
pub struct SseAssembler {
    /// Bytes of an event not yet complete (events end with a blank line).
    pending: Vec<u8>,
    content: String,
    reasoning: String,
    finish_reason: Option<String>,
    usage: Option<Value>,
    model: Option<String>,
    refusal: String,
    error: Option<Value>,
    done: bool,
}

impl SseAssembler {
    /// Takes in the next bytes of the body; true when the text (content or reasoning) grew.
    pub fn push(&mut self, bytes: &[u8]) -> Result<bool, LlmError> {
        self.pending.extend_from_slice(bytes);
        let mut grew = false;
        while let Some((end, gap)) = event_end(&self.pending) {
            let event: Vec<u8> = self.pending.drain(..end + gap).take(end).collect();
            grew |= self.event(&event)?;
        }
        Ok(grew)
    }

    /// The chain of thought so far.
    pub fn reasoning(&self) -> &str {
        &self.reasoning
    }

    /// The content so far (a `<think>` block, if the server sends one, still in it).
    pub fn content(&self) -> &str {
        &self.content
    }

    /// The whole reply in the shape of a non-streamed chat completion, once the body has ended.
    /// A stream that ended without `[DONE]` and without a finish reason was cut short.
    pub fn finish(mut self) -> Result<Vec<u8>, LlmError> {
        if !self.pending.iter().all(u8::is_ascii_whitespace) {
            let rest = std::mem::take(&mut self.pending);
            self.event(&rest)?;
        }
        if let Some(error) = self.error {
            return Ok(json!({ "error": error }).to_string().into_bytes());
        }
        if !self.done && self.finish_reason.is_none() {
            return Err(LlmError::BadResponse(
                "the streamed reply ended before the server finished it".into(),
            ));
        }
        let mut message = json!({ "role": "assistant", "content": self.content });
        if !self.reasoning.is_empty() {
            message["reasoning_content"] = Value::String(self.reasoning);
        }
        if !self.refusal.is_empty() {
            message["refusal"] = Value::String(self.refusal);
        }
        let mut whole = json!({
            "choices": [{ "message": message, "finish_reason": self.finish_reason }],
        });
        if let Some(usage) = self.usage {
            whole["usage"] = usage;
        }
        if let Some(model) = self.model {
            whole["model"] = Value::String(model);
        }
        Ok(whole.to_string().into_bytes())
    }

    /// One event: its `data:` lines joined. True when the text grew.
    fn event(&mut self, event: &[u8]) -> Result<bool, LlmError> {
        let text = String::from_utf8_lossy(event);
        let data: Vec<&str> = text
            .lines()
            .filter_map(|line| line.strip_prefix("data:"))
            .map(|d| d.strip_prefix(' ').unwrap_or(d))
            .collect();
        if data.is_empty() {
            // A comment (`: keep-alive`) or another field: nothing to read.
            return Ok(false);
        }
        let data = data.join("\n");
        if data.trim() == "[DONE]" {
            self.done = true;
            return Ok(false);
        }
        let chunk: Value = serde_json::from_str(&data).map_err(|e| {
            LlmError::BadResponse(format!(
                "a streamed chunk is not JSON ({e}): {}",
                snippet(data.as_bytes())
            ))
        })?;
        if let Some(error) = chunk.get("error").filter(|e| !e.is_null()) {
            self.error = Some(error.clone());
            return Ok(false);
        }
        if let Some(model) = chunk.get("model").and_then(Value::as_str)
            && !model.is_empty()
        {
            self.model = Some(model.to_owned());
        }
        if let Some(usage) = chunk.get("usage").filter(|u| u.is_object()) {
            self.usage = Some(usage.clone());
        }
        let Some(choice) = chunk.get("choices").and_then(|c| c.get(0)) else {
            return Ok(false);
        };
        if let Some(reason) = choice.get("finish_reason").and_then(Value::as_str) {
            self.finish_reason = Some(reason.to_owned());
        }
        let Some(delta) = choice.get("delta") else {
            return Ok(false);
        };
        let mut grew = false;
        if let Some(text) = delta.get("content").and_then(text_of) {
            grew |= !text.is_empty();
            self.content.push_str(&text);
        }
        for field in ["reasoning_content", "reasoning", "thinking"] {
            if let Some(text) = delta.get(field).and_then(text_of) {
                grew |= !text.is_empty();
                self.reasoning.push_str(&text);
            }
        }
        if let Some(text) = delta.get("refusal").and_then(text_of) {
            self.refusal.push_str(&text);
        }
        Ok(grew)
    }
}

/// Where the first complete event in `bytes` ends, and the length of the blank line after it
/// (`\n\n`, or `\r\n\r\n` from servers that end lines so).
fn event_end(bytes: &[u8]) -> Option<(usize, usize)> {
    let lf = bytes.windows(2).position(|w| w == b"\n\n").map(|i| (i, 2));
    let crlf = bytes
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .map(|i| (i, 4));
    match (lf, crlf) {
        (Some(a), Some(b)) => Some(if a.0 <= b.0 { a } else { b }),
        (a, b) => a.or(b),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shape llama.cpp's server streams (role first, then content deltas, the finish reason,
    /// and usage with `stream_options.include_usage`), cut at awkward places.
    const LLAMA_CPP: &str = concat!(
        "data: {\"choices\":[{\"finish_reason\":null,\"index\":0,\"delta\":{\"role\":\"assistant\",\"content\":null}}],\"model\":\"qwen\",\"object\":\"chat.completion.chunk\"}\n\n",
        "data: {\"choices\":[{\"finish_reason\":null,\"index\":0,\"delta\":{\"content\":\"{\\\"reasoning\\\": \\\"Al\"}}],\"model\":\"qwen\"}\n\n",
        ": keep-alive\n\n",
        "data: {\"choices\":[{\"finish_reason\":null,\"index\":0,\"delta\":{\"content\":\"fa flies.\\\"}\"}}],\"model\":\"qwen\"}\r\n\r\n",
        "data: {\"choices\":[{\"finish_reason\":\"stop\",\"index\":0,\"delta\":{}}],\"model\":\"qwen\"}\n\n",
        "data: {\"choices\":[],\"usage\":{\"completion_tokens\":9,\"prompt_tokens\":120,\"total_tokens\":129},\"model\":\"qwen\"}\n\n",
        "data: [DONE]\n\n",
    );

    fn assemble(body: &str, cut: usize) -> (SseAssembler, Vec<String>) {
        let mut sse = SseAssembler::default();
        let mut seen = Vec::new();
        for piece in body.as_bytes().chunks(cut) {
            if sse.push(piece).expect("valid stream") {
                seen.push(sse.content().to_owned());
            }
        }
        (sse, seen)
    }

    #[test]
    fn a_stream_read_in_any_pieces_gives_the_whole_reply_and_its_progress() {
        for cut in [1, 7, 64, 4096] {
            let (sse, seen) = assemble(LLAMA_CPP, cut);
            let expected: &[&str] = if cut <= 64 {
                &["{\"reasoning\": \"Al", "{\"reasoning\": \"Alfa flies.\"}"]
            } else {
                // Read at once: told once, whole.
                &["{\"reasoning\": \"Alfa flies.\"}"]
            };
            assert_eq!(seen, expected, "read {cut} bytes at a time");
            let whole: Value =
                serde_json::from_slice(&sse.finish().expect("finished")).expect("JSON");
            assert_eq!(
                whole["choices"][0]["message"]["content"],
                "{\"reasoning\": \"Alfa flies.\"}"
            );
            assert_eq!(whole["choices"][0]["finish_reason"], "stop");
            assert_eq!(whole["usage"]["completion_tokens"], 9);
            assert_eq!(whole["model"], "qwen");
        }
    }

    #[test]
    fn reasoning_errors_and_streams_cut_short_are_kept_apart() {
        let (sse, _) = assemble(
            concat!(
                "data: {\"choices\":[{\"delta\":{\"reasoning_content\":\"think \"}}]}\n\n",
                "data: {\"choices\":[{\"delta\":{\"reasoning_content\":\"more\"}}]}\n\n",
                "data: {\"choices\":[{\"delta\":{\"content\":\"{}\"},\"finish_reason\":\"length\"}]}\n\n",
            ),
            5,
        );
        assert_eq!(sse.reasoning(), "think more");
        let whole: Value =
            serde_json::from_slice(&sse.finish().expect("a finish reason")).expect("JSON");
        assert_eq!(
            whole["choices"][0]["message"]["reasoning_content"],
            "think more"
        );
        assert_eq!(whole["choices"][0]["finish_reason"], "length");

        let (sse, _) = assemble(
            "data: {\"error\":{\"code\":500,\"message\":\"the context is full\"}}\n\n",
            9,
        );
        let whole: Value =
            serde_json::from_slice(&sse.finish().expect("an error body")).expect("JSON");
        assert_eq!(whole["error"]["message"], "the context is full");

        let (sse, _) = assemble(
            "data: {\"choices\":[{\"delta\":{\"content\":\"{\\\"a\"}}]}\n\n",
            3,
        );
        assert!(
            matches!(sse.finish(), Err(LlmError::BadResponse(_))),
            "cut short"
        );

        let mut sse = SseAssembler::default();
        assert!(matches!(
            sse.push(b"data: {oops\n\n"),
            Err(LlmError::BadResponse(_))
        ));
    }
}

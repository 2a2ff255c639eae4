//! An OpenAI-compatible chat-completions server on loopback, for running the real
//! `tacos-ground` binary against a stand-in model. It speaks HTTP/1.1 the way a served model
//! does: `POST /v1/chat/completions` only (404 otherwise), a JSON body with `model` and
//! `messages` (400 when malformed), the configured model name (404 for another), a chat
//! completion with `usage` on success, and `{"error": {...}}` bodies on errors. The reply text
//! comes from a policy that reads the request; it may answer with an error status instead.
//!
//! Error bodies have llama.cpp's shape, as its server answers (`tests/tests/real_llm_server.rs`):
//! `{"error": {"code": <status>, "message": …, "type": …}}` with its type for the status
//! (`invalid_request_error` for 400, `not_found_error` for 404, `unavailable_error` for 503,
//! `server_error` otherwise). Unlike llama.cpp, which serves whatever model name a request gives,
//! the stand-in refuses another name, as Ollama, vLLM and OpenAI do: it checks what the ground
//! sends.

use serde_json::{Value, json};
use std::sync::{Arc, Mutex};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// What the policy answers: the message content, or an error the server returns as HTTP.
pub type PolicyResult = Result<String, (u16, String)>;

/// A running server; it stops when the test's runtime ends.
pub struct ChatServer {
    /// Base URL for `--llm-url` (ends in `/v1`).
    pub url: String,
    /// The model name it serves.
    pub model: String,
    /// Every request body received, in order, with the status answered.
    pub exchanges: Arc<Mutex<Vec<(Value, u16)>>>,
}

impl ChatServer {
    /// Serves `model` on a free loopback port; `policy` sees each request's JSON body (with
    /// its index, from 0) and decides the reply.
    pub async fn start<F>(model: &str, policy: F) -> std::io::Result<ChatServer>
    where
        F: Fn(usize, &Value) -> PolicyResult + Send + Sync + 'static,
    {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let url = format!("http://{}/v1", listener.local_addr()?);
        let exchanges: Arc<Mutex<Vec<(Value, u16)>>> = Arc::new(Mutex::new(Vec::new()));
        let policy = Arc::new(policy);
        let (served, log) = (model.to_owned(), exchanges.clone());
        tokio::spawn(async move {
            while let Ok((stream, _)) = listener.accept().await {
                let (policy, served, log) = (policy.clone(), served.clone(), log.clone());
                tokio::spawn(async move {
                    let _ = serve(stream, policy.as_ref(), &served, &log).await;
                });
            }
        });
        Ok(ChatServer {
            url,
            model: model.to_owned(),
            exchanges,
        })
    }

    /// How many requests were answered with `status`.
    pub fn count(&self, status: u16) -> usize {
        self.exchanges
            .lock()
            .map_or(0, |e| e.iter().filter(|(_, s)| *s == status).count())
    }
}

async fn serve<F>(
    mut stream: TcpStream,
    policy: &F,
    served: &str,
    log: &Mutex<Vec<(Value, u16)>>,
) -> std::io::Result<()>
where
    F: Fn(usize, &Value) -> PolicyResult,
{
    // One request per connection (`connection: close`), like a server that does not keep alive.
    let (head, body) = read_request(&mut stream).await?;
    let request_line = head.lines().next().unwrap_or_default().to_owned();
    let (status, reply) = if !request_line.starts_with("POST /v1/chat/completions ") {
        (404, error_body(404, "File Not Found"))
    } else {
        match serde_json::from_slice::<Value>(&body) {
            Err(e) => (400, error_body(400, &format!("invalid JSON: {e}"))),
            Ok(request) => {
                let answer = if request["model"] != served {
                    Err((404, format!("model {} not found", request["model"])))
                } else if !request["messages"].is_array() {
                    Err((400, "messages must be an array".to_owned()))
                } else {
                    let index = log.lock().map_or(0, |l| l.len());
                    policy(index, &request)
                };
                let status = answer.as_ref().map_or_else(|(s, _)| *s, |_| 200);
                if let Ok(mut l) = log.lock() {
                    l.push((request.clone(), status));
                }
                match answer {
                    Ok(content) => (200, completion(&request, served, &content)),
                    Err((status, message)) => (status, error_body(status, &message)),
                }
            }
        }
    };
    let reason = match status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        429 => "Too Many Requests",
        503 => "Service Unavailable",
        _ => "Error",
    };
    // Asked to stream, a real server answers a success as server-sent events (errors stay JSON).
    let (kind, body) = match serde_json::from_slice::<Value>(&body) {
        Ok(request) if status == 200 && request["stream"] == true => {
            ("text/event-stream", events(&reply))
        }
        _ => ("application/json", reply.to_string()),
    };
    let response = format!(
        "HTTP/1.1 {status} {reason}\r\ncontent-type: {kind}\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(response.as_bytes()).await?;
    stream.shutdown().await
}

/// An error body as llama.cpp's server writes it: the status as `code`, and its type for it.
fn error_body(status: u16, message: &str) -> Value {
    let kind = match status {
        400 => "invalid_request_error",
        401 => "authentication_error",
        403 => "permission_error",
        404 => "not_found_error",
        501 => "not_supported_error",
        503 => "unavailable_error",
        _ => "server_error",
    };
    json!({ "error": { "code": status, "message": message, "type": kind } })
}

/// A completion as llama.cpp's server streams it: the content in pieces of a few characters,
/// the finish reason, the usage in a last chunk without choices, then `[DONE]`.
fn events(completion: &Value) -> String {
    let model = &completion["model"];
    let choice = &completion["choices"][0];
    let content: Vec<char> = choice["message"]["content"]
        .as_str()
        .unwrap_or_default()
        .chars()
        .collect();
    let mut out = String::new();
    let mut event = |chunk: Value| out.push_str(&format!("data: {chunk}\n\n"));
    for piece in content.chunks(12) {
        let text: String = piece.iter().collect();
        event(json!({ "object": "chat.completion.chunk", "model": model,
            "choices": [{ "index": 0, "delta": { "content": text }, "finish_reason": null }] }));
    }
    event(json!({ "object": "chat.completion.chunk", "model": model,
        "choices": [{ "index": 0, "delta": {}, "finish_reason": choice["finish_reason"] }] }));
    event(
        json!({ "object": "chat.completion.chunk", "model": model, "choices": [],
        "usage": completion["usage"] }),
    );
    out.push_str("data: [DONE]\n\n");
    out
}

fn completion(request: &Value, model: &str, content: &str) -> Value {
    let words = |t: &str| t.split_whitespace().count();
    let prompt: usize = request["messages"]
        .as_array()
        .map(|m| {
            m.iter()
                .map(|m| words(m["content"].as_str().unwrap_or_default()))
                .sum()
        })
        .unwrap_or(0);
    json!({
        "id": "chatcmpl-standin",
        "object": "chat.completion",
        "created": 0,
        "model": model,
        "choices": [{
            "index": 0,
            "message": { "role": "assistant", "content": content },
            "finish_reason": "stop"
        }],
        "usage": {
            "prompt_tokens": prompt,
            "completion_tokens": words(content),
            "total_tokens": prompt + words(content)
        }
    })
}

/// Reads one HTTP/1.1 request: the head (as text) and a Content-Length body.
async fn read_request(stream: &mut TcpStream) -> std::io::Result<(String, Vec<u8>)> {
    let mut data = Vec::new();
    let mut buf = [0u8; 8192];
    loop {
        let n = stream.read(&mut buf).await?;
        if n == 0 {
            return Ok((String::from_utf8_lossy(&data).into_owned(), Vec::new()));
        }
        data.extend_from_slice(&buf[..n]);
        if let Some(end) = data.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&data[..end]).into_owned();
            let length = head
                .lines()
                .find_map(|l| {
                    let (name, value) = l.split_once(':')?;
                    name.trim()
                        .eq_ignore_ascii_case("content-length")
                        .then(|| value.trim().parse::<usize>().ok())
                        .flatten()
                })
                .unwrap_or(0);
            while data.len() < end + 4 + length {
                let n = stream.read(&mut buf).await?;
                if n == 0 {
                    break;
                }
                data.extend_from_slice(&buf[..n]);
            }
            let body = data.get(end + 4..).unwrap_or_default().to_vec();
            return Ok((head, body));
        }
    }
}

//! `tacos-ground demo` against an OpenAI-compatible server on loopback that only ever answers
//! with prose: the run ends with a clear error, the repair loop asked a bounded number of times,
//! and no action was sent to any drone.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};
use tacos_ground::mission::log::{self, Record};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;

/// Reads one HTTP/1.1 request (headers and a Content-Length body).
async fn read_request(stream: &mut tokio::net::TcpStream) -> std::io::Result<Vec<u8>> {
    let mut data = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        let n = stream.read(&mut buf).await?;
        if n == 0 {
            return Ok(data);
        }
        data.extend_from_slice(&buf[..n]);
        if let Some(end) = data.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&data[..end]).to_lowercase();
            let length = head
                .lines()
                .find_map(|l| {
                    l.strip_prefix("content-length:")
                        .and_then(|v| v.trim().parse::<usize>().ok())
                })
                .unwrap_or(0);
            while data.len() < end + 4 + length {
                let n = stream.read(&mut buf).await?;
                if n == 0 {
                    break;
                }
                data.extend_from_slice(&buf[..n]);
            }
            return Ok(data);
        }
    }
}

/// A chat-completions server whose every reply is well-formed HTTP and JSON, but whose message
/// content is prose instead of the requested JSON object.
async fn prose_server() -> anyhow::Result<(String, Arc<AtomicUsize>)> {
    let listener = TcpListener::bind("127.0.0.1:0").await?;
    let url = format!("http://{}/v1", listener.local_addr()?);
    let count = Arc::new(AtomicUsize::new(0));
    let c = count.clone();
    tokio::spawn(async move {
        while let Ok((mut stream, _)) = listener.accept().await {
            let c = c.clone();
            tokio::spawn(async move {
                if read_request(&mut stream).await.is_err() {
                    return;
                }
                c.fetch_add(1, Ordering::SeqCst);
                let body = serde_json::json!({
                    "id": "chatcmpl-1",
                    "object": "chat.completion",
                    "model": "broken",
                    "choices": [{
                        "index": 0,
                        "message": { "role": "assistant", "content": "Of course! I will ask all the drones to take off right away." },
                        "finish_reason": "stop"
                    }],
                    "usage": { "prompt_tokens": 900, "completion_tokens": 14 }
                })
                .to_string();
                let response = format!(
                    "HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
                    body.len()
                );
                let _ = stream.write_all(response.as_bytes()).await;
                let _ = stream.shutdown().await;
            });
        }
    });
    Ok((url, count))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_that_never_answers_json_ends_the_run_with_no_action_sent() -> anyhow::Result<()> {
    let (url, requests) = prose_server().await?;
    let log_path =
        std::env::temp_dir().join(format!("{}.jsonl", tacos_tests::unique_swarm("broken")));
    let ground = tacos_ground::launch::bin_dir().join("tacos-ground");
    let started = Instant::now();
    let output = tokio::time::timeout(
        Duration::from_secs(120),
        tokio::process::Command::new(ground)
            .args([
                "demo",
                "--drones",
                "3",
                "--no-terminal",
                "--say",
                "all drones take off",
                "--llm-url",
                &url,
                "--model",
                "broken",
            ])
            .arg("--log")
            .arg(&log_path)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .map_err(|_| anyhow::anyhow!("the demo did not end within 120 s"))??;
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success(),
        "the run must fail; stdout: {}",
        String::from_utf8_lossy(&output.stdout)
    );
    assert!(
        stderr.contains("no acceptable reply after 3 attempts"),
        "unclear error: {stderr}"
    );
    assert_eq!(
        requests.load(Ordering::SeqCst),
        3,
        "one request and two repairs"
    );
    let lines = log::read(&log_path)?;
    assert!(
        lines
            .iter()
            .any(|l| matches!(l.record, Record::LlmReply { .. })),
        "the replies were logged"
    );
    assert!(
        !lines
            .iter()
            .any(|l| matches!(l.record, Record::ActionSent { .. })),
        "an action was sent although no reply was acceptable"
    );
    println!("failed cleanly in {:.1} s", started.elapsed().as_secs_f64());
    let _ = std::fs::remove_file(&log_path);
    Ok(())
}

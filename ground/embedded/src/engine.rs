//! The model in process: the [`Decoder`] on CPU, llguidance masking the logits, and a prompt
//! started from the key/value cache that shares its beginning (`caches`: the fixed part of every
//! mission prompt, kept from the call before or read back from disk), so that it only computes
//! what is new.

use std::fs::File;
use std::io::{Cursor, Read, Seek};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use candle_core::quantized::{GgmlDType, QTensor, gguf_file};
use candle_core::{Device, Tensor};
use llguidance::api::TopLevelGrammar;
use llguidance::{Matcher, ParserFactory};
use tacos_llm::{ChatRequest, LlmError, PromptBeginning};

use crate::caches::PromptCaches;
use crate::catalogue::{Architecture, EmbeddedModel};
use crate::decoder::{Decoder, KvCache};
use crate::prompt_store::PromptStore;
use crate::sampling::{SplitMix64, penalise_repeats, sample, time_seed};
use crate::template::{chatml_segments, open_user_turn};
use crate::tokenizer::ModelTokenizer;

/// How the weights are held in memory. SmolLM2's file is Q4_1; candle's Q4_1 dot product is
/// scalar code, while its Q8_0 one uses AVX2/AVX-VNNI and its f32 matmul uses `gemm`, so
/// converting at load time is much faster on x86, at the cost of memory and about a second of
/// start-up. Qwen's files are Q4_K_M, mostly K-quants, which candle computes with AVX2 too; but
/// the 0.5B model's file also holds Q5_0/Q5_1 matrices (its width, 896, is no multiple of 256),
/// and with those as stored it decoded at 5.3 tokens/s against 26.7 with them as Q8_0.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightFormat {
    /// For SmolLM2: Q8_0 when candle's quantized kernels run single-threaded
    /// (`CANDLE_NUM_THREADS=1`, or one core), else f32: candle's multi-threaded quantized kernels
    /// collapse when the cores are busy with other work, its f32 matmul does not. For Qwen:
    /// [`WeightFormat::FastKernels`] (f32 would be 6 GB for 1.5B parameters).
    Auto,
    /// The formats candle has AVX2 kernels for (K-quants, Q4_0, Q8_0) as stored; every other
    /// quantized matrix re-quantized to Q8_0.
    FastKernels,
    /// As stored in the file (Q4_1, ~100 MB). Slowest.
    AsStored,
    /// Re-quantized to Q8_0 (~150 MB): no measurable quality loss from Q4_1.
    Q8_0,
    /// Dequantized to f32 (~540 MB).
    F32,
}

impl WeightFormat {
    pub fn parse(s: &str) -> Option<WeightFormat> {
        match s.to_ascii_lowercase().as_str() {
            "auto" => Some(WeightFormat::Auto),
            "q4_1" | "stored" | "as-stored" => Some(WeightFormat::AsStored),
            "q8_0" | "q8" => Some(WeightFormat::Q8_0),
            "fast" | "fast-kernels" => Some(WeightFormat::FastKernels),
            "f32" => Some(WeightFormat::F32),
            _ => None,
        }
    }

    /// `Auto` made concrete for this model and process (reads `CANDLE_NUM_THREADS` /
    /// `RAYON_NUM_THREADS`, as candle does).
    pub fn resolve(self, model: EmbeddedModel) -> WeightFormat {
        match self {
            WeightFormat::Auto if model.architecture() == Architecture::Qwen2 => {
                WeightFormat::FastKernels
            }
            WeightFormat::Auto => {
                let env_threads =
                    ["CANDLE_NUM_THREADS", "RAYON_NUM_THREADS"]
                        .iter()
                        .find_map(|k| {
                            std::env::var(k)
                                .ok()
                                .and_then(|v| v.trim().parse::<usize>().ok())
                                .filter(|n| *n > 0)
                        });
                let threads = env_threads.unwrap_or_else(|| {
                    std::thread::available_parallelism()
                        .map(|n| n.get())
                        .unwrap_or(1)
                });
                if threads == 1 {
                    WeightFormat::Q8_0
                } else {
                    WeightFormat::F32
                }
            }
            concrete => concrete,
        }
    }
}

/// Prompt tokens are fed in chunks of this many, to bound the attention scratch memory.
const PREFILL_CHUNK: usize = 512;

/// What one call produced.
#[derive(Debug, Clone)]
pub struct Generation {
    pub text: String,
    pub prompt_tokens: u32,
    pub completion_tokens: u32,
    /// Time to process the prompt (up to the first logits).
    pub prefill: Duration,
    /// Time of the decoding steps.
    pub decode: Duration,
    /// How many of the completion tokens the grammar forced (fed without sampling).
    pub forced_tokens: u32,
    /// How many prompt tokens came from a kept key/value cache (not computed again).
    pub reused_tokens: u32,
}

pub struct Engine {
    pub model: EmbeddedModel,
    decoder: Decoder,
    pub tokenizer: ModelTokenizer,
    factory: ParserFactory,
    /// The key/value caches a prompt may start from.
    caches: PromptCaches,
    /// See [`crate::EmbeddedOptions::repeat_penalty`].
    pub repeat_penalty: f32,
}

/// How many of the model's own recent free-text choices the repetition penalty looks back over.
const REPEAT_WINDOW: usize = 64;

/// A grammar state that allows at least this many tokens is free text (a string's body); fewer
/// is a choice among names, numbers or punctuation.
const FREE_TEXT_TOKENS: usize = 4096;

/// How often the text being written is told (`Engine::generate`'s `written`).
pub const WRITTEN_EVERY: std::time::Duration = std::time::Duration::from_millis(200);

fn gen_err(context: &str) -> impl Fn(candle_core::Error) -> LlmError + '_ {
    move |e| LlmError::Generation(format!("{context}: {e}"))
}

fn unavailable(path: &Path) -> impl Fn(String) -> LlmError + '_ {
    move |e| LlmError::ModelUnavailable(format!("cannot load {}: {e}", path.display()))
}

impl Engine {
    pub fn load(
        path: &Path,
        model: EmbeddedModel,
        format: WeightFormat,
    ) -> Result<Engine, LlmError> {
        let t0 = Instant::now();
        let bad = unavailable(path);
        let device = Device::Cpu;
        let mut file = File::open(path).map_err(|e| bad(e.to_string()))?;
        let ct = gguf_file::Content::read(&mut file).map_err(|e| bad(e.to_string()))?;
        let arch = ct
            .metadata
            .get("general.architecture")
            .and_then(|v| v.to_string().ok())
            .cloned()
            .unwrap_or_default();
        let expected = match model.architecture() {
            Architecture::Llama => "llama",
            Architecture::Qwen2 => "qwen2",
        };
        if arch != expected {
            return Err(bad(format!(
                "architecture `{arch}`, but {} is `{expected}`",
                model.name()
            )));
        }
        // candle lists the dims outermost first: (vocab, hidden).
        let n_logits = match ct
            .tensor_infos
            .get("token_embd.weight")
            .map(|i| i.shape.dims())
        {
            Some([n, _hidden]) => *n,
            other => return Err(bad(format!("token_embd.weight has shape {other:?}"))),
        };
        let tokenizer = ModelTokenizer::from_gguf(&ct, model, n_logits).map_err(&bad)?;
        let format = format.resolve(model);
        let arch = model.architecture();
        let decoder = match format {
            WeightFormat::Auto | WeightFormat::AsStored => {
                Decoder::from_gguf(arch, &ct, &mut file, &device)
            }
            WeightFormat::Q8_0 | WeightFormat::F32 | WeightFormat::FastKernels => {
                let (dtype, keep): (GgmlDType, fn(GgmlDType) -> bool) = match format {
                    WeightFormat::F32 => (GgmlDType::F32, |src| src == GgmlDType::F32),
                    WeightFormat::FastKernels => (GgmlDType::Q8_0, has_fast_kernel),
                    _ => (GgmlDType::Q8_0, |src| {
                        matches!(src, GgmlDType::Q8_0 | GgmlDType::F32)
                    }),
                };
                convert(ct, &mut file, dtype, keep, &device).and_then(|mut c| {
                    let ct = gguf_file::Content::read(&mut c)?;
                    Decoder::from_gguf(arch, &ct, &mut c, &device)
                })
            }
        }
        .map_err(|e| bad(e.to_string()))?;
        let mut factory = ParserFactory::new_simple(&tokenizer.tok_env)
            .map_err(|e| bad(format!("llguidance: {e}")))?;
        // Grammar errors are returned to the caller; do not also print them.
        factory.quiet();
        tracing::info!(
            path = %path.display(),
            model = model.name(),
            ?format,
            load_ms = t0.elapsed().as_millis() as u64,
            "embedded model loaded"
        );
        Ok(Engine {
            model,
            decoder,
            tokenizer,
            factory,
            caches: PromptCaches::default(),
            repeat_penalty: 1.0,
        })
    }

    /// Keeps the prompts' fixed beginnings in `store` too, and reads them back from it.
    pub fn with_store(mut self, store: PromptStore) -> Engine {
        self.caches = PromptCaches::with_store(store);
        self
    }

    /// The cache to start `prompt` from (see [`PromptCaches::take`]).
    fn take_cache(&self, prompt: &[u32]) -> KvCache {
        let feed = |tokens: &[u32], cache: &mut KvCache| {
            self.forward(tokens, cache)
                .map(|_| ())
                .map_err(|e| e.to_string())
        };
        self.caches.take(prompt, &feed)
    }

    /// Asks for `beginning` (a prompts' fixed beginning) to be stored once a call has computed
    /// it: for a warm-up that gives way to a waiting call.
    pub fn store_when_computed(&self, beginning: &PromptBeginning) -> Result<(), LlmError> {
        let tokens = self.beginning_tokens(beginning)?;
        self.caches.store_when_computed(tokens);
        Ok(())
    }

    /// Renders and tokenizes the request's prompt.
    pub fn prompt_tokens(&self, request: &ChatRequest) -> Result<Vec<u32>, LlmError> {
        let segments = chatml_segments(&request.messages, true, self.model.default_system_prompt());
        self.tokenizer
            .encode_segments(&segments)
            .map_err(LlmError::Generation)
    }

    /// Computes the keys and values of `beginning` (no generation prompt: the beginning of later
    /// prompts), keeps them and stores them; returns how many tokens were computed.
    pub fn warm_up(&self, beginning: &PromptBeginning) -> Result<usize, LlmError> {
        let tokens = self.beginning_tokens(beginning)?;
        if tokens.is_empty() || tokens.len() >= self.decoder.window {
            return Ok(0);
        }
        let mut cache = self.take_cache(&tokens);
        let start = cache.tokens().len();
        for chunk in tokens[start..].chunks(PREFILL_CHUNK) {
            self.forward(chunk, &mut cache)?;
        }
        self.caches.store_beginning(&cache, tokens.len());
        self.caches.keep(cache);
        Ok(tokens.len() - start)
    }

    /// The tokens of `beginning` as later prompts begin: its messages, then the user turn opened
    /// with its opening (no generation prompt).
    fn beginning_tokens(&self, beginning: &PromptBeginning) -> Result<Vec<u32>, LlmError> {
        let mut segments = chatml_segments(
            &beginning.messages,
            false,
            self.model.default_system_prompt(),
        );
        if !beginning.user_opening.is_empty() {
            segments.extend(open_user_turn(&beginning.user_opening));
        }
        self.tokenizer
            .encode_segments(&segments)
            .map_err(LlmError::Generation)
    }

    /// One chat completion. `cancel` is polled between steps: when set, the call stops with
    /// `LlmError::Generation("cancelled")`. `written` is told the text so far as it grows, at
    /// most every [`WRITTEN_EVERY`] (decoding the whole text each time costs far less than a
    /// step).
    pub fn generate(
        &self,
        request: &ChatRequest,
        cancel: &AtomicBool,
        written: Option<&dyn Fn(String)>,
    ) -> Result<Generation, LlmError> {
        let prompt = self.prompt_tokens(request)?;
        let window = self.decoder.window;
        if prompt.len() >= window {
            return Err(LlmError::Generation(format!(
                "the prompt has {} tokens; the embedded model's window is {window}",
                prompt.len()
            )));
        }
        let mut cache = self.take_cache(&prompt);
        let result = self.generate_with(request, &prompt, &mut cache, cancel, written);
        // A cache left by a failed step may be inconsistent; a finished or cancelled one is not.
        if result.is_ok() || matches!(&result, Err(LlmError::Truncated(_))) {
            self.caches.store_asked(&cache);
            self.caches.keep(cache);
        }
        result
    }

    fn generate_with(
        &self,
        request: &ChatRequest,
        prompt: &[u32],
        cache: &mut KvCache,
        cancel: &AtomicBool,
        written: Option<&dyn Fn(String)>,
    ) -> Result<Generation, LlmError> {
        let max_tokens = request.max_tokens as usize;
        let window = self.decoder.window;
        let mut matcher = match &request.schema {
            Some(s) => Some(self.matcher(&s.schema)?),
            None => None,
        };
        let mut rng = SplitMix64::new(request.seed.unwrap_or_else(time_seed));
        let temperature = request.temperature;
        let real_vocab = self.tokenizer.real_vocab;

        let t0 = Instant::now();
        let reused = cache.tokens().len();
        let mut hidden = None;
        for chunk in prompt[reused..].chunks(PREFILL_CHUNK) {
            if cancel.load(Ordering::Relaxed) {
                return Err(LlmError::Generation("cancelled".to_string()));
            }
            hidden = Some(self.forward(chunk, cache)?);
        }
        // `take_cache` always leaves at least the prompt's last token to feed.
        let Some(mut hidden) = hidden else {
            return Err(LlmError::Generation("an empty prompt".to_string()));
        };
        let prefill = t0.elapsed();

        let t1 = Instant::now();
        let mut out: Vec<u32> = Vec::new();
        // The free-text tokens the model chose (not forced, not enum values): what the penalty
        // counts.
        let mut chosen: Vec<u32> = Vec::new();
        let mut forced = 0u32;
        let mut told_at = Instant::now();
        let finished = loop {
            if cancel.load(Ordering::Relaxed) {
                return Err(LlmError::Generation("cancelled".to_string()));
            }
            if out.len() >= max_tokens {
                // At the limit: complete only if the grammar is satisfied (nothing can follow).
                break match &mut matcher {
                    Some(m) => m.is_accepting().unwrap_or(false),
                    None => false,
                };
            }
            let recent = &chosen[chosen.len().saturating_sub(REPEAT_WINDOW)..];
            let next = match &mut matcher {
                Some(m) => {
                    let mask = m
                        .compute_mask()
                        .map_err(|e| LlmError::Generation(format!("grammar: {e}")))?;
                    // Free text (the reasoning) only: where the grammar offers a handful of
                    // names, choosing the same one again ("arm_takeoff" for every drone) is
                    // right, not a loop.
                    let free_text = mask.num_set() >= FREE_TEXT_TOKENS;
                    let logits = if free_text {
                        let mut logits = self.logits(&hidden, None)?;
                        penalise_repeats(&mut logits, recent, self.repeat_penalty);
                        logits
                    } else {
                        // Only the rows the grammar allows are needed (`OutputProjection`).
                        let mut allowed = Vec::with_capacity(mask.num_set());
                        mask.iter_set_entries(|i| allowed.push(i));
                        self.logits(&hidden, Some(&allowed))?
                    };
                    let next = sample(&logits, real_vocab, Some(&mask), temperature, &mut rng);
                    if free_text {
                        chosen.extend(next);
                    }
                    next
                }
                None => {
                    let mut logits = self.logits(&hidden, None)?;
                    penalise_repeats(&mut logits, recent, self.repeat_penalty);
                    let next = sample(&logits, real_vocab, None, temperature, &mut rng);
                    chosen.extend(next);
                    next
                }
            };
            let Some(next) = next else {
                return Err(LlmError::Generation(
                    "the grammar allows no token".to_string(),
                ));
            };
            if self.tokenizer.is_end(next) {
                break true;
            }
            let mut feed = vec![next];
            if let Some(m) = &mut matcher {
                m.consume_token(next)
                    .map_err(|e| LlmError::Generation(format!("grammar: {e}")))?;
                if !m.is_stopped() {
                    let ff = m.consume_ff_tokens();
                    forced += ff.len() as u32;
                    feed.extend(ff);
                }
            }
            out.extend_from_slice(&feed);
            if let Some(written) = written
                && told_at.elapsed() >= WRITTEN_EVERY
            {
                told_at = Instant::now();
                written(self.tokenizer.decode(&out));
            }
            if matcher.as_ref().is_some_and(Matcher::is_stopped) {
                break out.len() <= max_tokens;
            }
            if out.len() > max_tokens {
                break false;
            }
            if cache.tokens().len() + feed.len() >= window {
                break false;
            }
            hidden = self.forward(&feed, cache)?;
        };
        let decode = t1.elapsed();
        if let Some(m) = &matcher
            && let Some(e) = m.get_error()
        {
            return Err(LlmError::Generation(format!("grammar: {e}")));
        }
        if !finished {
            return Err(LlmError::Truncated(request.max_tokens));
        }
        Ok(Generation {
            text: self.tokenizer.decode(&out),
            prompt_tokens: prompt.len() as u32,
            completion_tokens: out.len() as u32,
            prefill,
            decode,
            forced_tokens: forced,
            reused_tokens: reused as u32,
        })
    }

    fn matcher(&self, schema: &serde_json::Value) -> Result<Matcher, LlmError> {
        let mut schema = schema.clone();
        // Compact, fixed whitespace unless the caller chose otherwise: a small model given free
        // whitespace tends to spend its budget on newlines. No space after `,` and `:`, as the
        // few-shot replies are written (`serde_json`'s compact form). With `", "` and `": "`
        // the model wrote in a layout its examples never showed, and in the models bench the
        // 1.5B model's cold Coordinator planned take-offs for 3 of 6 drones where llama.cpp's
        // (which wrote compact JSON) planned all 6; compact, both give the same answers.
        if let Some(obj) = schema.as_object_mut()
            && !obj.contains_key("x-guidance")
        {
            obj.insert(
                "x-guidance".to_string(),
                serde_json::json!({
                    "whitespace_flexible": false,
                    "item_separator": ",",
                    "key_separator": ":",
                }),
            );
        }
        let grammar = TopLevelGrammar::from_json_schema(schema);
        let m = Matcher::new(self.factory.create_parser(grammar));
        if let Some(e) = m.get_error() {
            return Err(LlmError::Generation(format!(
                "the JSON schema cannot be compiled to a grammar: {e}"
            )));
        }
        Ok(m)
    }

    fn forward(&self, tokens: &[u32], cache: &mut KvCache) -> Result<Tensor, LlmError> {
        self.decoder
            .forward(tokens, cache)
            .map_err(gen_err("forward"))
    }

    fn logits(&self, hidden: &Tensor, only: Option<&[usize]>) -> Result<Vec<f32>, LlmError> {
        self.decoder
            .logits(hidden, only)
            .map_err(gen_err("output projection"))
    }
}

/// Whether candle multiplies matrices of this format with AVX2 (else scalar code).
fn has_fast_kernel(src: GgmlDType) -> bool {
    use GgmlDType::*;
    matches!(
        src,
        Q2K | Q3K | Q4K | Q5K | Q6K | Q8K | Q4_0 | Q8_0 | F32 | F16 | BF16
    )
}

/// Reads every tensor, converts the matrices whose format `keep` refuses to `dtype`, and writes a
/// GGUF image in memory that the decoder reads back.
fn convert<R: Read + Seek>(
    ct: gguf_file::Content,
    file: &mut R,
    dtype: GgmlDType,
    keep: fn(GgmlDType) -> bool,
    device: &Device,
) -> candle_core::Result<Cursor<Vec<u8>>> {
    let mut names: Vec<&String> = ct.tensor_infos.keys().collect();
    names.sort();
    let mut tensors: Vec<(&str, QTensor)> = Vec::with_capacity(names.len());
    for name in names {
        let qt = ct.tensor(file, name, device)?;
        let src = qt.dtype();
        let matrix = qt.shape().rank() == 2;
        let qt = if matrix && src != dtype && !keep(src) {
            let t = qt.dequantize(device)?;
            QTensor::quantize(&t, dtype)?
        } else {
            qt
        };
        tensors.push((name.as_str(), qt));
    }
    let metadata: Vec<(&str, &gguf_file::Value)> =
        ct.metadata.iter().map(|(k, v)| (k.as_str(), v)).collect();
    let refs: Vec<(&str, &QTensor)> = tensors.iter().map(|(n, t)| (*n, t)).collect();
    let mut buf = Cursor::new(Vec::new());
    gguf_file::write(&mut buf, &metadata, &refs)?;
    buf.set_position(0);
    Ok(buf)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weight_format_names() {
        assert_eq!(WeightFormat::parse("Q8_0"), Some(WeightFormat::Q8_0));
        assert_eq!(WeightFormat::parse("f32"), Some(WeightFormat::F32));
        assert_eq!(WeightFormat::parse("q4_1"), Some(WeightFormat::AsStored));
        assert_eq!(WeightFormat::parse("auto"), Some(WeightFormat::Auto));
        assert_eq!(WeightFormat::parse("q5"), None);
        let smol = EmbeddedModel::SmolLm2_135M;
        assert_ne!(WeightFormat::Auto.resolve(smol), WeightFormat::Auto);
        assert_eq!(WeightFormat::F32.resolve(smol), WeightFormat::F32);
        assert_eq!(
            WeightFormat::Auto.resolve(EmbeddedModel::QwenCoder1_5B),
            WeightFormat::FastKernels
        );
    }
}

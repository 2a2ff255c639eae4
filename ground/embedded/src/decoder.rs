//! The transformer itself, for the two GGUF architectures the catalogue holds (`llama`:
//! SmolLM2; `qwen2`: Qwen2.5-Coder), built on candle's quantized matrix products.
//!
//! Why not candle's own `quantized_llama` / `quantized_qwen2`: their key/value cache is private
//! state inside the model, so a call can only start from nothing. Here the cache is a value
//! ([`KvCache`]) that the caller keeps and cuts back to the prefix a new prompt shares with the
//! last one, so the fixed part of the mission prompts (system text, few-shot turns, the map) is
//! computed once, not on every call. The decoder itself is immutable and shared.

use candle_core::quantized::{QTensor, gguf_file};
use candle_core::{DType, Device, IndexOp, Module, Result, Tensor};
use candle_nn::Embedding;

use crate::catalogue::Architecture;
use crate::decode_attention::decode_attention;
use crate::matvec::Linear;
use crate::output::{BLOCK_ROWS, OutputProjection};

/// The longest sequence (prompt and reply) a call may have, whatever the model was trained for:
/// bounds the rotary tables and the key/value cache (Qwen2.5-Coder-1.5B: 28 KB per token).
pub const MAX_WINDOW: usize = 8192;

struct Layer {
    attn_norm: RmsNorm,
    wq: Linear,
    wk: Linear,
    wv: Linear,
    /// Qwen2 has biases on the query, key and value projections; Llama has none.
    bq: Option<Tensor>,
    bk: Option<Tensor>,
    bv: Option<Tensor>,
    wo: Linear,
    ffn_norm: RmsNorm,
    w_gate: Linear,
    w_up: Linear,
    w_down: Linear,
}

/// The weights and shape of one model.
pub struct Decoder {
    embed: Embedding,
    layers: Vec<Layer>,
    norm: RmsNorm,
    output: OutputProjection,
    cos: Tensor,
    sin: Tensor,
    n_head: usize,
    n_kv_head: usize,
    head_dim: usize,
    /// Qwen2 rotates the two halves of each head (NeoX); GGUF Llama rotates interleaved pairs.
    rope_neox: bool,
    /// The longest sequence this decoder takes (the model's context, at most [`MAX_WINDOW`]).
    pub window: usize,
}

/// The keys and values of the tokens fed so far, per layer, and those tokens.
///
/// Each layer's keys and values live in buffers with room to spare (batch, key/value heads,
/// capacity, head size), positions `..tokens.len()` filled: a new token's keys and values are
/// written in place. Growing the cache by concatenation instead copied all of it for every
/// generated token (86 MB a token at 1,500 positions for Qwen2.5-Coder-1.5B). Writing in place
/// means two caches must never share a buffer: there is no `Clone`, [`KvCache::prefix_copy`]
/// copies.
#[derive(Default)]
pub struct KvCache {
    layers: Vec<Option<(Tensor, Tensor)>>,
    tokens: Vec<u32>,
}

/// The smallest room a buffer is given (positions).
const MIN_CAPACITY: usize = 512;

/// The type the cache holds keys and values in. bf16, not f32: a decode step's attention reads
/// the whole cache (2,000 positions of Qwen2.5-Coder-1.5B: 115 MB in f32), and bf16 is what
/// the AMX tiles multiply (`prompt_attention`). The model's own training type; the keys and
/// values are rounded once, when written.
pub const KV_DTYPE: DType = DType::BF16;

impl KvCache {
    /// The tokens whose keys and values are held, in order.
    pub fn tokens(&self) -> &[u32] {
        &self.tokens
    }

    /// Each layer's key and value buffers (positions `..tokens().len()` filled).
    pub fn layers(&self) -> &[Option<(Tensor, Tensor)>] {
        &self.layers
    }

    /// A cache of these buffers holding `tokens` (read back from disk: `prompt_store`).
    pub fn from_layers(layers: Vec<Option<(Tensor, Tensor)>>, tokens: Vec<u32>) -> KvCache {
        KvCache { layers, tokens }
    }

    /// Forgets the positions from `n` on: the next tokens are written over them.
    pub fn truncate(&mut self, n: usize) {
        self.tokens.truncate(n);
    }

    /// A cache of its own holding the first `n` tokens (all, when `n` is larger).
    pub fn prefix_copy(&self, n: usize) -> Result<KvCache> {
        let n = n.min(self.tokens.len());
        if n == 0 {
            return Ok(KvCache::default());
        }
        let copy = |t: &Tensor| t.narrow(2, 0, n)?.contiguous();
        let layers = self
            .layers
            .iter()
            .map(|kv| match kv {
                Some((k, v)) => Ok(Some((copy(k)?, copy(v)?))),
                None => Ok(None),
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(KvCache {
            layers,
            tokens: self.tokens[..n].to_vec(),
        })
    }
}

/// Writes `k` and `v` (batch, heads, seq, head size) at position `pos` of a layer's buffers,
/// growing them (up to `window` positions) when they are full; returns the filled positions
/// `..pos + seq` of both.
fn append_kv(
    slot: &mut Option<(Tensor, Tensor)>,
    k: &Tensor,
    v: &Tensor,
    pos: usize,
    window: usize,
) -> Result<(Tensor, Tensor)> {
    let end = pos + k.dim(2)?;
    let (k, v) = (&k.to_dtype(KV_DTYPE)?, &v.to_dtype(KV_DTYPE)?);
    let capacity = match slot {
        Some((kb, _)) => kb.dim(2)?,
        None => 0,
    };
    if end > capacity {
        let room = (end + end / 2).max(MIN_CAPACITY).min(window).max(end);
        let grow = |old: Option<&Tensor>, new: &Tensor| -> Result<Tensor> {
            let (b, h, _, d) = new.dims4()?;
            let buffer = Tensor::zeros((b, h, room, d), new.dtype(), new.device())?;
            if let Some(old) = old
                && pos > 0
            {
                buffer.slice_set(&old.narrow(2, 0, pos)?.contiguous()?, 2, 0)?;
            }
            Ok(buffer)
        };
        let old = slot.take();
        *slot = Some((
            grow(old.as_ref().map(|(kb, _)| kb), k)?,
            grow(old.as_ref().map(|(_, vb)| vb), v)?,
        ));
    }
    let Some((kb, vb)) = slot.as_ref() else {
        candle_core::bail!("the key/value buffers were not made");
    };
    kb.slice_set(&k.contiguous()?, 2, pos)?;
    vb.slice_set(&v.contiguous()?, 2, pos)?;
    Ok((kb.narrow(2, 0, end)?, vb.narrow(2, 0, end)?))
}

fn md_u32(ct: &gguf_file::Content, key: &str) -> Result<usize> {
    match ct.metadata.get(key) {
        Some(v) => Ok(v.to_u32()? as usize),
        None => candle_core::bail!("GGUF metadata has no `{key}`"),
    }
}

fn md_f32(ct: &gguf_file::Content, key: &str) -> Option<f32> {
    ct.metadata.get(key).and_then(|v| v.to_f32().ok())
}

impl Decoder {
    pub fn from_gguf<R: std::io::Seek + std::io::Read>(
        arch: Architecture,
        ct: &gguf_file::Content,
        reader: &mut R,
        device: &Device,
    ) -> Result<Decoder> {
        let p = match arch {
            Architecture::Llama => "llama",
            Architecture::Qwen2 => "qwen2",
        };
        let n_head = md_u32(ct, &format!("{p}.attention.head_count"))?;
        let n_kv_head = md_u32(ct, &format!("{p}.attention.head_count_kv"))?;
        let hidden = md_u32(ct, &format!("{p}.embedding_length"))?;
        let n_layer = md_u32(ct, &format!("{p}.block_count"))?;
        let context = md_u32(ct, &format!("{p}.context_length"))?;
        let eps =
            md_f32(ct, &format!("{p}.attention.layer_norm_rms_epsilon")).unwrap_or(1e-6) as f64;
        let rope_base = md_f32(ct, &format!("{p}.rope.freq_base")).unwrap_or(10_000.0);
        if n_head == 0 || n_kv_head == 0 || n_head % n_kv_head != 0 || hidden % n_head != 0 {
            candle_core::bail!(
                "inconsistent heads: {n_head} query, {n_kv_head} key/value, width {hidden}"
            );
        }
        let head_dim = hidden / n_head;
        let window = context.min(MAX_WINDOW);

        let tensor = |name: &str, r: &mut R| ct.tensor(r, name, device);
        let embed_q = tensor("token_embd.weight", reader)?;
        let embed = Embedding::new(embed_q.dequantize(device)?, hidden);
        let output = match tensor("output.weight", reader) {
            Ok(w) => w,
            // Tied embeddings: the input table is also the output matrix.
            Err(_) => tensor("token_embd.weight", reader)?,
        };
        let output = OutputProjection::new(output, BLOCK_ROWS)?;
        let norm = RmsNorm::from_qtensor(tensor("output_norm.weight", reader)?, eps)?;
        let bias = |name: String, r: &mut R| -> Result<Option<Tensor>> {
            match arch {
                Architecture::Llama => Ok(None),
                Architecture::Qwen2 => Ok(Some(ct.tensor(r, &name, device)?.dequantize(device)?)),
            }
        };
        let mut layers = Vec::with_capacity(n_layer);
        for i in 0..n_layer {
            let b = format!("blk.{i}");
            let q = |name: &str, r: &mut R| -> Result<Linear> {
                Linear::new(ct.tensor(r, &format!("{b}.{name}.weight"), device)?)
            };
            let n = |name: &str, r: &mut R| -> Result<RmsNorm> {
                let t: QTensor = ct.tensor(r, &format!("{b}.{name}.weight"), device)?;
                RmsNorm::from_qtensor(t, eps)
            };
            layers.push(Layer {
                attn_norm: n("attn_norm", reader)?,
                wq: q("attn_q", reader)?,
                wk: q("attn_k", reader)?,
                wv: q("attn_v", reader)?,
                bq: bias(format!("{b}.attn_q.bias"), reader)?,
                bk: bias(format!("{b}.attn_k.bias"), reader)?,
                bv: bias(format!("{b}.attn_v.bias"), reader)?,
                wo: q("attn_output", reader)?,
                ffn_norm: n("ffn_norm", reader)?,
                w_gate: q("ffn_gate", reader)?,
                w_up: q("ffn_up", reader)?,
                w_down: q("ffn_down", reader)?,
            });
        }
        let (cos, sin) = rotary_tables(head_dim, rope_base, window, device)?;
        Ok(Decoder {
            embed,
            layers,
            norm,
            output,
            cos,
            sin,
            n_head,
            n_kv_head,
            head_dim,
            rope_neox: arch == Architecture::Qwen2,
            window,
        })
    }

    /// Feeds `tokens` after those in `cache` and returns the last one's final hidden state
    /// (1 × width), which [`Decoder::logits`] turns into the logits of the next token.
    /// On an error the cache may be inconsistent: drop it.
    pub fn forward(&self, tokens: &[u32], cache: &mut KvCache) -> Result<Tensor> {
        let pos = cache.tokens.len();
        let seq = tokens.len();
        if seq == 0 {
            candle_core::bail!("nothing to feed");
        }
        if pos + seq > self.window {
            candle_core::bail!("{} tokens exceed the window of {}", pos + seq, self.window);
        }
        let device = self.cos.device();
        if cache.layers.len() != self.layers.len() {
            cache.layers = vec![None; self.layers.len()];
        }
        let input = Tensor::new(tokens, device)?.unsqueeze(0)?;
        let mask = if seq > 1 {
            Some(causal_mask(seq, pos, device)?)
        } else {
            None
        };
        let cos = self.cos.narrow(0, pos, seq)?;
        let sin = self.sin.narrow(0, pos, seq)?;
        let mut x = self.embed.forward(&input)?;
        for (layer, kv) in self.layers.iter().zip(cache.layers.iter_mut()) {
            let h = layer.attn_norm.forward(&x)?;
            let a = self.attention(layer, &h, kv, pos, mask.as_ref(), &cos, &sin)?;
            let x1 = (x + a)?;
            let h = layer.ffn_norm.forward(&x1)?;
            let gate = candle_nn::ops::silu(&layer.w_gate.forward(&h)?)?;
            let m = layer.w_down.forward(&(gate * layer.w_up.forward(&h)?)?)?;
            x = (x1 + m)?;
        }
        cache.tokens.extend_from_slice(tokens);
        self.norm.forward(&x)?.i((.., seq - 1, ..))
    }

    /// The logits that follow `hidden` (from [`Decoder::forward`]): all of them, or with `only`
    /// at least those tokens' (see [`OutputProjection::logits`]), the others `-inf`.
    pub fn logits(&self, hidden: &Tensor, only: Option<&[usize]>) -> Result<Vec<f32>> {
        self.output.logits(hidden, only)
    }

    /// Attention of the tokens `x` at positions `pos..`, their keys and values added to `kv`.
    #[allow(clippy::too_many_arguments)]
    fn attention(
        &self,
        l: &Layer,
        x: &Tensor,
        kv: &mut Option<(Tensor, Tensor)>,
        pos: usize,
        mask: Option<&Tensor>,
        cos: &Tensor,
        sin: &Tensor,
    ) -> Result<Tensor> {
        let (b, seq, _) = x.dims3()?;
        let project = |w: &Linear, bias: &Option<Tensor>, heads: usize| -> Result<Tensor> {
            let mut t = w.forward(x)?;
            if let Some(bias) = bias {
                t = t.broadcast_add(bias)?;
            }
            t.reshape((b, seq, heads, self.head_dim))?
                .transpose(1, 2)?
                .contiguous()
        };
        let q = self.rope(&project(&l.wq, &l.bq, self.n_head)?, cos, sin)?;
        let k = self.rope(&project(&l.wk, &l.bk, self.n_kv_head)?, cos, sin)?;
        let v = project(&l.wv, &l.bv, self.n_kv_head)?;
        let (k, v) = append_kv(kv, &k, &v, pos, self.window)?;
        let y = match decode_attention(&q, &k, &v)? {
            Some(y) => y,
            None => match prompt_attention(&q, &k, &v)? {
                Some(y) => y,
                None => {
                    let (k, v) = (k.to_dtype(DType::F32)?, v.to_dtype(DType::F32)?);
                    grouped_attention(&q, &k, &v, mask, self.n_kv_head)?
                }
            },
        };
        l.wo.forward(&y)
    }

    fn rope(&self, x: &Tensor, cos: &Tensor, sin: &Tensor) -> Result<Tensor> {
        if self.rope_neox {
            candle_nn::rotary_emb::rope(x, cos, sin)
        } else {
            candle_nn::rotary_emb::rope_i(x, cos, sin)
        }
    }
}

/// The attention of many new tokens on AMX tiles where the CPU has them (`prompt_attention`),
/// else none: candle's products take them.
fn prompt_attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Option<Tensor>> {
    #[cfg(target_arch = "x86_64")]
    {
        crate::prompt_attention::prompt_attention(q, k, v)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (q, k, v);
        Ok(None)
    }
}

/// Attention of `q` (batch, query heads, seq, head size) over `k` and `v` (batch, key/value
/// heads, positions, head size; f32), `mask` added to the scores when given; (batch, seq,
/// width). Candle's products: what [`Decoder::forward`] falls back on where `decode_attention`
/// and `prompt_attention` do not run (a CPU without AVX-512 or AMX), and the tests' reference.
/// The mask is [`causal_mask`]'s for the `seq` new tokens, which the AVX-512 softmax
/// (`decode_attention::causal_softmax`) applies without reading it.
///
/// Grouped-query attention without copying each key/value head once per query head (candle's
/// `repeat_kv`, which at 2,000 positions copied about 700 MB per generated token): query head h
/// reads key/value head h / n_rep, and the n_rep query heads of one key/value head are adjacent,
/// so they are viewed as n_rep × seq rows of it.
pub(crate) fn grouped_attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    mask: Option<&Tensor>,
    n_kv_head: usize,
) -> Result<Tensor> {
    let (b, n_head, seq, head_dim) = q.dims4()?;
    let n_rep = n_head / n_kv_head;
    let q = q.reshape((b, n_kv_head, n_rep * seq, head_dim))?;
    let scores = q.matmul(&k.t()?)?;
    let total = scores.dim(3)?;
    // The mask given is the causal one (or none, for one new token): the same rows as
    // `causal_softmax` computes.
    if mask.is_some() || seq == 1 {
        let mut weights = scores.flatten_all()?.to_vec1::<f32>()?;
        let scale = 1.0 / (head_dim as f32).sqrt();
        if crate::decode_attention::causal_softmax(&mut weights, total, seq, scale) {
            let att = Tensor::from_vec(weights, scores.shape(), scores.device())?;
            return att
                .matmul(v)?
                .reshape((b, n_head, seq, head_dim))?
                .transpose(1, 2)?
                .reshape((b, seq, n_head * head_dim));
        }
    }
    let mut att = (scores / (head_dim as f64).sqrt())?;
    if let Some(mask) = mask {
        // The same mask for each query head of the group: broadcast over a group axis.
        att = att
            .reshape((b, n_kv_head, n_rep, seq, total))?
            .broadcast_add(&mask.unsqueeze(2)?)?
            .reshape((b, n_kv_head, n_rep * seq, total))?;
    }
    let att = candle_nn::ops::softmax_last_dim(&att)?;
    att.matmul(v)?
        .reshape((b, n_head, seq, head_dim))?
        .transpose(1, 2)?
        .reshape((b, seq, n_head * head_dim))
}

/// The rotary embedding's cosines and sines for positions `0..len`: `(len, head_dim / 2)`.
fn rotary_tables(
    head_dim: usize,
    base: f32,
    len: usize,
    device: &Device,
) -> Result<(Tensor, Tensor)> {
    let inv_freq: Vec<f32> = (0..head_dim)
        .step_by(2)
        .map(|i| 1.0 / base.powf(i as f32 / head_dim as f32))
        .collect();
    let n = inv_freq.len();
    let inv_freq = Tensor::from_vec(inv_freq, (1, n), device)?;
    let positions = Tensor::arange(0u32, len as u32, device)?
        .to_dtype(DType::F32)?
        .reshape((len, 1))?;
    let angles = positions.matmul(&inv_freq)?;
    Ok((angles.cos()?, angles.sin()?))
}

/// RMS normalisation by a weight vector (dequantized from the GGUF: one value per channel).
struct RmsNorm {
    weight: Tensor,
    eps: f32,
}

impl RmsNorm {
    fn from_qtensor(weight: QTensor, eps: f64) -> Result<RmsNorm> {
        Ok(RmsNorm {
            weight: weight.dequantize(&weight.device())?,
            eps: eps as f32,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        candle_nn::ops::rms_norm(x, &self.weight, self.eps)
    }
}

/// The additive causal mask of `seq` new positions after `past` cached ones (1 × 1 × seq ×
/// (past + seq)): 0 where new position i may look (every cached one, and new ones up to
/// itself), minus infinity where it would see a later token.
pub(crate) fn causal_mask(seq: usize, past: usize, device: &Device) -> Result<Tensor> {
    let total = past + seq;
    let mask: Vec<f32> = (0..seq)
        .flat_map(|i| {
            (0..total).map(move |j| {
                if j <= past + i {
                    0.0
                } else {
                    f32::NEG_INFINITY
                }
            })
        })
        .collect();
    Tensor::from_slice(&mask, (1, 1, seq, total), device)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each key/value head copied for the query heads that share it (head h reads head
    /// h / n_rep), as candle's own models do before attention.
    fn repeat_heads(kv: &Tensor, n_head: usize) -> Tensor {
        let n_rep = n_head / kv.dim(1).expect("4 dims");
        let heads: Vec<Tensor> = (0..n_head)
            .map(|h| kv.i((.., h / n_rep..h / n_rep + 1)).expect("head"))
            .collect();
        Tensor::cat(&heads, 1).expect("cat")
    }

    /// Attention as candle's own models compute it: each key/value head copied per query head.
    fn repeated_attention(q: &Tensor, k: &Tensor, v: &Tensor, mask: Option<&Tensor>) -> Tensor {
        let (b, n_head, seq, head_dim) = q.dims4().expect("4 dims");
        let k = repeat_heads(k, n_head);
        let v = repeat_heads(v, n_head).contiguous().expect("copy");
        let mut att =
            (q.matmul(&k.t().expect("t")).expect("q k") / (head_dim as f64).sqrt()).expect("scale");
        if let Some(mask) = mask {
            att = att.broadcast_add(mask).expect("mask");
        }
        let att = candle_nn::ops::softmax_last_dim(&att).expect("softmax");
        att.matmul(&v)
            .expect("att v")
            .transpose(1, 2)
            .expect("t")
            .reshape((b, seq, n_head * head_dim))
            .expect("reshape")
    }

    #[test]
    fn the_causal_mask_hides_later_tokens_only() {
        let mask = causal_mask(2, 1, &Device::Cpu).expect("mask");
        let rows: Vec<Vec<f32>> = mask
            .squeeze(0)
            .and_then(|m| m.squeeze(0))
            .expect("2 dims")
            .to_vec2()
            .expect("rows");
        let inf = f32::NEG_INFINITY;
        assert_eq!(rows, [[0.0, 0.0, inf], [0.0, 0.0, 0.0]]);
    }

    #[test]
    fn grouped_attention_is_the_attention_of_repeated_heads() {
        let device = Device::Cpu;
        // Qwen2.5-Coder-1.5B's shape (12 query heads over 2 key/value heads, 128 wide): a
        // prompt of 5 after 7 cached positions, with the causal mask, then one generated token.
        for (seq, past) in [(5, 7), (1, 12), (40, 100)] {
            let total = seq + past;
            let q = Tensor::randn(0f32, 1.0, (1, 12, seq, 128), &device).expect("q");
            let k = Tensor::randn(0f32, 1.0, (1, 2, total, 128), &device).expect("k");
            let v = Tensor::randn(0f32, 1.0, (1, 2, total, 128), &device).expect("v");
            let mask = (seq > 1).then(|| causal_mask(seq, past, &device).expect("mask"));
            let grouped = grouped_attention(&q, &k, &v, mask.as_ref(), 2).expect("attention");
            let repeated = repeated_attention(&q, &k, &v, mask.as_ref());
            assert_eq!(grouped.dims(), [1, seq, 12 * 128]);
            let diff = (grouped - repeated)
                .expect("diff")
                .abs()
                .expect("abs")
                .flatten_all()
                .expect("flat")
                .max(0)
                .expect("max")
                .to_scalar::<f32>()
                .expect("scalar");
            assert!(diff < 1e-5, "seq {seq}: differs by {diff}");
        }
    }

    /// Random keys or values (1, 2 heads, `seq`, 4) a bf16 holds exactly: the cache keeps
    /// them as they are.
    fn held_exactly(seq: usize, device: &Device) -> Tensor {
        Tensor::randn(0f32, 1.0, (1, 2, seq, 4), device)
            .and_then(|t| t.to_dtype(KV_DTYPE))
            .and_then(|t| t.to_dtype(DType::F32))
            .expect("chunk")
    }

    fn positions(t: &Tensor) -> Vec<f32> {
        t.to_dtype(DType::F32)
            .and_then(|t| t.flatten_all())
            .expect("flat")
            .to_vec1::<f32>()
            .expect("values")
    }

    #[test]
    fn keys_and_values_written_in_place_are_those_concatenated() {
        let device = Device::Cpu;
        let chunk = |seq| held_exactly(seq, &device);
        // A prompt of 300, 400 more (past the first buffer's room), then one at a time.
        let chunks: Vec<(Tensor, Tensor)> = [300, 400, 1, 1]
            .iter()
            .map(|seq| (chunk(*seq), chunk(*seq)))
            .collect();
        let mut slot = None;
        let mut pos = 0;
        for (i, (k, v)) in chunks.iter().enumerate() {
            let (k_all, v_all) = append_kv(&mut slot, k, v, pos, 2000).expect("append");
            pos += k.dim(2).expect("seq");
            let ks: Vec<&Tensor> = chunks[..=i].iter().map(|(k, _)| k).collect();
            let vs: Vec<&Tensor> = chunks[..=i].iter().map(|(_, v)| v).collect();
            assert_eq!(
                positions(&k_all),
                positions(&Tensor::cat(&ks, 2).expect("cat"))
            );
            assert_eq!(
                positions(&v_all),
                positions(&Tensor::cat(&vs, 2).expect("cat"))
            );
        }
        let room = slot.as_ref().map(|(k, _)| k.dim(2).expect("room"));
        assert_eq!(room, Some(1050), "grown once past 512, by half again");
        // The window bounds the room; the buffers still hold what they must.
        let mut slot = None;
        let (k, v) = (chunk(600), chunk(600));
        let (k_all, _) = append_kv(&mut slot, &k, &v, 0, 700).expect("append");
        assert_eq!(k_all.dims(), [1, 2, 600, 4]);
        assert_eq!(slot.map(|(k, _)| k.dim(2).expect("room")), Some(700));
    }

    #[test]
    fn a_prefix_copy_shares_nothing_with_its_cache() {
        let device = Device::Cpu;
        let chunk = |seq| held_exactly(seq, &device);
        let mut cache = KvCache::default();
        let (k, v) = (chunk(10), chunk(10));
        cache.layers = vec![None];
        append_kv(&mut cache.layers[0], &k, &v, 0, 100).expect("append");
        cache.tokens = (0..10).collect();
        let mut copy = cache.prefix_copy(4).expect("copy");
        assert_eq!(copy.tokens(), &[0, 1, 2, 3]);
        // Writing the copy's next positions leaves the cache's positions 4.. as they were.
        let (k2, v2) = (chunk(6), chunk(6));
        append_kv(&mut copy.layers[0], &k2, &v2, 4, 100).expect("append");
        let Some((k_kept, _)) = &cache.layers[0] else {
            panic!("the cache lost its layer");
        };
        assert_eq!(
            positions(&k_kept.narrow(2, 0, 10).expect("narrow")),
            positions(&k)
        );
        assert_eq!(cache.prefix_copy(0).expect("empty").tokens(), &[] as &[u32]);
    }
}

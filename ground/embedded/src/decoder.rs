//! The transformer itself, for the two GGUF architectures the catalogue holds (`llama`:
//! SmolLM2; `qwen2`: Qwen2.5-Coder), built on candle's quantized matrix products.
//!
//! Why not candle's own `quantized_llama` / `quantized_qwen2`: their key/value cache is private
//! state inside the model, so a call can only start from nothing. Here the cache is a value
//! ([`KvCache`]) that the caller keeps and cuts back to the prefix a new prompt shares with the
//! last one, so the fixed part of the mission prompts (system text, few-shot turns, the map) is
//! computed once, not on every call. The decoder itself is immutable and shared.

use candle_core::quantized::{QMatMul, QTensor, gguf_file};
use candle_core::{DType, Device, IndexOp, Module, Result, Tensor};
use candle_nn::Embedding;
use candle_transformers::quantized_nn::RmsNorm;
use candle_transformers::utils::build_additive_causal_mask;

use crate::catalogue::Architecture;

/// The longest sequence (prompt and reply) a call may have, whatever the model was trained for:
/// bounds the rotary tables and the key/value cache (Qwen2.5-Coder-1.5B: 57 KB per token).
pub const MAX_WINDOW: usize = 8192;

struct Layer {
    attn_norm: RmsNorm,
    wq: QMatMul,
    wk: QMatMul,
    wv: QMatMul,
    /// Qwen2 has biases on the query, key and value projections; Llama has none.
    bq: Option<Tensor>,
    bk: Option<Tensor>,
    bv: Option<Tensor>,
    wo: QMatMul,
    ffn_norm: RmsNorm,
    w_gate: QMatMul,
    w_up: QMatMul,
    w_down: QMatMul,
}

/// The weights and shape of one model.
pub struct Decoder {
    embed: Embedding,
    layers: Vec<Layer>,
    norm: RmsNorm,
    output: QMatMul,
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
#[derive(Clone, Default)]
pub struct KvCache {
    layers: Vec<Option<(Tensor, Tensor)>>,
    tokens: Vec<u32>,
}

impl KvCache {
    /// The tokens whose keys and values are held, in order.
    pub fn tokens(&self) -> &[u32] {
        &self.tokens
    }

    /// Keeps the first `n` tokens (all, when `n` is larger).
    pub fn truncate(&mut self, n: usize) -> Result<()> {
        if n >= self.tokens.len() {
            return Ok(());
        }
        if n == 0 {
            self.clear();
            return Ok(());
        }
        for (k, v) in self.layers.iter_mut().flatten() {
            *k = k.narrow(2, 0, n)?;
            *v = v.narrow(2, 0, n)?;
        }
        self.tokens.truncate(n);
        Ok(())
    }

    pub fn clear(&mut self) {
        self.layers.clear();
        self.tokens.clear();
    }
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
            Ok(w) => QMatMul::from_qtensor(w)?,
            // Tied embeddings: the input table is also the output matrix.
            Err(_) => QMatMul::from_qtensor(tensor("token_embd.weight", reader)?)?,
        };
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
            let q = |name: &str, r: &mut R| -> Result<QMatMul> {
                QMatMul::from_qtensor(ct.tensor(r, &format!("{b}.{name}.weight"), device)?)
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

    /// Feeds `tokens` after those in `cache` and returns the logits that follow the last one.
    /// On an error the cache may be inconsistent: clear it.
    pub fn forward(&self, tokens: &[u32], cache: &mut KvCache) -> Result<Vec<f32>> {
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
            Some(build_additive_causal_mask(
                seq,
                pos,
                None,
                device,
                DType::F32,
            )?)
        } else {
            None
        };
        let cos = self.cos.narrow(0, pos, seq)?;
        let sin = self.sin.narrow(0, pos, seq)?;
        let mut x = self.embed.forward(&input)?;
        for (layer, kv) in self.layers.iter().zip(cache.layers.iter_mut()) {
            let h = layer.attn_norm.forward(&x)?;
            let a = self.attention(layer, &h, kv, mask.as_ref(), &cos, &sin)?;
            let x1 = (x + a)?;
            let h = layer.ffn_norm.forward(&x1)?;
            let gate = candle_nn::ops::silu(&layer.w_gate.forward(&h)?)?;
            let m = layer.w_down.forward(&(gate * layer.w_up.forward(&h)?)?)?;
            x = (x1 + m)?;
        }
        cache.tokens.extend_from_slice(tokens);
        let last = self.norm.forward(&x)?.i((.., seq - 1, ..))?;
        self.output
            .forward(&last)?
            .squeeze(0)?
            .to_dtype(DType::F32)?
            .to_vec1::<f32>()
    }

    fn attention(
        &self,
        l: &Layer,
        x: &Tensor,
        kv: &mut Option<(Tensor, Tensor)>,
        mask: Option<&Tensor>,
        cos: &Tensor,
        sin: &Tensor,
    ) -> Result<Tensor> {
        let (b, seq, _) = x.dims3()?;
        let project = |w: &QMatMul, bias: &Option<Tensor>, heads: usize| -> Result<Tensor> {
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
        let (k, v) = match kv.take() {
            Some((k0, v0)) => (Tensor::cat(&[&k0, &k], 2)?, Tensor::cat(&[&v0, &v], 2)?),
            None => (k, v),
        };
        *kv = Some((k.clone(), v.clone()));
        let y = grouped_attention(&q, &k, &v, mask, self.n_kv_head)?;
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

/// Attention of `q` (batch, query heads, seq, head size) over `k` and `v` (batch, key/value
/// heads, positions, head size), `mask` added to the scores when given; (batch, seq, width).
///
/// Grouped-query attention without copying each key/value head once per query head (candle's
/// `repeat_kv`, which at 2,000 positions copied about 700 MB per generated token): query head h
/// reads key/value head h / n_rep, and the n_rep query heads of one key/value head are adjacent,
/// so they are viewed as n_rep × seq rows of it.
fn grouped_attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    mask: Option<&Tensor>,
    n_kv_head: usize,
) -> Result<Tensor> {
    let (b, n_head, seq, head_dim) = q.dims4()?;
    let n_rep = n_head / n_kv_head;
    let q = q.reshape((b, n_kv_head, n_rep * seq, head_dim))?;
    let mut att = (q.matmul(&k.t()?)? / (head_dim as f64).sqrt())?;
    if let Some(mask) = mask {
        // The same mask for each query head of the group: broadcast over a group axis.
        let total = att.dim(3)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use candle_transformers::utils::repeat_kv;

    /// Attention as candle's own models compute it: each key/value head copied per query head.
    fn repeated_attention(q: &Tensor, k: &Tensor, v: &Tensor, mask: Option<&Tensor>) -> Tensor {
        let (b, n_head, seq, head_dim) = q.dims4().expect("4 dims");
        let n_rep = n_head / k.dim(1).expect("4 dims");
        let k = repeat_kv(k.clone(), n_rep).expect("repeat");
        let v = repeat_kv(v.clone(), n_rep)
            .expect("repeat")
            .contiguous()
            .expect("copy");
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
    fn grouped_attention_is_the_attention_of_repeated_heads() {
        let device = Device::Cpu;
        // Qwen2.5-Coder-1.5B's shape (12 query heads over 2 key/value heads, 128 wide): a
        // prompt of 5 after 7 cached positions, with the causal mask, then one generated token.
        for (seq, past) in [(5, 7), (1, 12)] {
            let total = seq + past;
            let q = Tensor::randn(0f32, 1.0, (1, 12, seq, 128), &device).expect("q");
            let k = Tensor::randn(0f32, 1.0, (1, 2, total, 128), &device).expect("k");
            let v = Tensor::randn(0f32, 1.0, (1, 2, total, 128), &device).expect("v");
            let mask = (seq > 1).then(|| {
                build_additive_causal_mask(seq, past, None, &device, DType::F32).expect("mask")
            });
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
}

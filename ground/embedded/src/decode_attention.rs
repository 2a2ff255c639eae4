//! Attention of a decode step's few new tokens over the key/value cache, read in place from the
//! cache's buffers.
//!
//! Why not candle's ([`crate::decoder`]'s `grouped_attention`, which prompts still use): for one
//! token at 2,000 positions it took about 1 ms a layer, 28 ms of a ~95 ms step of Qwen2.5-Coder-
//! 1.5B (timers around it in the Coordinator call of the models bench's probes), though the
//! step's attention reads 4 MB and does 6 M multiply-adds a layer. Here each key/value head is
//! one task on candle's thread pool; each key row is read once for all the query rows of its
//! group (the group's query heads × the new tokens), each value row once per query row from
//! cache, the softmax's exponentials 16 at a time; the arithmetic is AVX-512 (on other CPUs
//! candle's attention is used). Measured with the same probes: the cached Coordinator call
//! 8.1–9.3 s before, 6.5–6.8 s after (179 tokens, 81 steps).
//!
//! The cache holds bf16 (`decoder::KV_DTYPE`): each key and value row is widened to f32 as it
//! is read, the queries stay f32. More new tokens take `prompt_attention` (AMX tiles) where
//! the CPU has them, else candle's products with this module's softmax ([`causal_softmax`]:
//! a restarted Supervisor call's 259 prompt tokens at 1,541 cached positions 2.8–3.0 → 2.5 s
//! before the tiles).

use candle_core::{Result, Tensor};

use crate::cache_view::{Shape, attend_in_place};
use crate::pool::Shared;

/// The most new tokens a step may feed here; more (a prompt) use candle's attention.
pub const MAX_TOKENS: usize = 8;

/// Lanes of the arithmetic: a 512-bit vector of f32.
const LANES: usize = 16;

/// Attention of `q` (1, heads, new tokens, head size; f32) over the first `total` positions of
/// the keys and values `k`, `v` (1, key/value heads, `total`, head size; bf16 views of the
/// cache's buffers), the new tokens being the last positions, each seeing itself and what
/// precedes it. Returns (1, new tokens, heads × head size), or `None` when this does not apply
/// (more than [`MAX_TOKENS`] new tokens, not bf16 on the CPU, a layout other than the cache's,
/// a head size other than 64 or 128, a CPU without AVX-512): the caller uses another.
pub fn decode_attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Option<Tensor>> {
    let applies = |shape: &Shape| {
        shape.seq <= MAX_TOKENS && matches!(shape.head_dim, 64 | 128) && cpu_has_avx512()
    };
    attend_in_place(q, k, v, applies, |shape, queries, keys, values| {
        let mut out = vec![0f32; shape.seq * shape.n_head * shape.head_dim];
        let target = Shared(out.as_mut_ptr());
        let group_queries = shape.rows() * shape.head_dim;
        candle_core::utils::barrier_pool().execute_chunked(shape.n_kv_head, |groups| {
            for g in groups {
                let queries = &queries[g * group_queries..(g + 1) * group_queries];
                let group_out = group(shape, queries, keys.head(g), values.head(g));
                for (r, row) in group_out.chunks_exact(shape.head_dim).enumerate() {
                    // SAFETY: row `r` of head `g` is inside `out`, and each (token, head)
                    // belongs to one group: no two tasks write the same element.
                    unsafe { target.write(shape.out_at(g, r), row) };
                }
            }
        });
        out
    })
}

/// A prompt's attention weights, in place of its scores: `scores` holds rows of `total`
/// (query row `r`: new token `r % seq`, at position `total − seq + r % seq`), each scaled by
/// `scale`, softmaxed over the positions its token sees and zero past them. One pass, the
/// exponentials 16 at a time, rows shared over candle's thread pool: where candle divided,
/// added the mask and took the softmax (scalar `expf`) in three passes over scores of up to
/// 2 × 3,000 × 2,300 values a layer. Returns `false`, nothing done, on a CPU without AVX-512.
pub fn causal_softmax(scores: &mut [f32], total: usize, seq: usize, scale: f32) -> bool {
    if !cpu_has_avx512()
        || total == 0
        || seq == 0
        || seq > total
        || !scores.len().is_multiple_of(total)
    {
        return false;
    }
    let rows = scores.len() / total;
    let target = Shared(scores.as_mut_ptr());
    candle_core::utils::barrier_pool().execute_chunked(rows, |range| {
        for r in range {
            // SAFETY: row `r` is inside `scores` (rows × total), and each row belongs to one
            // task.
            let row = unsafe { std::slice::from_raw_parts_mut(target.at(r * total), total) };
            let visible = total - seq + r % seq + 1;
            #[cfg(target_arch = "x86_64")]
            // SAFETY: AVX-512 is there (checked above).
            unsafe {
                avx512::causal_softmax_row(row, visible, scale)
            };
            #[cfg(not(target_arch = "x86_64"))]
            let _ = (row, visible);
        }
    });
    true
}

/// Whether this CPU runs [`avx512`]'s arithmetic (else candle's attention is used).
fn cpu_has_avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// The group's output rows (query row `r` = the group's query head `r / seq`, new token
/// `r % seq`), each `head_dim` long.
fn group(shape: &Shape, queries: &[f32], keys: &[u16], values: &[u16]) -> Vec<f32> {
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: `decode_attention` is only taken when `cpu_has_avx512()`.
        unsafe { avx512::group(shape, queries, keys, values) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (shape, queries, keys, values);
        unreachable!("decode_attention is only taken with AVX-512")
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) use avx512::causal_softmax_row;

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{LANES, Shape};
    use std::arch::x86_64::*;

    /// One key/value head's attention: `queries` holds the group's query rows, `keys` and
    /// `values` the head's `total` rows. Returns the output rows in the order of `queries`.
    /// Head sizes of 64 and 128 (4 or 8 vectors, the output rows' sums kept in registers).
    #[target_feature(enable = "avx512f")]
    pub fn group(shape: &Shape, queries: &[f32], keys: &[u16], values: &[u16]) -> Vec<f32> {
        match shape.head_dim / LANES {
            4 => group_of::<4>(shape, queries, keys, values),
            _ => group_of::<8>(shape, queries, keys, values),
        }
    }

    #[target_feature(enable = "avx512f")]
    fn group_of<const VECTORS: usize>(
        shape: &Shape,
        queries: &[f32],
        keys: &[u16],
        values: &[u16],
    ) -> Vec<f32> {
        let &Shape {
            n_rep,
            seq,
            total,
            head_dim,
            scale,
            ..
        } = shape;
        debug_assert_eq!(head_dim, VECTORS * LANES);
        let rows = n_rep * seq;
        // New token t sits at position total - seq + t and sees the positions up to it.
        let visible = |r: usize| total - seq + r % seq + 1;
        let mut scores = vec![0f32; rows * total];
        for (p, key) in keys
            .as_chunks::<LANES>()
            .0
            .chunks_exact(VECTORS)
            .enumerate()
        {
            let key: [__m512; VECTORS] = load_bf16(key);
            for (r, query) in queries
                .as_chunks::<LANES>()
                .0
                .chunks_exact(VECTORS)
                .enumerate()
            {
                if p < visible(r) {
                    let mut sum = _mm512_setzero_ps();
                    for (k, q) in key.iter().zip(query) {
                        // SAFETY: `q` is 16 f32.
                        sum = _mm512_fmadd_ps(*k, unsafe { _mm512_loadu_ps(q.as_ptr()) }, sum);
                    }
                    scores[r * total + p] = _mm512_reduce_add_ps(sum) * scale;
                }
            }
        }
        let mut out = vec![0f32; rows * head_dim];
        for (r, (row_scores, row_out)) in scores
            .chunks_exact_mut(total)
            .zip(out.as_chunks_mut::<LANES>().0.chunks_exact_mut(VECTORS))
            .enumerate()
        {
            let row_scores = &mut row_scores[..visible(r)];
            let sum = softmax_numerators(row_scores, 1.0);
            let mut acc = [_mm512_setzero_ps(); VECTORS];
            for (weight, value) in row_scores
                .iter()
                .zip(values.as_chunks::<LANES>().0.chunks_exact(VECTORS))
            {
                let weight = _mm512_set1_ps(*weight);
                let value: [__m512; VECTORS] = load_bf16(value);
                for (a, v) in acc.iter_mut().zip(value) {
                    *a = _mm512_fmadd_ps(weight, v, *a);
                }
            }
            let inverse = _mm512_set1_ps(1.0 / sum);
            for (o, a) in row_out.iter_mut().zip(acc) {
                // SAFETY: `o` is 16 f32.
                unsafe { _mm512_storeu_ps(o.as_mut_ptr(), _mm512_mul_ps(a, inverse)) };
            }
        }
        out
    }

    /// `VECTORS` vectors of f32 from as many chunks of 16 bf16 (a bf16 is an f32's high half).
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn load_bf16<const VECTORS: usize>(chunks: &[[u16; LANES]]) -> [__m512; VECTORS] {
        let mut vectors = [_mm512_setzero_ps(); VECTORS];
        for (v, c) in vectors.iter_mut().zip(chunks) {
            // SAFETY: `c` is 16 u16.
            let bits = unsafe { _mm256_loadu_si256(c.as_ptr() as *const _) };
            *v = _mm512_castsi512_ps(_mm512_slli_epi32::<16>(_mm512_cvtepu16_epi32(bits)));
        }
        vectors
    }

    /// A prompt's attention weights in place: see [`super::causal_softmax`].
    #[target_feature(enable = "avx512f")]
    pub(crate) fn causal_softmax_row(row: &mut [f32], visible: usize, scale: f32) {
        let (seen, unseen) = row.split_at_mut(visible);
        let inverse = _mm512_set1_ps(1.0 / softmax_numerators(seen, scale));
        let (chunks, rest) = seen.as_chunks_mut::<LANES>();
        for c in chunks.iter_mut() {
            // SAFETY: `c` is 16 f32.
            unsafe {
                _mm512_storeu_ps(
                    c.as_mut_ptr(),
                    _mm512_mul_ps(_mm512_loadu_ps(c.as_ptr()), inverse),
                )
            };
        }
        let inverse = _mm512_cvtss_f32(inverse);
        for s in rest {
            *s *= inverse;
        }
        unseen.fill(0.0);
    }

    /// Replaces `scores` by `exp(scale · (score − largest))` and returns their sum (`scale` > 0).
    #[target_feature(enable = "avx512f")]
    fn softmax_numerators(scores: &mut [f32], scale: f32) -> f32 {
        let (chunks, rest) = scores.as_chunks_mut::<LANES>();
        let mut largest_lanes = _mm512_set1_ps(f32::NEG_INFINITY);
        for c in chunks.iter() {
            // SAFETY: `c` is 16 f32.
            largest_lanes = _mm512_max_ps(largest_lanes, unsafe { _mm512_loadu_ps(c.as_ptr()) });
        }
        let largest = rest
            .iter()
            .fold(_mm512_reduce_max_ps(largest_lanes), |m, s| m.max(*s));
        let shift = _mm512_set1_ps(largest);
        let factor = _mm512_set1_ps(scale);
        let mut sum_lanes = _mm512_setzero_ps();
        for c in chunks.iter_mut() {
            // SAFETY: `c` is 16 f32.
            unsafe {
                let e = exp(_mm512_mul_ps(
                    _mm512_sub_ps(_mm512_loadu_ps(c.as_ptr()), shift),
                    factor,
                ));
                _mm512_storeu_ps(c.as_mut_ptr(), e);
                sum_lanes = _mm512_add_ps(sum_lanes, e);
            }
        }
        let mut sum = _mm512_reduce_add_ps(sum_lanes);
        for s in rest.iter_mut() {
            *s = ((*s - largest) * scale).exp();
            sum += *s;
        }
        sum
    }

    /// `e^x` for `x ≤ 0` (relative error under 1e-6; below −87, about 0): `x = n ln 2 + y` with
    /// `n` whole and `|y| ≤ ½ ln 2` (`ln 2` in two parts, so that `y` keeps its precision),
    /// `e^y` by its Taylor series to the 6th power, scaled by `2^n`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub(super) fn exp(x: __m512) -> __m512 {
        const LN2_HIGH: f32 = 0.693_359_4;
        const LN2_LOW: f32 = -2.121_944_4e-4;
        let x = _mm512_max_ps(x, _mm512_set1_ps(-87.0));
        let t = _mm512_mul_ps(x, _mm512_set1_ps(std::f32::consts::LOG2_E));
        let n = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(t);
        let y = _mm512_fnmadd_ps(n, _mm512_set1_ps(LN2_HIGH), x);
        let y = _mm512_fnmadd_ps(n, _mm512_set1_ps(LN2_LOW), y);
        let mut p = _mm512_set1_ps(1.0 / 720.0);
        for c in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
            p = _mm512_fmadd_ps(p, y, _mm512_set1_ps(c));
        }
        _mm512_scalef_ps(p, n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache_view::test_inputs::{cache_views, filled};
    use crate::decoder::{causal_mask, grouped_attention};
    use candle_core::Device;

    #[test]
    fn the_attention_of_new_tokens_is_candles() {
        if !cpu_has_avx512() {
            eprintln!("this CPU has no AVX-512: not checked");
            return;
        }
        for (n_head, n_kv, d) in [(12, 2, 128), (9, 3, 64)] {
            for seq in [1, 3, MAX_TOKENS] {
                let total = 40;
                let q = filled((1, n_head, seq, d), 3);
                let (k, v) = cache_views(n_kv, total, d);
                let ours = decode_attention(&q, &k, &v)
                    .expect("attention")
                    .expect("applies to the cache's layout");
                let mask =
                    (seq > 1).then(|| causal_mask(seq, total - seq, &Device::Cpu).expect("mask"));
                // Candle's on the same values in f32 (a bf16 is exactly an f32).
                let f32s = |t: &Tensor| t.to_dtype(candle_core::DType::F32).expect("f32");
                let theirs = grouped_attention(&q, &f32s(&k), &f32s(&v), mask.as_ref(), n_kv)
                    .expect("candle's");
                assert_eq!(ours.dims(), theirs.dims());
                let ours = ours
                    .flatten_all()
                    .and_then(|t| t.to_vec1::<f32>())
                    .expect("ours");
                let theirs = theirs
                    .flatten_all()
                    .and_then(|t| t.to_vec1::<f32>())
                    .expect("theirs");
                for (a, b) in ours.iter().zip(&theirs) {
                    assert!(
                        (a - b).abs() < 1e-4,
                        "{n_head}/{n_kv} heads, {seq} tokens: {a} against {b}"
                    );
                }
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_vector_exponential_is_the_exponential() {
        use std::arch::x86_64::*;
        if !cpu_has_avx512() {
            eprintln!("this CPU has no AVX-512: not checked");
            return;
        }
        let xs: Vec<f32> = (0..=16_000).map(|i| -(i as f32) / 160.0).collect();
        for chunk in xs.as_chunks::<LANES>().0 {
            let mut got = [0f32; LANES];
            // SAFETY: AVX-512 is there (checked above); both arrays are 16 f32.
            unsafe {
                let e = avx512::exp(_mm512_loadu_ps(chunk.as_ptr()));
                _mm512_storeu_ps(got.as_mut_ptr(), e);
            }
            for (x, e) in chunk.iter().zip(got) {
                let expected = x.exp();
                assert!(
                    (e - expected).abs() <= 1e-6 * expected + 1e-37,
                    "exp({x}) = {e}, not {expected}"
                );
            }
        }
    }

    #[test]
    fn what_it_does_not_apply_to_goes_to_candle() {
        if !cpu_has_avx512() {
            return;
        }
        let (k, v) = cache_views(2, 40, 128);
        let too_many = filled((1, 12, MAX_TOKENS + 1, 128), 3);
        assert!(
            decode_attention(&too_many, &k, &v)
                .expect("no error")
                .is_none()
        );
        let odd_width = filled((1, 12, 1, 120), 3);
        let (k, v) = cache_views(2, 40, 120);
        assert!(
            decode_attention(&odd_width, &k, &v)
                .expect("no error")
                .is_none()
        );
        // Keys whose rows are not contiguous: not the cache's layout.
        let (_, v) = cache_views(2, 40, 128);
        let q = filled((1, 12, 1, 128), 3);
        let k_t = cache_views(2, 128, 40)
            .0
            .transpose(2, 3)
            .expect("transposed");
        assert!(decode_attention(&q, &k_t, &v).expect("no error").is_none());
    }
}

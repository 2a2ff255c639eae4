//! Attention of more new tokens than a decode step feeds (a prompt's chunk, a run of forced
//! tokens) over the key/value cache, on AMX tiles in bf16, where the CPU has them (Intel
//! Sapphire Rapids and later).
//!
//! Why: candle's products for the scores and the weighted values run on 256-bit vectors (its
//! `gemm` has no AVX-512 kernels on stable Rust), ~45 G multiply-adds a second on two cores:
//! a restarted Supervisor call's 259 prompt tokens at 1,541 cached positions spent 0.87 s of
//! their 2.2 s there, and each run of 20–26 forced tokens ~90 ms of ~290 (timers in
//! `decoder::attention`). A `tdpbf16ps` does 8,192 multiply-adds.
//!
//! How: per key/value head, the keys are laid out once as the tiles' second operand (each 16
//! keys × 32 dimensions a tile, pairs of dimensions per 32 bits), the values likewise (each 32
//! keys × 16 dimensions a tile, pairs of keys per 32 bits). Then per 16 query rows: their
//! scores over the visible keys (four key tiles at a time), the causal softmax in f32
//! (`decode_attention::causal_softmax_row`), the weights rounded to bf16, and the weighted
//! values (four tiles of 16 dimensions at a time). The cache holds bf16 already; the queries
//! and the weights are rounded to bf16 (to nearest, ties to even), the sums are f32.

use std::arch::asm;
use std::arch::x86_64::*;

use candle_core::{Result, Tensor};

use crate::cache_view::{CacheView, Shape, attend_in_place};
use crate::decode_attention::causal_softmax_row;
use crate::pool::Shared;
use crate::tiles::{TILE_BYTES, TILE_ROWS, TilesInUse, bf16_available};

/// Keys per tile of values (pairs of keys per 32 bits).
const KEYS_PER_CHUNK: usize = 32;
/// Key tiles (16 keys) or value tiles (16 dimensions) one tile program takes at a time.
const TILES_AT_ONCE: usize = 4;
/// Keys the laid-out keys are padded to: whole programs of four key tiles.
const KEY_PADDING: usize = TILE_ROWS * TILES_AT_ONCE;

/// Whether [`prompt_attention`] runs here: AMX with bf16 products, and AVX-512 BW.
pub fn available() -> bool {
    bf16_available() && std::arch::is_x86_feature_detected!("avx512bw")
}

/// Attention of `q` (1, heads, new tokens, head size; f32) over the first `total` positions of
/// `k`, `v` (1, key/value heads, `total`, head size; bf16 views of the cache's buffers), the
/// new tokens being the last positions, each seeing itself and what precedes it. Returns (1,
/// new tokens, heads × head size), or `None` when this does not apply (no AMX bf16 here, not
/// the cache's layout or type, a head size not a multiple of 64): the caller uses candle's.
pub fn prompt_attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Option<Tensor>> {
    let applies = |shape: &Shape| shape.head_dim.is_multiple_of(KEYS_PER_CHUNK * 2) && available();
    attend_in_place(q, k, v, applies, |shape, queries, keys, values| {
        // SAFETY: `available()` said yes.
        unsafe { attend(shape, queries, keys, values) }
    })
}

/// # Safety
/// [`available`] said yes.
unsafe fn attend(
    shape: &Shape,
    queries: &[f32],
    keys: &CacheView<u16>,
    values: &CacheView<u16>,
) -> Vec<f32> {
    let (rows, head_dim) = (shape.rows(), shape.head_dim);
    let row_tiles = rows.div_ceil(TILE_ROWS);
    // Each head's keys and values laid out for the tiles, one task a head.
    let mut laid_out: Vec<LaidOut> = (0..shape.n_kv_head).map(|_| LaidOut::default()).collect();
    let heads = Shared(laid_out.as_mut_ptr());
    candle_core::utils::barrier_pool().execute_chunked(shape.n_kv_head, |range| {
        for g in range {
            // SAFETY: `g` is below `n_kv_head`, the length of `laid_out`, and each head belongs
            // to one task; `available()` said yes (the caller's promise).
            unsafe { *heads.at(g) = LaidOut::new(shape, keys.head(g), values.head(g)) };
        }
    });
    let mut out = vec![0f32; shape.seq * shape.n_head * head_dim];
    let target = Shared(out.as_mut_ptr());
    // Then the query rows, 16 at a time, over every head.
    candle_core::utils::barrier_pool().execute_chunked(shape.n_kv_head * row_tiles, |range| {
        let mut scratch = Scratch::new(shape);
        for task in range {
            let (g, tile) = (task / row_tiles, task % row_tiles);
            let queries = &queries[g * rows * head_dim..(g + 1) * rows * head_dim];
            let first = tile * TILE_ROWS;
            // SAFETY: `available()` said yes (the caller's promise).
            let rows_out = unsafe { scratch.rows(shape, &laid_out[g], queries, first) };
            for (r, row) in (first..rows).zip(rows_out.chunks_exact(head_dim)) {
                // SAFETY: row `r` of head `g` is inside `out`; each is one task's.
                unsafe { target.write(shape.out_at(g, r), row) };
            }
        }
    });
    out
}

/// Keys the laid-out keys hold: the positions, padded to whole programs of four key tiles.
fn padded_keys(shape: &Shape) -> usize {
    shape.total.div_ceil(KEY_PADDING) * KEY_PADDING
}

/// One head's keys and values as the tiles take them (bf16 pairs per 32 bits), zero past the
/// last key. `keys`: per 32 dimensions, per 16 keys, a tile whose row `i` holds dimensions
/// `2i, 2i + 1` of the 16 keys; `values`: per 32 keys, per 16 dimensions, a tile whose row `i`
/// holds keys `2i, 2i + 1` of the 16 dimensions.
#[derive(Default)]
struct LaidOut {
    keys: Vec<u32>,
    values: Vec<u32>,
}

impl LaidOut {
    /// # Safety
    /// [`available`] said yes.
    #[target_feature(enable = "avx512f,avx512bw")]
    unsafe fn new(shape: &Shape, keys: &[u16], values: &[u16]) -> LaidOut {
        let (d, total) = (shape.head_dim, shape.total);
        let padded = padded_keys(shape);
        let key_tiles = padded / TILE_ROWS;
        let chunks = d / KEYS_PER_CHUNK;
        let mut laid = LaidOut {
            keys: vec![0; padded * d / 2],
            values: vec![0; padded * d / 2],
        };
        let words = TILE_BYTES / 4;
        for tile in 0..key_tiles {
            for chunk in 0..chunks {
                // Row `n`: key `16 · tile + n`'s 32 dimensions of this chunk (16 pairs).
                let rows: [__m512; TILE_ROWS] = std::array::from_fn(|n| {
                    let key = tile * TILE_ROWS + n;
                    if key < total {
                        let at = key * d + chunk * KEYS_PER_CHUNK;
                        // SAFETY: 32 bf16 from `at`, inside the head's `total` rows of `d`.
                        unsafe { _mm512_loadu_ps(keys.as_ptr().add(at) as *const f32) }
                    } else {
                        _mm512_setzero_ps()
                    }
                });
                let at = (chunk * key_tiles + tile) * words;
                for (i, row) in crate::tiles::transpose(rows).into_iter().enumerate() {
                    // SAFETY: 16 words of the tile at `at`, inside `laid.keys`.
                    unsafe {
                        _mm512_storeu_ps(laid.keys.as_mut_ptr().add(at + i * 16) as *mut f32, row)
                    };
                }
            }
        }
        // Word 2j of the result: word j of the first row; word 2j + 1: word j of the second.
        let interleave: [i16; 32] = std::array::from_fn(|w| (w / 2 + 32 * (w % 2)) as i16);
        // SAFETY: 32 words.
        let interleave = unsafe { _mm512_loadu_si512(interleave.as_ptr() as *const _) };
        let dim_tiles = d / TILE_ROWS;
        let row_of = |key: usize, dim_tile: usize| {
            if key < total {
                // SAFETY: 16 bf16 of key `key`, inside the head's rows.
                unsafe {
                    _mm512_castsi256_si512(_mm256_loadu_si256(
                        values.as_ptr().add(key * d + dim_tile * TILE_ROWS) as *const _,
                    ))
                }
            } else {
                _mm512_setzero_si512()
            }
        };
        for chunk in 0..padded / KEYS_PER_CHUNK {
            for dim_tile in 0..dim_tiles {
                let at = (chunk * dim_tiles + dim_tile) * words;
                for i in 0..TILE_ROWS {
                    let key = chunk * KEYS_PER_CHUNK + 2 * i;
                    let pairs = _mm512_permutex2var_epi16(
                        row_of(key, dim_tile),
                        interleave,
                        row_of(key + 1, dim_tile),
                    );
                    // SAFETY: 16 words of the tile at `at`, inside `laid.values`.
                    unsafe {
                        _mm512_storeu_si512(
                            laid.values.as_mut_ptr().add(at + i * 16) as *mut _,
                            pairs,
                        )
                    };
                }
            }
        }
        laid
    }
}

/// A task's buffers, kept over its query tiles.
struct Scratch {
    /// 16 query rows in bf16.
    queries: Vec<u16>,
    /// Their scores over the padded keys (f32), then the weights in place.
    scores: Vec<f32>,
    /// The weights in bf16.
    weights: Vec<u16>,
    /// The 16 output rows.
    out: Vec<f32>,
}

impl Scratch {
    fn new(shape: &Shape) -> Scratch {
        let padded = padded_keys(shape);
        Scratch {
            queries: vec![0; TILE_ROWS * shape.head_dim],
            scores: vec![0.0; TILE_ROWS * padded],
            weights: vec![0; TILE_ROWS * padded],
            out: vec![0.0; TILE_ROWS * shape.head_dim],
        }
    }

    /// The output rows of query rows `first..first + 16` of a head (`queries`: the head's
    /// rows), in order; rows past the head's last are zero.
    ///
    /// # Safety
    /// [`available`] said yes.
    #[target_feature(enable = "avx512f,avx512bw")]
    unsafe fn rows(
        &mut self,
        shape: &Shape,
        laid: &LaidOut,
        queries: &[f32],
        first: usize,
    ) -> &[f32] {
        let d = shape.head_dim;
        let rows = shape.rows();
        let last = (first + TILE_ROWS).min(rows);
        self.queries.fill(0);
        to_bf16(&queries[first * d..last * d], &mut self.queries);
        let padded = padded_keys(shape);
        let seen = (first..last).map(|r| shape.visible(r)).max().unwrap_or(0);
        let key_tiles = seen.div_ceil(KEY_PADDING) * TILES_AT_ONCE;
        let chunks = d / KEYS_PER_CHUNK;
        // SAFETY: tiles available (the caller's promise); the pointers and strides stay inside
        // the buffers: see the two calls of `four_tile_products`.
        let _tiles = unsafe { TilesInUse::take() };
        for tile in (0..key_tiles).step_by(TILES_AT_ONCE) {
            // The scores. SAFETY: `queries` holds 16 rows of d bf16 (d / 32 ≥ 2 chunks);
            // `laid.keys` the tiles of every chunk for `padded / 16` key tiles (from `tile`,
            // four); `scores` 16 rows of `padded`.
            unsafe {
                four_tile_products(
                    self.queries.as_ptr(),
                    d * 2,
                    laid.keys.as_ptr().add(tile * TILE_BYTES / 4),
                    padded / TILE_ROWS * TILE_BYTES,
                    chunks,
                    self.scores.as_mut_ptr().add(tile * TILE_ROWS),
                    padded * 4,
                )
            };
        }
        let width = key_tiles * TILE_ROWS;
        for (i, (scores, weights)) in self
            .scores
            .chunks_exact_mut(padded)
            .zip(self.weights.chunks_exact_mut(padded))
            .enumerate()
        {
            let r = first + i;
            if r < last {
                causal_softmax_row(&mut scores[..width], shape.visible(r), shape.scale);
                to_bf16(&scores[..width], &mut weights[..width]);
            } else {
                weights[..width].fill(0);
            }
        }
        let dim_tiles = d / TILE_ROWS;
        for dim_tile in (0..dim_tiles).step_by(TILES_AT_ONCE) {
            // The weighted values. SAFETY: `weights` 16 rows of `padded` bf16, `width / 32` ≥ 2
            // chunks of them used; `laid.values` per chunk `dim_tiles` tiles (from `dim_tile`,
            // four); `out` 16 rows of d f32 (from column `16 · dim_tile`, 64).
            unsafe {
                four_tile_products(
                    self.weights.as_ptr(),
                    padded * 2,
                    laid.values.as_ptr().add(dim_tile * TILE_BYTES / 4),
                    dim_tiles * TILE_BYTES,
                    width / KEYS_PER_CHUNK,
                    self.out.as_mut_ptr().add(dim_tile * TILE_ROWS),
                    d * 4,
                )
            };
        }
        &self.out
    }
}

/// f32 to bf16, to nearest with ties to even (as `half::bf16::from_f32` for finite values).
#[target_feature(enable = "avx512f,avx512bw")]
fn to_bf16(from: &[f32], to: &mut [u16]) {
    let to = &mut to[..from.len()];
    let (chunks, rest) = from.as_chunks::<16>();
    let (out, out_rest) = to.as_chunks_mut::<16>();
    for (c, o) in chunks.iter().zip(out.iter_mut()) {
        // SAFETY: 16 f32 in, 16 u16 out.
        unsafe {
            let bits = _mm512_castps_si512(_mm512_loadu_ps(c.as_ptr()));
            let odd = _mm512_and_si512(_mm512_srli_epi32::<16>(bits), _mm512_set1_epi32(1));
            let rounded = _mm512_add_epi32(bits, _mm512_add_epi32(odd, _mm512_set1_epi32(0x7fff)));
            let high = _mm512_cvtepi32_epi16(_mm512_srli_epi32::<16>(rounded));
            _mm256_storeu_si256(o.as_mut_ptr() as *mut _, high);
        }
    }
    for (f, o) in rest.iter().zip(out_rest.iter_mut()) {
        *o = half::bf16::from_f32(*f).to_bits();
    }
}

/// `C_j = Σ_c A_c · B_{c,j}` for four tiles `j` over `chunks` chunks `c` on AMX bf16 tiles,
/// stored at `out` (16 rows, `out_stride` bytes apart, 64 floats each): a row of `A` holds 32
/// bf16 of a chunk (`a`'s rows `a_stride` bytes apart, chunk `c` at byte `64·c`), a `B` tile is
/// 1,024 bytes of bf16 pairs. `b` points at chunk 0's first tile, a chunk's tiles are
/// `chunk_stride` bytes after the previous chunk's, its four tiles 1,024 bytes apart. The
/// scores (`A` the queries, `B` the laid-out keys: four tiles of 16 keys) and the weighted
/// values (`A` the weights, `B` the laid-out values: four tiles of 16 dimensions) are both this.
///
/// # Safety
/// Tiles configured by [`TilesInUse::take`] on a CPU with AMX-BF16; `chunks` > 0; every address
/// read or written is inside its buffer.
unsafe fn four_tile_products(
    a: *const u16,
    a_stride: usize,
    b: *const u32,
    chunk_stride: usize,
    chunks: usize,
    out: *mut f32,
    out_stride: usize,
) {
    // SAFETY: the caller's promises. tmm0–3 the four sums, tmm4 `A`'s chunk, tmm5–7 and tmm5
    // again the `B` tiles.
    unsafe {
        asm!(
            "tilezero tmm0",
            "tilezero tmm1",
            "tilezero tmm2",
            "tilezero tmm3",
            "2:",
            "tileloadd tmm4, [{a} + {as}*1]",
            "tileloadd tmm5, [{b} + {s}*1]",
            "tdpbf16ps tmm0, tmm4, tmm5",
            "tileloadd tmm6, [{b} + {s}*1 + 1024]",
            "tdpbf16ps tmm1, tmm4, tmm6",
            "tileloadd tmm7, [{b} + {s}*1 + 2048]",
            "tdpbf16ps tmm2, tmm4, tmm7",
            "tileloadd tmm5, [{b} + {s}*1 + 3072]",
            "tdpbf16ps tmm3, tmm4, tmm5",
            "add {a}, 64",
            "add {b}, {cs}",
            "dec {n}",
            "jnz 2b",
            "tilestored [{out} + {os}*1], tmm0",
            "tilestored [{out} + {os}*1 + 64], tmm1",
            "tilestored [{out} + {os}*1 + 128], tmm2",
            "tilestored [{out} + {os}*1 + 192], tmm3",
            a = inout(reg) a => _,
            as = in(reg) a_stride,
            b = inout(reg) b => _,
            s = in(reg) 64usize,
            cs = in(reg) chunk_stride,
            n = inout(reg) chunks => _,
            out = in(reg) out,
            os = in(reg) out_stride,
            options(nostack),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache_view::test_inputs::{cache_views, filled};
    use crate::decoder::{causal_mask, grouped_attention};
    use candle_core::{DType, Device};

    fn values(t: &Tensor) -> Vec<f32> {
        t.flatten_all()
            .and_then(|t| t.to_vec1::<f32>())
            .expect("values")
    }

    #[test]
    fn the_attention_of_many_new_tokens_is_candles() {
        if !available() {
            eprintln!("this CPU has no AMX with bf16 (or Linux does not grant it): not checked");
            return;
        }
        // Qwen2.5-Coder-1.5B's heads and SmolLM2's; a run of forced tokens, a chunk past a
        // tile of queries (and two heads in one tile), a prompt from nothing, 64 + 1 keys.
        for (n_head, n_kv, d) in [(12, 2, 128), (9, 3, 64)] {
            for (seq, past) in [(9, 40), (26, 1541), (40, 0), (33, 32)] {
                let total = seq + past;
                // The queries as bf16 already: what is left to differ is the weights'
                // rounding to bf16 (within 2⁻⁹ each) and the order of the sums.
                let q = filled((1, n_head, seq, d), 3)
                    .to_dtype(DType::BF16)
                    .and_then(|q| q.to_dtype(DType::F32))
                    .expect("q");
                let (k, v) = cache_views(n_kv, total, d);
                let ours = prompt_attention(&q, &k, &v)
                    .expect("attention")
                    .expect("applies to the cache's layout");
                let mask = causal_mask(seq, past, &Device::Cpu).expect("mask");
                let (k32, v32) = (
                    k.to_dtype(DType::F32).expect("k"),
                    v.to_dtype(DType::F32).expect("v"),
                );
                let theirs =
                    grouped_attention(&q, &k32, &v32, Some(&mask), n_kv).expect("candle's");
                assert_eq!(ours.dims(), theirs.dims());
                for (i, (a, b)) in values(&ours).iter().zip(values(&theirs)).enumerate() {
                    assert!(
                        (a - b).abs() < 4e-3,
                        "{n_head}/{n_kv} heads, {seq} after {past}, value {i}: {a} against {b}"
                    );
                }
            }
        }
    }

    #[test]
    fn rounding_to_bf16_is_halfs() {
        let xs: Vec<f32> = (0..1000)
            .map(|i| (i as f32 * 0.7371).sin() * 10f32.powi(i % 7 - 3))
            .chain([
                0.0,
                -0.0,
                1.0 + f32::EPSILON * 64.0,
                1.0 + f32::EPSILON * 192.0,
            ])
            .collect();
        let mut ours = vec![0u16; xs.len()];
        if !std::arch::is_x86_feature_detected!("avx512bw") {
            return;
        }
        // SAFETY: AVX-512 BW is there (checked just before).
        unsafe { to_bf16(&xs, &mut ours) };
        for (x, b) in xs.iter().zip(ours) {
            assert_eq!(b, half::bf16::from_f32(*x).to_bits(), "{x}");
        }
    }
}

//! Products of many activation rows (a prompt's chunks, the decode steps that feed a run of
//! forced tokens) with Q4_K and Q6_K matrices on AMX tiles, where the CPU has them (Intel
//! Sapphire Rapids and later) and Linux lets this process use them.
//!
//! Why: a `vpdpbusd` does 64 multiply-adds, an AMX `tdpbusd` 16,384 (16 weight rows × 16
//! activation rows × 64 values), measured here at ~13 cycles each. candle has an AMX kernel
//! for Q4_K too (`repack_x86::amx`), but it takes one 32-value sub-block per instruction and
//! stores and rescales its tiles after each, repacks the matrices (1.33× their bytes) on first
//! use, and has none for Q6_K.
//!
//! How the sub-block scales fit in a tile: a Q4_K value is `d·s·q − dmin·m` (q 4 bits; s and m
//! 6 bits, one per 32 values; d and dmin one per 256). `s·q` (below 1,024) goes into two byte
//! tiles, its low byte and its high bits: two accumulators sum a whole 256-value block in four
//! instructions each, and only then are stored and multiplied by the block's float scales; the
//! mins' term `dmin · Σ m · (sub-block sum)` comes from the activations' sub-block sums on the
//! vector units (`block_value`). A Q6_K value is `d·s·(q − 32)` (s signed, one per 16 values):
//! `s·(q − 32)` is within ±4,096, a low byte (unsigned) and a signed high byte, two tiles.
//! The integers are those the VNNI kernels sum, from the same activation bytes: the results
//! differ from theirs only in float rounding.

use std::arch::asm;
use std::arch::x86_64::*;

use super::{ActivationBlock, BLOCK_VALUES, Format};
use crate::pool::Shared;
pub use crate::tiles::TILE_ROWS;
use crate::tiles::{TILE_BYTES, TilesInUse, transpose};

/// Whether the CPU has AMX with 8-bit products and the vector instructions these products use,
/// and this process may use the tiles.
pub fn available() -> bool {
    crate::tiles::int8_available()
        && std::arch::is_x86_feature_detected!("avx512bw")
        && std::arch::is_x86_feature_detected!("avx512vbmi")
        && std::arch::is_x86_feature_detected!("avx512vnni")
}

/// 64-value pieces of a 256-value block: one instruction each.
const PIECES: usize = BLOCK_VALUES / 64;
/// Pairs of Q4_K's 32-value sub-blocks in a block: one `vpdpwssd` each for the mins.
const PAIRS: usize = 4;
/// Activation tiles one pass over a group of weight rows takes (128 rows): their bytes, at
/// most 1.1 MB for Qwen2.5-Coder-1.5B's widest matrix, stay in the core's cache while the
/// group's blocks are unpacked once for all of them.
const TILES_PER_PASS: usize = 8;

/// The activation rows quantised and laid out as the tiles take them: per block, per tile of
/// 16 rows, per 64-value piece, 16 groups of four values, each group for the 16 rows in turn
/// (`tdpbusd`'s second operand). Rows past the last are zero.
pub struct PackedActivations {
    bytes: Vec<u8>,
    /// Per block, per (padded) row: the row's scale for that block (0 for padding).
    scales: Vec<f32>,
    /// Q4_K only: per block, per tile, per pair of 32-value sub-blocks `(2p, 2p + 1)`, the 16
    /// rows' sums of those sub-blocks as two 16-bit halves (`vpdpwssd`'s operand; see
    /// [`block_value`]). Padding rows are zero.
    sub_sums: Vec<i32>,
    rows: usize,
    tiles: usize,
    blocks: usize,
}

impl PackedActivations {
    /// `x`: `rows` rows of `blocks` blocks of values, quantised here (`ActivationBlock`), a
    /// block column per task on candle's pool; Q4_K's pieces are in its load order
    /// (`ActivationBlock::q4k_order`), Q6_K's the values in order.
    pub fn new(x: &[f32], rows: usize, blocks: usize, format: Format) -> PackedActivations {
        assert_eq!(x.len(), rows * blocks * BLOCK_VALUES, "activations");
        let tiles = rows.div_ceil(TILE_ROWS);
        let (block_bytes, block_scales) = (tiles * PIECES * TILE_BYTES, tiles * TILE_ROWS);
        let block_sums = match format {
            Format::Q4K => tiles * PAIRS * TILE_ROWS,
            Format::Q6K => 0,
        };
        let mut bytes = vec![0u8; blocks * block_bytes];
        let mut scales = vec![0f32; blocks * block_scales];
        let mut sub_sums = vec![0i32; blocks * block_sums];
        let shared = (
            Shared(bytes.as_mut_ptr()),
            Shared(scales.as_mut_ptr()),
            Shared(sub_sums.as_mut_ptr()),
        );
        candle_core::utils::barrier_pool().execute_chunked(blocks, |range| {
            for b in range {
                // SAFETY: block `b`'s parts of the three buffers (each `blocks` parts long),
                // filled by this task alone.
                let (bytes, scales, sub_sums) = unsafe {
                    (
                        shared.0.part(b * block_bytes, block_bytes),
                        shared.1.part(b * block_scales, block_scales),
                        shared.2.part(b * block_sums, block_sums),
                    )
                };
                for (i, scale) in scales[..rows].iter_mut().enumerate() {
                    let at = (i * blocks + b) * BLOCK_VALUES;
                    let block = ActivationBlock::quantise(&x[at..at + BLOCK_VALUES]);
                    let (tile, in_tile) = (i / TILE_ROWS, i % TILE_ROWS);
                    *scale = block.scale;
                    if format == Format::Q4K {
                        for (pair, sums) in block.sums32.chunks_exact(2).enumerate() {
                            sub_sums[(tile * PAIRS + pair) * TILE_ROWS + in_tile] =
                                pack_words(sums[0], sums[1]);
                        }
                    }
                    let values = match format {
                        Format::Q4K => &block.q4k_order,
                        Format::Q6K => &block.natural,
                    };
                    for (piece, values) in values.chunks_exact(64).enumerate() {
                        let at = (tile * PIECES + piece) * TILE_BYTES + 4 * in_tile;
                        for (group, four) in values.chunks_exact(4).enumerate() {
                            let four = [four[0] as u8, four[1] as u8, four[2] as u8, four[3] as u8];
                            bytes[at + 64 * group..at + 64 * group + 4].copy_from_slice(&four);
                        }
                    }
                }
            }
        });
        PackedActivations {
            bytes,
            scales,
            sub_sums,
            rows,
            tiles,
            blocks,
        }
    }
}

/// A group of 16 weight rows of one block, unpacked for the tiles: per piece, 16 rows of 64
/// bytes each — `low` and `high` the low byte and the high bits of the scaled values — and
/// each row's float scales and (Q4_K) its sub-blocks' mins, a pair of them per 32 bits.
#[repr(C, align(64))]
struct WeightTiles {
    low: [[u8; TILE_BYTES]; PIECES],
    high: [[u8; TILE_BYTES]; PIECES],
    d: [f32; TILE_ROWS],
    dmin: [f32; TILE_ROWS],
    min_pairs: [[i32; PAIRS]; TILE_ROWS],
}

/// The accumulators as stored: per activation tile of a pair, the low bytes' and the high
/// bits' sums, each 16 weight rows of 16 activation rows.
#[repr(C, align(64))]
struct Sums([[i32; TILE_ROWS * TILE_ROWS]; 4]);

/// Two signed 16-bit values in the halves of 32 bits, `low` first (`vpdpwssd`'s pairs).
fn pack_words(low: i16, high: i16) -> i32 {
    (low as u16 as u32 | (high as u16 as u32) << 16) as i32
}

/// `out[i · out_stride + r] = Σ_c x[i][c] · W[row_start + r][c]` for the 16-row groups
/// `groups` (of rows counted from `row_start`) and every activation row `i`; `weights` the whole
/// matrix's blocks, `row_bytes` a row's.
///
/// # Safety
/// [`available`] said yes; `out` holds as many rows of `out_stride` values as `activations`
/// has rows, `out_stride` ≥ 16 × `groups.end`, and no other thread writes the columns of these
/// groups.
#[allow(clippy::too_many_arguments)]
pub unsafe fn product(
    format: Format,
    weights: &[u8],
    row_bytes: usize,
    row_start: usize,
    groups: std::ops::Range<usize>,
    activations: &PackedActivations,
    out: *mut f32,
    out_stride: usize,
) {
    // SAFETY: the caller's promises.
    unsafe {
        product_on_tiles(
            format,
            weights,
            row_bytes,
            row_start,
            groups,
            activations,
            out,
            out_stride,
        )
    }
}

#[target_feature(enable = "avx512f,avx512bw,avx512vbmi,avx512vnni,fma,f16c")]
#[allow(clippy::too_many_arguments)]
unsafe fn product_on_tiles(
    format: Format,
    weights: &[u8],
    row_bytes: usize,
    row_start: usize,
    groups: std::ops::Range<usize>,
    activations: &PackedActivations,
    out: *mut f32,
    out_stride: usize,
) {
    let block_bytes = format.block_bytes();
    let blocks = activations.blocks;
    assert_eq!(row_bytes, blocks * block_bytes, "a row's blocks");
    // SAFETY: the caller's promise (`available`).
    let _tiles = unsafe { TilesInUse::take() };
    let empty = || WeightTiles {
        low: [[0; TILE_BYTES]; PIECES],
        high: [[0; TILE_BYTES]; PIECES],
        d: [0.0; TILE_ROWS],
        dmin: [0.0; TILE_ROWS],
        min_pairs: [[0; PAIRS]; TILE_ROWS],
    };
    // Two: a block is unpacked while the tiles read the one before. A tile load waits for
    // the stores to its bytes to reach the cache; loading the block just written stalled on
    // them (half the time of a product of a few rows).
    let mut unpacked = Box::new([empty(), empty()]);
    let mut sums = Sums([[0; TILE_ROWS * TILE_ROWS]; 4]);
    for group in groups {
        let first_row = row_start + group * TILE_ROWS;
        let rows_at = first_row * row_bytes;
        let group_bytes = &weights[rows_at..rows_at + TILE_ROWS * row_bytes];
        for pass in (0..activations.tiles).step_by(TILES_PER_PASS) {
            let tiles = pass..(pass + TILES_PER_PASS).min(activations.tiles);
            let mut totals = [[_mm512_setzero_ps(); TILES_PER_PASS]; TILE_ROWS];
            for next in 0..=blocks {
                if pass == 0 && next < blocks {
                    // The next group's rows follow this group's: ask for a block's share of
                    // them while this one is multiplied (the hardware's prefetcher alone left
                    // the tiles waiting on memory in a decode step's product).
                    let share = TILE_ROWS * block_bytes;
                    let ahead = group_bytes
                        .as_ptr()
                        .wrapping_add(group_bytes.len() + next * share);
                    // A prefetch is a hint: past the matrix's end it does not fault.
                    for line in (0..share).step_by(64) {
                        _mm_prefetch::<_MM_HINT_T0>(ahead.wrapping_add(line) as *const i8);
                    }
                }
                if next < blocks {
                    let into = &mut unpacked[next % 2];
                    for (r, row) in group_bytes.chunks_exact(row_bytes).enumerate() {
                        let block = &row[next * block_bytes..(next + 1) * block_bytes];
                        match format {
                            Format::Q4K => unpack_q4k(block, r, into),
                            Format::Q6K => unpack_q6k(block, r, into),
                        }
                    }
                }
                let Some(b) = next.checked_sub(1) else {
                    continue;
                };
                let unpacked = &unpacked[b % 2];
                // Two activation tiles at a time: each weight tile loaded serves both.
                for first in tiles.clone().step_by(2) {
                    let pair = first + 1 < tiles.end;
                    let at = (b * activations.tiles + first) * PIECES * TILE_BYTES;
                    let pieces =
                        &activations.bytes[at..at + (1 + pair as usize) * PIECES * TILE_BYTES];
                    // SAFETY: `pieces` holds four tiles per activation tile, `unpacked` four
                    // of each kind, `sums` four; the tiles are configured (`_tiles`).
                    unsafe { multiply(format, pieces, pair, unpacked, &mut sums) };
                    for (half, tile) in (first..tiles.end).take(1 + pair as usize).enumerate() {
                        let slot = tile - tiles.start;
                        let scales_at = (b * activations.tiles + tile) * TILE_ROWS;
                        // SAFETY: 16 scales from `scales_at`: each block has `tiles` × 16.
                        let scales =
                            unsafe { _mm512_loadu_ps(activations.scales.as_ptr().add(scales_at)) };
                        let sub_sums = (format == Format::Q4K).then(|| {
                            let at = (b * activations.tiles + tile) * PAIRS * TILE_ROWS;
                            let sums = &activations.sub_sums[at..at + PAIRS * TILE_ROWS];
                            // SAFETY: four rows of 16 from `at`, each block's tile has them.
                            [0, 1, 2, 3].map(|pair| unsafe {
                                _mm512_loadu_si512(sums.as_ptr().add(pair * TILE_ROWS) as *const _)
                            })
                        });
                        for (r, total) in totals.iter_mut().enumerate() {
                            let value =
                                block_value(&sums, 2 * half, unpacked, sub_sums.as_ref(), r);
                            total[slot] = _mm512_fmadd_ps(value, scales, total[slot]);
                        }
                    }
                }
            }
            // Each activation row's 16 values of this group as one store (a scalar store per
            // value, a cache line at a time per activation row, was a third of a product with
            // 8,960 outputs a row).
            for (slot, tile) in tiles.clone().enumerate() {
                let by_activation = transpose(totals.map(|total| total[slot]));
                let first = tile * TILE_ROWS;
                let last = (first + TILE_ROWS).min(activations.rows);
                for (i, values) in (first..last).zip(by_activation) {
                    // SAFETY: `i` is an activation row, `group * 16 ..` 16 columns of this
                    // thread's groups: inside `out` and written by no other thread.
                    unsafe {
                        _mm512_storeu_ps(out.add(i * out_stride + group * TILE_ROWS), values)
                    };
                }
            }
        }
    }
}

/// One piece (64 values) of [`multiply`]'s program for two activation tiles (`{x}`, and
/// 4,096 bytes on): tmm6 and tmm7 the weights' low bytes and high bits, tmm4 and tmm5 the
/// activation tiles, tmm0–1 the first tile's sums, tmm2–3 the second's. `$high` multiplies
/// the high bits (Q6_K's are signed).
macro_rules! piece_of_two {
    ($high:literal, $at:literal) => {
        concat!(
            "tileloadd tmm6, [{lo} + {s}*1 + ",
            $at,
            "]\n",
            "tileloadd tmm4, [{x} + {s}*1 + ",
            $at,
            "]\n",
            "tdpbusd tmm0, tmm6, tmm4\n",
            "tileloadd tmm7, [{hi} + {s}*1 + ",
            $at,
            "]\n",
            $high,
            " tmm1, tmm7, tmm4\n",
            "tileloadd tmm5, [{x} + {s}*1 + 4096 + ",
            $at,
            "]\n",
            "tdpbusd tmm2, tmm6, tmm5\n",
            $high,
            " tmm3, tmm7, tmm5\n",
        )
    };
}

/// One piece of [`multiply`]'s program for one activation tile, on tmm2–4 or tmm5–7 (`$x`
/// the activations, `$lo` and `$hi` the weights): a piece's loads then need not wait for the
/// products reading the piece before (tiles are not renamed). Sums in tmm0–1.
macro_rules! piece_of_one {
    ($high:literal, $at:literal, $x:literal, $lo:literal, $hi:literal) => {
        concat!(
            "tileloadd ",
            $x,
            ", [{x} + {s}*1 + ",
            $at,
            "]\n",
            "tileloadd ",
            $lo,
            ", [{lo} + {s}*1 + ",
            $at,
            "]\n",
            "tdpbusd tmm0, ",
            $lo,
            ", ",
            $x,
            "\n",
            "tileloadd ",
            $hi,
            ", [{hi} + {s}*1 + ",
            $at,
            "]\n",
            $high,
            " tmm1, ",
            $hi,
            ", ",
            $x,
            "\n",
        )
    };
}

/// The tile program of [`multiply`]: a whole block's four pieces for two activation tiles or
/// one, then the sums stored.
macro_rules! tile_program {
    (two, $high:literal) => {
        concat!(
            "tilezero tmm0\n",
            "tilezero tmm1\n",
            "tilezero tmm2\n",
            "tilezero tmm3\n",
            piece_of_two!($high, "0"),
            piece_of_two!($high, "1024"),
            piece_of_two!($high, "2048"),
            piece_of_two!($high, "3072"),
            "tilestored [{out} + {s}*1], tmm0\n",
            "tilestored [{out} + {s}*1 + 1024], tmm1\n",
            "tilestored [{out} + {s}*1 + 2048], tmm2\n",
            "tilestored [{out} + {s}*1 + 3072], tmm3\n",
        )
    };
    (one, $high:literal) => {
        concat!(
            "tilezero tmm0\n",
            "tilezero tmm1\n",
            piece_of_one!($high, "0", "tmm2", "tmm3", "tmm4"),
            piece_of_one!($high, "1024", "tmm5", "tmm6", "tmm7"),
            piece_of_one!($high, "2048", "tmm2", "tmm3", "tmm4"),
            piece_of_one!($high, "3072", "tmm5", "tmm6", "tmm7"),
            "tilestored [{out} + {s}*1], tmm0\n",
            "tilestored [{out} + {s}*1 + 1024], tmm1\n",
        )
    };
}

/// The sums of one activation tile, or of two (`pair`), against the unpacked weights over a
/// whole block, into `sums`: per tile, the low bytes' then the high bits' (products with
/// Q6_K's signed high bytes are `tdpbssd`). Each weight tile loaded serves both activation
/// tiles of a pair, and the four accumulators' products do not wait on one another.
///
/// # Safety
/// Tiles configured by [`TilesInUse::take`]; `pieces` is four tiles per activation tile.
#[rustfmt::skip]
unsafe fn multiply(
    format: Format,
    pieces: &[u8],
    pair: bool,
    unpacked: &WeightTiles,
    sums: &mut Sums,
) {
    let x = pieces.as_ptr();
    let (lo, hi) = (unpacked.low.as_ptr(), unpacked.high.as_ptr());
    let out = sums.0.as_mut_ptr();
    // SAFETY: every load reads 16 rows of 64 bytes at a stride of 64 from the start of a
    // 1,024-byte tile (`pieces`' four or eight, `unpacked`'s fields of four), every store
    // writes one of `sums`' four 1,024-byte tiles.
    unsafe {
        match (format, pair) {
            (Format::Q4K, true) => asm!(
                tile_program!(two, "tdpbusd"),
                x = in(reg) x, lo = in(reg) lo, hi = in(reg) hi, out = in(reg) out,
                s = in(reg) 64usize, options(nostack),
            ),
            (Format::Q6K, true) => asm!(
                tile_program!(two, "tdpbssd"),
                x = in(reg) x, lo = in(reg) lo, hi = in(reg) hi, out = in(reg) out,
                s = in(reg) 64usize, options(nostack),
            ),
            (Format::Q4K, false) => asm!(
                tile_program!(one, "tdpbusd"),
                x = in(reg) x, lo = in(reg) lo, hi = in(reg) hi, out = in(reg) out,
                s = in(reg) 64usize, options(nostack),
            ),
            (Format::Q6K, false) => asm!(
                tile_program!(one, "tdpbssd"),
                x = in(reg) x, lo = in(reg) lo, hi = in(reg) hi, out = in(reg) out,
                s = in(reg) 64usize, options(nostack),
            ),
        }
    }
}

/// Weight row `r`'s sums for the 16 activation rows of a tile (`sums` from `first`: the low
/// bytes', then the high bits'), times its block scales. For Q4_K, `sub_sums` the tile's
/// sub-block sums in pairs ([`PackedActivations`]): the mins' term `dmin · Σ m·sum` is four
/// `vpdpwssd` on the vector units, which the tiles would have taken a third accumulator for.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
fn block_value(
    sums: &Sums,
    first: usize,
    unpacked: &WeightTiles,
    sub_sums: Option<&[__m512i; PAIRS]>,
    r: usize,
) -> __m512 {
    let row = |k: usize| {
        // SAFETY: row `r` (below 16) of a 16 × 16 tile.
        unsafe { _mm512_loadu_si512(sums.0[k].as_ptr().add(r * TILE_ROWS) as *const _) }
    };
    let scaled = _mm512_add_epi32(row(first), _mm512_slli_epi32(row(first + 1), 8));
    let value = _mm512_mul_ps(_mm512_cvtepi32_ps(scaled), _mm512_set1_ps(unpacked.d[r]));
    let Some(sub_sums) = sub_sums else {
        return value;
    };
    let mut mins = _mm512_setzero_si512();
    for (pair, sums) in sub_sums.iter().enumerate() {
        mins = _mm512_dpwssd_epi32(mins, *sums, _mm512_set1_epi32(unpacked.min_pairs[r][pair]));
    }
    _mm512_fnmadd_ps(
        _mm512_cvtepi32_ps(mins),
        _mm512_set1_ps(unpacked.dmin[r]),
        value,
    )
}

/// Row `r` of a Q4_K block into the tiles. The pieces follow the kernel's load order: the low
/// nibbles of bytes 0–63 (sub-blocks 0 and 2), their high nibbles (1 and 3), then of bytes
/// 64–127 (4 and 6, 5 and 7).
///
/// A piece's two sub-blocks' products `s·q` for every `q` (0–15) are 32 words, one multiply;
/// each value's low and high bytes are then looked up by `vpermb` at `2q` and `2q + 1` (plus 32
/// for the second sub-block). Half the instructions of widening, multiplying and narrowing
/// each value (a product of 16 rows spent most of its time unpacking).
#[target_feature(enable = "avx512f,avx512bw,avx512vbmi,f16c")]
fn unpack_q4k(block: &[u8], r: usize, unpacked: &mut WeightTiles) {
    let Some(packed) = block[4..16].first_chunk::<12>() else {
        return;
    };
    let (scales, mins) = super::q4k::unpack_scales(packed);
    let d = _mm_cvtph_ps(_mm_cvtsi32_si128(i32::from_le_bytes([
        block[0], block[1], block[2], block[3],
    ])));
    unpacked.d[r] = _mm_cvtss_f32(d);
    unpacked.dmin[r] = _mm_cvtss_f32(_mm_shuffle_ps::<1>(d, d));
    let min = |s: usize| (mins >> (8 * s)) as u8 as i16;
    unpacked.min_pairs[r] = [0, 1, 2, 3].map(|pair| pack_words(min(2 * pair), min(2 * pair + 1)));
    let nibble = _mm512_set1_epi8(0x0F);
    // SAFETY: the block is 144 bytes: 128 from 16.
    let (first, second) = unsafe {
        (
            _mm512_loadu_si512(block.as_ptr().add(16) as *const _),
            _mm512_loadu_si512(block.as_ptr().add(80) as *const _),
        )
    };
    // Words 0–7: the sub-blocks' scales.
    let scale_words = _mm512_cvtepu8_epi16(_mm256_set1_epi64x(scales as i64));
    #[rustfmt::skip]
    let counting = _mm512_set_epi16(
        15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0,
        15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0,
    );
    let second_half =
        _mm512_mask_blend_epi8(u64::MAX << 32, _mm512_setzero_si512(), _mm512_set1_epi8(32));
    let one = _mm512_set1_epi8(1);
    let pieces = [
        (_mm512_and_si512(first, nibble), [0, 2]),
        (
            _mm512_and_si512(_mm512_srli_epi16::<4>(first), nibble),
            [1, 3],
        ),
        (_mm512_and_si512(second, nibble), [4, 6]),
        (
            _mm512_and_si512(_mm512_srli_epi16::<4>(second), nibble),
            [5, 7],
        ),
    ];
    let at = r * 64;
    for (piece, (values, [a, b])) in pieces.into_iter().enumerate() {
        let pair =
            _mm512_mask_blend_epi16(u32::MAX << 16, _mm512_set1_epi16(a), _mm512_set1_epi16(b));
        let products = _mm512_mullo_epi16(_mm512_permutexvar_epi16(pair, scale_words), counting);
        let low_at = _mm512_add_epi8(_mm512_add_epi8(values, values), second_half);
        let low = _mm512_permutexvar_epi8(low_at, products);
        let high = _mm512_permutexvar_epi8(_mm512_add_epi8(low_at, one), products);
        // SAFETY: row `r` (below 16) of 1,024-byte tiles: 64 bytes from `at`.
        unsafe {
            _mm512_storeu_si512(unpacked.low[piece].as_mut_ptr().add(at) as *mut _, low);
            _mm512_storeu_si512(unpacked.high[piece].as_mut_ptr().add(at) as *mut _, high);
        }
    }
}

/// Row `r` of a Q6_K block into the tiles: pieces of 64 values in order, each value
/// `s·(q − 32)` under its 16-value scale, as 16-bit products whose low and high bytes are
/// gathered by `vpermt2b`.
#[target_feature(enable = "avx512f,avx512bw,avx512vbmi,f16c")]
fn unpack_q6k(block: &[u8], r: usize, unpacked: &mut WeightTiles) {
    /// Byte `i` of the result: byte `2i` (`LOW`) or `2i + 1` (`HIGH`) of two vectors' 128.
    const LOW: [u8; 64] = byte_picks(0);
    const HIGH: [u8; 64] = byte_picks(1);
    const fn byte_picks(first: u8) -> [u8; 64] {
        let mut picks = [0u8; 64];
        let mut i = 0;
        while i < 64 {
            picks[i] = 2 * i as u8 + first;
            i += 1;
        }
        picks
    }
    let values = super::q6k::block_values(block);
    unpacked.d[r] = super::q6k::f16_to_f32(u16::from_le_bytes([block[208], block[209]]));
    // SAFETY: the block is 210 bytes: the 16 scales from 192; `LOW` and `HIGH` are 64 bytes.
    let (scale_words, low_picks, high_picks) = unsafe {
        (
            _mm512_castsi256_si512(_mm256_cvtepi8_epi16(_mm_loadu_si128(
                block.as_ptr().add(192) as *const _,
            ))),
            _mm512_loadu_si512(LOW.as_ptr() as *const _),
            _mm512_loadu_si512(HIGH.as_ptr() as *const _),
        )
    };
    let offset = _mm512_set1_epi16(32);
    let at = r * 64;
    for (piece, values) in values.into_iter().enumerate() {
        let halves = [
            _mm512_cvtepu8_epi16(_mm512_castsi512_si256(values)),
            _mm512_cvtepu8_epi16(_mm512_extracti64x4_epi64::<1>(values)),
        ];
        let products = [0, 1].map(|h| {
            // Words 0–15 under scale 4·piece + 2h, 16–31 under the next.
            let first = (4 * piece + 2 * h) as i16;
            let scales = _mm512_permutexvar_epi16(
                _mm512_mask_blend_epi16(
                    u32::MAX << 16,
                    _mm512_set1_epi16(first),
                    _mm512_set1_epi16(first + 1),
                ),
                scale_words,
            );
            _mm512_mullo_epi16(_mm512_sub_epi16(halves[h], offset), scales)
        });
        let low = _mm512_permutex2var_epi8(products[0], low_picks, products[1]);
        let high = _mm512_permutex2var_epi8(products[0], high_picks, products[1]);
        // SAFETY: row `r` (below 16) of 1,024-byte tiles: 64 bytes from `at`.
        unsafe {
            _mm512_storeu_si512(unpacked.low[piece].as_mut_ptr().add(at) as *mut _, low);
            _mm512_storeu_si512(unpacked.high[piece].as_mut_ptr().add(at) as *mut _, high);
        }
    }
}

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
//! tiles, its low byte and its high bits, and `m` into a third: three accumulators sum a whole
//! 256-value block in four instructions each, and only then are stored and multiplied by the
//! block's float scales. A Q6_K value is `d·s·(q − 32)` (s signed, one per 16 values):
//! `s·(q − 32)` is within ±4,096, a low byte (unsigned) and a signed high byte, two tiles.
//! The integers are those the VNNI kernels sum, from the same activation bytes: the results
//! differ from theirs only in float rounding.

use std::arch::asm;
use std::arch::x86_64::*;
use std::sync::OnceLock;

use super::{ActivationBlock, BLOCK_VALUES, Format};

/// Rows of a tile: weight rows of the accumulators and of the weight tiles, activation rows of
/// the accumulators' columns.
pub const TILE_ROWS: usize = 16;
/// 64-value pieces of a 256-value block: one instruction each.
const PIECES: usize = BLOCK_VALUES / 64;
/// Bytes of a full tile (16 rows of 64 bytes).
const TILE_BYTES: usize = 1024;
/// Activation tiles one pass over a group of weight rows takes (128 rows): their bytes, at
/// most 1.1 MB for Qwen2.5-Coder-1.5B's widest matrix, stay in the core's cache while the
/// group's blocks are unpacked once for all of them.
const TILES_PER_PASS: usize = 8;

/// Whether the CPU has AMX with 8-bit products and this process may use its tiles (Linux asks
/// each process to request them: `arch_prctl(ARCH_REQ_XCOMP_PERM)`); asked once.
pub fn available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    *AVAILABLE.get_or_init(|| {
        cpu_has_amx()
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512vbmi")
            && tiles_granted()
    })
}

fn cpu_has_amx() -> bool {
    // CPUID leaf 7, sub-leaf 0, EDX: bit 24 AMX-TILE, bit 25 AMX-INT8.
    let leaf7 = __cpuid_count(7, 0);
    let tile = leaf7.edx & (1 << 24) != 0;
    let int8 = leaf7.edx & (1 << 25) != 0;
    tile && int8
}

#[cfg(target_os = "linux")]
fn tiles_granted() -> bool {
    const SYS_ARCH_PRCTL: i64 = 158;
    const ARCH_REQ_XCOMP_PERM: i64 = 0x1023;
    const XFEATURE_XTILEDATA: i64 = 18;
    let result: i64;
    // SAFETY: the system call asks the kernel to let this process use the tile registers; it
    // reads and writes none of the program's memory, and clobbers only rax, rcx and r11.
    unsafe {
        asm!(
            "syscall",
            inlateout("rax") SYS_ARCH_PRCTL => result,
            in("rdi") ARCH_REQ_XCOMP_PERM,
            in("rsi") XFEATURE_XTILEDATA,
            lateout("rcx") _,
            lateout("r11") _,
            options(nostack),
        );
    }
    result == 0
}

#[cfg(not(target_os = "linux"))]
fn tiles_granted() -> bool {
    false
}

/// The activation rows quantised and laid out as the tiles take them: per block, per tile of
/// 16 rows, per 64-value piece, 16 groups of four values, each group for the 16 rows in turn
/// (`tdpbusd`'s second operand). Rows past the last are zero.
pub struct PackedActivations {
    bytes: Vec<u8>,
    /// Per block, per (padded) row: the row's scale for that block (0 for padding).
    scales: Vec<f32>,
    rows: usize,
    tiles: usize,
    blocks: usize,
}

impl PackedActivations {
    /// `activations`: `rows` rows of `blocks` blocks each; Q4_K's pieces are its load order
    /// (`ActivationBlock::q4k_order`), Q6_K's the values in order.
    pub fn new(
        activations: &[ActivationBlock],
        rows: usize,
        blocks: usize,
        format: Format,
    ) -> PackedActivations {
        assert_eq!(activations.len(), rows * blocks, "activation blocks");
        let tiles = rows.div_ceil(TILE_ROWS);
        let mut bytes = vec![0u8; blocks * tiles * PIECES * TILE_BYTES];
        let mut scales = vec![0f32; blocks * tiles * TILE_ROWS];
        for (i, row) in activations.chunks_exact(blocks).enumerate() {
            let (tile, in_tile) = (i / TILE_ROWS, i % TILE_ROWS);
            for (b, block) in row.iter().enumerate() {
                scales[b * tiles * TILE_ROWS + i] = block.scale;
                let values = match format {
                    Format::Q4K => &block.q4k_order,
                    Format::Q6K => &block.natural,
                };
                for (piece, values) in values.chunks_exact(64).enumerate() {
                    let at = ((b * tiles + tile) * PIECES + piece) * TILE_BYTES + 4 * in_tile;
                    for (group, four) in values.chunks_exact(4).enumerate() {
                        let four = [four[0] as u8, four[1] as u8, four[2] as u8, four[3] as u8];
                        bytes[at + 64 * group..at + 64 * group + 4].copy_from_slice(&four);
                    }
                }
            }
        }
        PackedActivations {
            bytes,
            scales,
            rows,
            tiles,
            blocks,
        }
    }
}

/// A group of 16 weight rows of one block, unpacked for the tiles: per piece, 16 rows of 64
/// bytes each — `low` and `high` the low byte and the high bits of the scaled values, `mins`
/// (Q4_K) each value's sub-block min — and each row's float scales.
#[repr(C, align(64))]
struct WeightTiles {
    low: [[u8; TILE_BYTES]; PIECES],
    high: [[u8; TILE_BYTES]; PIECES],
    mins: [[u8; TILE_BYTES]; PIECES],
    d: [f32; TILE_ROWS],
    dmin: [f32; TILE_ROWS],
}

/// The three accumulators as stored: per tile, 16 weight rows of 16 activation rows.
#[repr(C, align(64))]
struct Sums([[i32; TILE_ROWS * TILE_ROWS]; 3]);

/// The tile configuration `ldtilecfg` reads (64 bytes, palette 1).
#[repr(C, align(64))]
struct TileConfig {
    palette: u8,
    start_row: u8,
    reserved: [u8; 14],
    bytes_per_row: [u16; 16],
    rows: [u8; 16],
}

/// The tiles a thread uses for its part of a product, and the configuration they replace: a
/// thread of candle's pool that ran candle's own AMX kernel keeps that kernel's configuration
/// and expects it still there, so it is put back when done.
struct TilesInUse {
    previous: TileConfig,
}

impl TilesInUse {
    /// All eight 16 × 64 bytes: see [`multiply`].
    ///
    /// # Safety
    /// [`available`] said yes (else the instructions fault).
    unsafe fn take() -> TilesInUse {
        let mut previous = TileConfig {
            palette: 0,
            start_row: 0,
            reserved: [0; 14],
            bytes_per_row: [0; 16],
            rows: [0; 16],
        };
        let mut ours = TileConfig {
            palette: 1,
            start_row: 0,
            reserved: [0; 14],
            bytes_per_row: [0; 16],
            rows: [0; 16],
        };
        for t in 0..8 {
            ours.bytes_per_row[t] = 64;
            ours.rows[t] = TILE_ROWS as u8;
        }
        // SAFETY: both point at 64 bytes, aligned to 64 as the instructions ask; the CPU has
        // AMX (the caller's promise).
        unsafe {
            asm!("sttilecfg [{}]", in(reg) &mut previous, options(nostack));
            asm!("ldtilecfg [{}]", in(reg) &ours, options(nostack));
        }
        TilesInUse { previous }
    }
}

impl Drop for TilesInUse {
    fn drop(&mut self) {
        // SAFETY: only `take` makes a `TilesInUse`, on a CPU with AMX; `previous` is 64
        // bytes aligned to 64; a palette of 0 means no configuration was loaded before.
        unsafe {
            if self.previous.palette == 0 {
                asm!("tilerelease", options(nostack));
            } else {
                asm!("ldtilecfg [{}]", in(reg) &self.previous, options(nostack));
            }
        }
    }
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

#[target_feature(enable = "avx512f,avx512bw,avx512vbmi,fma,f16c")]
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
        mins: [[0; TILE_BYTES]; PIECES],
        d: [0.0; TILE_ROWS],
        dmin: [0.0; TILE_ROWS],
    };
    // Two: a block is unpacked while the tiles read the one before. A tile load waits for
    // the stores to its bytes to reach the cache; loading the block just written stalled on
    // them (half the time of a product of a few rows).
    let mut unpacked = Box::new([empty(), empty()]);
    let mut sums = Sums([[0; TILE_ROWS * TILE_ROWS]; 3]);
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
                for (slot, tile) in tiles.clone().enumerate() {
                    let at = (b * activations.tiles + tile) * PIECES * TILE_BYTES;
                    let pieces = &activations.bytes[at..at + PIECES * TILE_BYTES];
                    // SAFETY: `pieces` holds four tiles, `unpacked` four of each kind, `sums`
                    // three; the tiles are configured (`_tiles`).
                    unsafe { multiply(format, pieces, unpacked, &mut sums) };
                    let scales_at = b * activations.tiles * TILE_ROWS + tile * TILE_ROWS;
                    // SAFETY: 16 scales from `scales_at`: each block has `tiles` × 16.
                    let scales =
                        unsafe { _mm512_loadu_ps(activations.scales.as_ptr().add(scales_at)) };
                    for (r, total) in totals.iter_mut().enumerate() {
                        let value = block_value(format, &sums, unpacked, r);
                        total[slot] = _mm512_fmadd_ps(value, scales, total[slot]);
                    }
                }
            }
            for (r, total) in totals.iter().enumerate() {
                for (slot, tile) in tiles.clone().enumerate() {
                    let mut lanes = [0f32; TILE_ROWS];
                    // SAFETY: `lanes` is 16 floats.
                    unsafe { _mm512_storeu_ps(lanes.as_mut_ptr(), total[slot]) };
                    let first = tile * TILE_ROWS;
                    let last = (first + TILE_ROWS).min(activations.rows);
                    for (i, value) in (first..last).zip(lanes) {
                        // SAFETY: `i` is an activation row, `group * 16 + r` a column of this
                        // thread's groups: inside `out` and written by no other thread.
                        unsafe { *out.add(i * out_stride + group * TILE_ROWS + r) = value };
                    }
                }
            }
        }
    }
}

/// The three (Q6_K: two) accumulators of one activation tile against the unpacked weights,
/// summed over a whole block, into `sums`.
///
/// # Safety
/// Tiles configured by [`TilesInUse::take`]; `pieces` is four tiles.
unsafe fn multiply(format: Format, pieces: &[u8], unpacked: &WeightTiles, sums: &mut Sums) {
    let x = pieces.as_ptr();
    let (low, high, mins) = (
        unpacked.low.as_ptr(),
        unpacked.high.as_ptr(),
        unpacked.mins.as_ptr(),
    );
    let out = sums.0.as_mut_ptr();
    // SAFETY: every load reads 16 rows of 64 bytes at a stride of 64 from the start of a
    // 1,024-byte tile (`pieces`' four, `unpacked`'s fields of four), every store writes one of
    // `sums`' three 1,024-byte tiles.
    unsafe {
        match format {
            // tmm0–2 the sums of the low bytes, the high bits and the mins; the activations
            // alternate between tmm3 and tmm7 so that a piece's load need not wait for the
            // products reading the piece before (tiles are not renamed).
            Format::Q4K => asm!(
                "tilezero tmm0",
                "tilezero tmm1",
                "tilezero tmm2",
                "tileloadd tmm3, [{x} + {s}*1]",
                "tileloadd tmm4, [{lo} + {s}*1]",
                "tdpbusd tmm0, tmm4, tmm3",
                "tileloadd tmm5, [{hi} + {s}*1]",
                "tdpbusd tmm1, tmm5, tmm3",
                "tileloadd tmm6, [{mn} + {s}*1]",
                "tdpbusd tmm2, tmm6, tmm3",
                "tileloadd tmm7, [{x} + {s}*1 + 1024]",
                "tileloadd tmm4, [{lo} + {s}*1 + 1024]",
                "tdpbusd tmm0, tmm4, tmm7",
                "tileloadd tmm5, [{hi} + {s}*1 + 1024]",
                "tdpbusd tmm1, tmm5, tmm7",
                "tileloadd tmm6, [{mn} + {s}*1 + 1024]",
                "tdpbusd tmm2, tmm6, tmm7",
                "tileloadd tmm3, [{x} + {s}*1 + 2048]",
                "tileloadd tmm4, [{lo} + {s}*1 + 2048]",
                "tdpbusd tmm0, tmm4, tmm3",
                "tileloadd tmm5, [{hi} + {s}*1 + 2048]",
                "tdpbusd tmm1, tmm5, tmm3",
                "tileloadd tmm6, [{mn} + {s}*1 + 2048]",
                "tdpbusd tmm2, tmm6, tmm3",
                "tileloadd tmm7, [{x} + {s}*1 + 3072]",
                "tileloadd tmm4, [{lo} + {s}*1 + 3072]",
                "tdpbusd tmm0, tmm4, tmm7",
                "tileloadd tmm5, [{hi} + {s}*1 + 3072]",
                "tdpbusd tmm1, tmm5, tmm7",
                "tileloadd tmm6, [{mn} + {s}*1 + 3072]",
                "tdpbusd tmm2, tmm6, tmm7",
                "tilestored [{out} + {s}*1], tmm0",
                "tilestored [{out} + {s}*1 + 1024], tmm1",
                "tilestored [{out} + {s}*1 + 2048], tmm2",
                x = in(reg) x,
                lo = in(reg) low,
                hi = in(reg) high,
                mn = in(reg) mins,
                out = in(reg) out,
                s = in(reg) 64usize,
                options(nostack),
            ),
            // tmm0–1 the sums of the low bytes and the (signed) high bytes; the weights
            // alternate between tmm4–5 and tmm6 with tmm2.
            Format::Q6K => asm!(
                "tilezero tmm0",
                "tilezero tmm1",
                "tileloadd tmm3, [{x} + {s}*1]",
                "tileloadd tmm4, [{lo} + {s}*1]",
                "tdpbusd tmm0, tmm4, tmm3",
                "tileloadd tmm5, [{hi} + {s}*1]",
                "tdpbssd tmm1, tmm5, tmm3",
                "tileloadd tmm7, [{x} + {s}*1 + 1024]",
                "tileloadd tmm6, [{lo} + {s}*1 + 1024]",
                "tdpbusd tmm0, tmm6, tmm7",
                "tileloadd tmm2, [{hi} + {s}*1 + 1024]",
                "tdpbssd tmm1, tmm2, tmm7",
                "tileloadd tmm3, [{x} + {s}*1 + 2048]",
                "tileloadd tmm4, [{lo} + {s}*1 + 2048]",
                "tdpbusd tmm0, tmm4, tmm3",
                "tileloadd tmm5, [{hi} + {s}*1 + 2048]",
                "tdpbssd tmm1, tmm5, tmm3",
                "tileloadd tmm7, [{x} + {s}*1 + 3072]",
                "tileloadd tmm6, [{lo} + {s}*1 + 3072]",
                "tdpbusd tmm0, tmm6, tmm7",
                "tileloadd tmm2, [{hi} + {s}*1 + 3072]",
                "tdpbssd tmm1, tmm2, tmm7",
                "tilestored [{out} + {s}*1], tmm0",
                "tilestored [{out} + {s}*1 + 1024], tmm1",
                x = in(reg) x,
                lo = in(reg) low,
                hi = in(reg) high,
                out = in(reg) out,
                s = in(reg) 64usize,
                options(nostack),
            ),
        }
    }
}

/// Weight row `r`'s sums for the 16 activation rows of a tile, times its block scales.
#[target_feature(enable = "avx512f,avx512bw")]
#[inline]
fn block_value(format: Format, sums: &Sums, unpacked: &WeightTiles, r: usize) -> __m512 {
    let row = |k: usize| {
        // SAFETY: row `r` (below 16) of a 16 × 16 tile.
        unsafe { _mm512_loadu_si512(sums.0[k].as_ptr().add(r * TILE_ROWS) as *const _) }
    };
    let scaled = _mm512_add_epi32(row(0), _mm512_slli_epi32(row(1), 8));
    let value = _mm512_mul_ps(_mm512_cvtepi32_ps(scaled), _mm512_set1_ps(unpacked.d[r]));
    match format {
        Format::Q4K => _mm512_fnmadd_ps(
            _mm512_cvtepi32_ps(row(2)),
            _mm512_set1_ps(unpacked.dmin[r]),
            value,
        ),
        Format::Q6K => value,
    }
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
    let nibble = _mm512_set1_epi8(0x0F);
    // SAFETY: the block is 144 bytes: 128 from 16.
    let (first, second) = unsafe {
        (
            _mm512_loadu_si512(block.as_ptr().add(16) as *const _),
            _mm512_loadu_si512(block.as_ptr().add(80) as *const _),
        )
    };
    // Words 0–7: the sub-blocks' scales; bytes 0–7: their mins.
    let scale_words = _mm512_cvtepu8_epi16(_mm256_set1_epi64x(scales as i64));
    let min_bytes = _mm512_set1_epi64(mins as i64);
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
        let mins = _mm512_permutexvar_epi8(
            _mm512_mask_blend_epi8(
                u64::MAX << 32,
                _mm512_set1_epi8(a as i8),
                _mm512_set1_epi8(b as i8),
            ),
            min_bytes,
        );
        // SAFETY: row `r` (below 16) of 1,024-byte tiles: 64 bytes from `at`.
        unsafe {
            _mm512_storeu_si512(unpacked.low[piece].as_mut_ptr().add(at) as *mut _, low);
            _mm512_storeu_si512(unpacked.high[piece].as_mut_ptr().add(at) as *mut _, high);
            _mm512_storeu_si512(unpacked.mins[piece].as_mut_ptr().add(at) as *mut _, mins);
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

//! The Q4_K × 8-bit kernel with AVX-512 VNNI: one weight row against up to eight activation
//! rows, each block's weights unpacked once for all of them.
//!
//! Per block: two 64-byte loads of the 4-bit values; low and high nibbles by mask and shift
//! (four vectors of 64 unsigned bytes); per activation row four `vpdpbusd` against the
//! activation's 64-byte vectors (arranged to match by `ActivationBlock::quantise`), each giving
//! 16 sums of four products: lanes 0–7 belong to one 32-value sub-block, 8–15 to another, so the
//! sub-block scales are spread to match (`pair_scales`) once per block and multiplied in by
//! `scaled_block_dot` (packed to 16 bits: a 3-token step ~90 → ~84 ms against 32-bit multiplies,
//! at 2,400 positions). One float multiply by the two scales per block and row; the mins
//! through the activation's sub-block sums.

use std::arch::x86_64::*;

use super::{ActivationBlock, Format, MAX_ROWS, scaled_block_dot};

const BLOCK_BYTES: usize = Format::Q4K.block_bytes();

/// Offsets inside a block.
const D_AT: usize = 0;
const SCALES_AT: usize = 4;
const VALUES_AT: usize = 16;

/// The 16-bit scales of a packed pair of sums vectors (`_mm512_packs_epi32(first, second)`:
/// per 128-bit lane, four sums of `first` then four of `second`), from the scales of sub-blocks
/// `first` (`first`'s lanes 0–7), `first + 2` (its lanes 8–15), `first + 1` and `first + 3`
/// (`second`'s).
#[target_feature(enable = "avx512f,avx512bw")]
fn pair_scales(scale_bytes: __m128i, first: i8) -> __m512i {
    let (a, b, c, d) = (first, first + 1, first + 2, first + 3);
    let order = _mm_setr_epi8(a, a, a, a, b, b, b, b, c, c, c, c, d, d, d, d);
    // 128-bit lanes: [a×4 b×4], [c×4 d×4]; wanted [a b], [a b], [c d], [c d].
    let halves = _mm256_cvtepu8_epi16(_mm_shuffle_epi8(scale_bytes, order));
    let wide = _mm512_castsi256_si512(halves);
    _mm512_shuffle_i64x2::<0b01_01_00_00>(wide, wide)
}

/// The dot products of one weight row (`row`: whole Q4_K blocks, `blocks` of them) with `M`
/// activation rows (`activations`: `M` rows of `blocks`), into `dots[..M]`.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni,fma,f16c")]
pub(super) fn rows_of<const M: usize>(
    row: &[u8],
    activations: &[ActivationBlock],
    blocks: usize,
    dots: &mut [f32; MAX_ROWS],
) {
    let nibble = _mm512_set1_epi8(0x0F);
    let mut sums = [_mm512_setzero_ps(); M];
    let mut mins = [_mm_setzero_ps(); M];
    for (b, block) in row.chunks_exact(BLOCK_BYTES).enumerate() {
        super::prefetch_ahead(block.as_ptr(), BLOCK_BYTES);
        let Some(packed) = block[SCALES_AT..SCALES_AT + 12].first_chunk::<12>() else {
            continue;
        };
        let (scales, min_scales) = unpack_scales(packed);
        let scale_bytes = _mm_cvtsi64_si128(scales as i64);
        let min_bytes = _mm_cvtsi64_si128(min_scales as i64);
        let d_and_min = i32::from_le_bytes([
            block[D_AT],
            block[D_AT + 1],
            block[D_AT + 2],
            block[D_AT + 3],
        ]);
        // SAFETY: `block` is 144 bytes, 128 read from VALUES_AT.
        let (low, high) = unsafe {
            (
                _mm512_loadu_si512(block.as_ptr().add(VALUES_AT) as *const _),
                _mm512_loadu_si512(block.as_ptr().add(VALUES_AT + 64) as *const _),
            )
        };
        let weights = [
            _mm512_and_si512(low, nibble),
            _mm512_and_si512(_mm512_srli_epi16(low, 4), nibble),
            _mm512_and_si512(high, nibble),
            _mm512_and_si512(_mm512_srli_epi16(high, 4), nibble),
        ];
        // Low nibbles of the first 64 bytes hold sub-blocks 0 and 2, high nibbles 1 and 3; of
        // the next 64 bytes, 4 and 6, then 5 and 7.
        let pair_scales = [pair_scales(scale_bytes, 0), pair_scales(scale_bytes, 4)];
        let min_words = _mm_cvtepu8_epi16(min_bytes);
        let d_and_min = _mm_cvtph_ps(_mm_cvtsi32_si128(d_and_min));
        let d = _mm_cvtss_f32(d_and_min);
        let d_min = _mm_cvtss_f32(_mm_shuffle_ps(d_and_min, d_and_min, 1));
        for i in 0..M {
            let a = &activations[i * blocks + b];
            let total = scaled_block_dot(&weights, &pair_scales, &a.q4k_order);
            sums[i] = _mm512_fmadd_ps(
                _mm512_cvtepi32_ps(total),
                _mm512_set1_ps(d * a.scale),
                sums[i],
            );
            // SAFETY: `sums32` is 8 × i16, 16 bytes.
            let block_sums = unsafe { _mm_loadu_si128(a.sums32.as_ptr() as *const __m128i) };
            let weighted = _mm_madd_epi16(min_words, block_sums);
            mins[i] = _mm_fmadd_ps(
                _mm_cvtepi32_ps(weighted),
                _mm_set1_ps(d_min * a.scale),
                mins[i],
            );
        }
    }
    for i in 0..M {
        let mut lanes = [0f32; 4];
        // SAFETY: `lanes` is 4 × f32.
        unsafe { _mm_storeu_ps(lanes.as_mut_ptr(), mins[i]) };
        dots[i] = _mm512_reduce_add_ps(sums[i]) - lanes.iter().sum::<f32>();
    }
}

/// The 6-bit scales and mins of a block's eight sub-blocks, from its 12 packed bytes: bytes
/// 0–3 hold scales 0–3 (low 6 bits), 4–7 mins 0–3; bytes 8–11 the low 4 bits of scales 4–7
/// (low nibble) and of mins 4–7 (high nibble), whose top 2 bits are the top bits of bytes 0–3
/// (scales) and 4–7 (mins). Four bytes at a time, as little-endian words; byte `j` of each
/// result is sub-block `j`'s.
#[inline(always)]
pub fn unpack_scales(packed: &[u8; 12]) -> (u64, u64) {
    const LOW6: u32 = 0x3f3f_3f3f;
    const LOW4: u32 = 0x0f0f_0f0f;
    const LOW2: u32 = 0x0303_0303;
    let word =
        |i: usize| u32::from_le_bytes([packed[i], packed[i + 1], packed[i + 2], packed[i + 3]]);
    let (w0, w1, w2) = (word(0), word(4), word(8));
    let scales_low = w0 & LOW6;
    let mins_low = w1 & LOW6;
    let scales_high = (w2 & LOW4) | (((w0 >> 6) & LOW2) << 4);
    let mins_high = ((w2 >> 4) & LOW4) | (((w1 >> 6) & LOW2) << 4);
    (
        scales_low as u64 | (scales_high as u64) << 32,
        mins_low as u64 | (mins_high as u64) << 32,
    )
}

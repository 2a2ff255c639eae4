//! The Q6_K × 8-bit kernel with AVX-512 VNNI: one weight row against up to eight activation
//! rows, each block's 6-bit values assembled once for all of them.
//!
//! A Q6_K block (210 bytes) holds 256 values as 128 bytes of low 4 bits (`ql`), 64 bytes of
//! high 2 bits (`qh`), 16 signed 8-bit scales (one per 16 values) and an f16 scale. Per half of
//! the block (128 values): one 64-byte load of `ql` gives, as low nibbles, values 0–63 of the
//! half and, as high nibbles, values 64–127, in order; the 32 bytes of `qh` hold the two high
//! bits of four values each (bits 0–1: values 0–31, 2–3: 32–63, 4–5: 64–95, 6–7: 96–127),
//! broadcast to both halves of a vector and shifted per half. The values are stored plus 32:
//! `Σ (q − 32)·x = Σ q·x − 32 Σ x`, the second from the activation's 16-value sums.

use std::arch::x86_64::*;

use super::{ActivationBlock, Format, MAX_ROWS, scaled_block_dot};

const BLOCK_BYTES: usize = Format::Q6K.block_bytes();
/// Offsets inside a block.
const QL_AT: usize = 0;
const QH_AT: usize = 128;
const SCALES_AT: usize = 192;
const D_AT: usize = 208;

/// The 16-bit scales of a packed pair of sums vectors (`_mm512_packs_epi32(first, second)`:
/// per 128-bit lane `L`, four sums of `first` then four of `second`), for the vectors of values
/// 64·`k`… and 64·(`k` + 1)… (`first_scale` = 4·`k`): lane `j` of such a vector sums values
/// 4·`j`…, under scale 4·`k` + `j` / 4.
#[target_feature(enable = "avx512f,avx512bw")]
fn pair_scales(scales: __m128i, first_scale: i8) -> __m512i {
    let s = |i: i8| first_scale + i;
    let (a, b, c, d) = (s(0), s(4), s(1), s(5));
    let (e, f, g, h) = (s(2), s(6), s(3), s(7));
    #[rustfmt::skip]
    let order = _mm256_setr_epi8(
        a, a, a, a, b, b, b, b, c, c, c, c, d, d, d, d,
        e, e, e, e, f, f, f, f, g, g, g, g, h, h, h, h,
    );
    let bytes = _mm256_shuffle_epi8(_mm256_broadcastsi128_si256(scales), order);
    _mm512_cvtepi8_epi16(bytes)
}

/// The dot products of one weight row (`row`: whole Q6_K blocks, `blocks` of them) with `M`
/// activation rows (`activations`: `M` rows of `blocks`), into `dots[..M]`.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni,fma,f16c")]
pub(super) fn rows_of<const M: usize>(
    row: &[u8],
    activations: &[ActivationBlock],
    blocks: usize,
    dots: &mut [f32; MAX_ROWS],
) {
    let mut sums = [_mm512_setzero_ps(); M];
    let mut offsets = [_mm256_setzero_ps(); M];
    for (b, block) in row.chunks_exact(BLOCK_BYTES).enumerate() {
        super::prefetch_ahead(block.as_ptr(), BLOCK_BYTES);
        let d = f16_to_f32(u16::from_le_bytes([block[D_AT], block[D_AT + 1]]));
        let weights = block_values(block);
        // SAFETY: `block` is 210 bytes: 16 from SCALES_AT.
        let scales = unsafe { _mm_loadu_si128(block.as_ptr().add(SCALES_AT) as *const _) };
        let pair_scales = [pair_scales(scales, 0), pair_scales(scales, 8)];
        let scale_words = _mm256_cvtepi8_epi16(scales);
        for i in 0..M {
            let a = &activations[i * blocks + b];
            let total = scaled_block_dot(&weights, &pair_scales, &a.natural);
            sums[i] = _mm512_fmadd_ps(
                _mm512_cvtepi32_ps(total),
                _mm512_set1_ps(d * a.scale),
                sums[i],
            );
            // SAFETY: `sums16` is 16 × i16, 32 bytes.
            let block_sums = unsafe { _mm256_loadu_si256(a.sums16.as_ptr() as *const _) };
            let weighted = _mm256_madd_epi16(scale_words, block_sums);
            offsets[i] = _mm256_fmadd_ps(
                _mm256_cvtepi32_ps(weighted),
                _mm256_set1_ps(32.0 * d * a.scale),
                offsets[i],
            );
        }
    }
    for i in 0..M {
        let mut lanes = [0f32; 8];
        // SAFETY: `lanes` is 8 × f32.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), offsets[i]) };
        dots[i] = _mm512_reduce_add_ps(sums[i]) - lanes.iter().sum::<f32>();
    }
}

/// The four 64-value vectors of a block (`block`: its 210 bytes), in order: the 6-bit values,
/// unsigned (stored plus 32).
#[target_feature(enable = "avx512f,avx512bw")]
pub(super) fn block_values(block: &[u8]) -> [__m512i; 4] {
    assert!(
        block.len() >= BLOCK_BYTES,
        "a Q6_K block of {} bytes",
        block.len()
    );
    let nibble = _mm512_set1_epi8(0x0F);
    let two_bits = _mm512_set1_epi8(0x03);
    // Per 16-bit lane: the low half of the vector (values 0–31) shifts `qh` by 0 (or 4), the
    // high half (values 32–63) by 2 (or 6).
    let shifts_low = _mm512_inserti64x4(_mm512_set1_epi16(0), _mm256_set1_epi16(2), 1);
    let shifts_high = _mm512_inserti64x4(_mm512_set1_epi16(4), _mm256_set1_epi16(6), 1);
    // SAFETY: `block` is 210 bytes (checked): 2 × 64 from QL_AT, 2 × 32 from QH_AT.
    let (ql, qh) = unsafe {
        let p = block.as_ptr();
        (
            [
                _mm512_loadu_si512(p.add(QL_AT) as *const _),
                _mm512_loadu_si512(p.add(QL_AT + 64) as *const _),
            ],
            [
                _mm256_loadu_si256(p.add(QH_AT) as *const _),
                _mm256_loadu_si256(p.add(QH_AT + 32) as *const _),
            ],
        )
    };
    let mut weights = [_mm512_setzero_si512(); 4];
    for half in 0..2 {
        let high_bits = _mm512_broadcast_i64x4(qh[half]);
        let low_top = _mm512_and_si512(_mm512_srlv_epi16(high_bits, shifts_low), two_bits);
        let high_top = _mm512_and_si512(_mm512_srlv_epi16(high_bits, shifts_high), two_bits);
        weights[2 * half] = _mm512_or_si512(
            _mm512_and_si512(ql[half], nibble),
            _mm512_slli_epi16(low_top, 4),
        );
        weights[2 * half + 1] = _mm512_or_si512(
            _mm512_and_si512(_mm512_srli_epi16(ql[half], 4), nibble),
            _mm512_slli_epi16(high_top, 4),
        );
    }
    weights
}

#[target_feature(enable = "f16c")]
pub(super) fn f16_to_f32(h: u16) -> f32 {
    _mm_cvtss_f32(_mm_cvtph_ps(_mm_cvtsi32_si128(h as i32)))
}

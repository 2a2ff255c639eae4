//! Q4_K and Q6_K matrix products read straight from the GGUF's blocks: for decode steps (one to
//! [`MAX_FEED`] activation rows) on AVX-512 VNNI, and where the CPU has AMX, from
//! [`AMX_MIN_ROWS`] rows on (forced runs, a prompt's chunks) on its tiles (`amx`).
//!
//! Why not candle's: for a few rows candle repacks Q4_K into tiles of 16 rows with f32 scales
//! and mins, 1.33× the GGUF's bytes, and its tile kernel does per activation row nearly all
//! the work it does per weight tile, so a step of two or three tokens (the grammar's forced
//! tokens fed with the sampled one) costs nearly two or three steps; Q6_K goes to the same
//! tiles from two rows on. A decode step reads every weight once; on two cores that read is
//! the step's time. These products read the blocks as stored (candle keeps them: no memory is
//! added), unpack each block once for all the rows, and split the matrix's rows over candle's
//! own thread pool (the one its other products use, so no thread competes with it). Measured
//! with the `speed` example and the models bench: see the README's model figures.
//!
//! Used only where the CPU has AVX-512 with VNNI ([`DecodeMatrix::new`] says `None` elsewhere
//! and the caller keeps candle's product); `TACOS_EMBEDDED_MATVEC=candle` turns them off, to
//! compare. The activation rows are quantised to 8 bits per 256 values (one f32 scale each),
//! as candle's and llama.cpp's K-quant products do.

use std::ops::Range;
use std::sync::Arc;

use candle_core::quantized::{GgmlDType, QMatMul, QTensor};
use candle_core::{Module, Tensor};

use crate::pool::Shared;

#[cfg(target_arch = "x86_64")]
mod amx;
#[cfg(target_arch = "x86_64")]
mod q4k;
#[cfg(target_arch = "x86_64")]
mod q6k;

/// Values per K-quant block.
pub const BLOCK_VALUES: usize = 256;
/// The activation rows a kernel takes at once (its sums stay in registers).
pub const MAX_ROWS: usize = 8;
/// The most activation rows the VNNI kernels take, [`MAX_ROWS`] at a time against each weight
/// row (read from memory once, then from cache); more (a prompt) go to the AMX products where
/// they run, else to candle's product. A decode
/// step feeds the grammar's forced tokens with the sampled one: the Coordinator's replies force
/// runs of 11 (`","target":"none","xyz":null},{"task":"T`), which took ~235 ms a step here
/// against ~280 in candle's product, the Supervisor's runs of 20–26 as long either way (the
/// models bench's probes, Qwen2.5-Coder-1.5B, 2 threads). Up to 32, candle's product for a few
/// rows (which repacks the matrices on first use: ~0.65 s once) is not needed while decoding.
pub const MAX_FEED: usize = 32;
/// The fewest activation rows a product takes on AMX tiles where it can: fewer go to the
/// VNNI kernels, which need no unpacking into tiles. Measured (2 threads) on twenty 8960 × 1536
/// Q4_K matrices in turn, the weights streamed from memory as in a decode step, ms a matrix,
/// AMX / VNNI: 11 rows 1.48 / 1.28, 16 rows 1.57 / 1.74, 26 rows 1.92 / 3.05 (one row: 0.53);
/// in the models bench's mission calls the Coordinator's forced runs of 11 took as long either
/// way, the Supervisor's of 20–26 ~0.3 s less a call on AMX.
const AMX_MIN_ROWS: usize = 16;
// Products of more than MAX_FEED rows are taken only where AMX runs: they must reach it.
const _: () = assert!(AMX_MIN_ROWS <= MAX_FEED);
/// Output rows a thread takes at a time.
const ROWS_PER_GRAB: usize = 16;

/// The block formats these products read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// 144 bytes: f16 scale and min scale, 12 bytes of 6-bit sub-block scales and mins, 128
    /// bytes of 4-bit values.
    Q4K,
    /// 210 bytes: 128 bytes of low 4 bits, 64 of high 2 bits, 16 signed 8-bit scales, f16.
    Q6K,
}

impl Format {
    pub const fn block_bytes(self) -> usize {
        match self {
            Format::Q4K => 144,
            Format::Q6K => 210,
        }
    }

    fn of(dtype: GgmlDType) -> Option<Format> {
        match dtype {
            GgmlDType::Q4K => Some(Format::Q4K),
            GgmlDType::Q6K => Some(Format::Q6K),
            _ => None,
        }
    }
}

/// A layer's weight matrix: its products with a few rows (a decode step) by [`DecodeMatrix`]
/// when it is Q4_K or Q6_K and the CPU has the kernels, every other product by candle's.
pub struct Linear {
    candle: QMatMul,
    decode: Option<DecodeMatrix>,
}

impl Linear {
    pub fn new(weights: QTensor) -> candle_core::Result<Linear> {
        let weights = Arc::new(weights);
        Ok(Linear {
            decode: DecodeMatrix::new(&weights),
            candle: QMatMul::from_arc(weights)?,
        })
    }

    /// `x` (…, columns) times the matrix's transpose: (…, rows).
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let Some(matrix) = &self.decode else {
            return self.candle.forward(x);
        };
        let m = x.elem_count() / matrix.columns;
        if !matrix.takes(m) || x.dims().last() != Some(&matrix.columns) {
            return self.candle.forward(x);
        }
        let input = x.flatten_all()?.to_vec1::<f32>()?;
        let mut out = vec![0f32; m * matrix.rows];
        matrix.product(&input, 0..matrix.rows, &mut out)?;
        let mut dims = x.dims().to_vec();
        if let Some(last) = dims.last_mut() {
            *last = matrix.rows;
        }
        Tensor::from_vec(out, dims, x.device())
    }
}

/// One activation block quantised for the kernels: 256 signed bytes in natural order (Q6_K's)
/// and in the order the Q4_K kernel reads them, the sums of each 32 and each 16 values (for the
/// Q4_K mins and the Q6_K offset), and the scale.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
pub struct ActivationBlock {
    natural: [i8; BLOCK_VALUES],
    /// Per 128 values `p`: `[x[p..p+32], x[p+64..p+96], x[p+32..p+64], x[p+96..p+128]]`, the
    /// order of a 64-byte load of Q4_K's low nibbles then high nibbles.
    q4k_order: [i8; BLOCK_VALUES],
    sums32: [i16; 8],
    sums16: [i16; 16],
    scale: f32,
}

impl ActivationBlock {
    /// Quantises 256 values to bytes with one scale (largest magnitude to 127).
    pub fn quantise(x: &[f32]) -> ActivationBlock {
        debug_assert_eq!(x.len(), BLOCK_VALUES);
        let mut block = ActivationBlock {
            natural: [0; BLOCK_VALUES],
            q4k_order: [0; BLOCK_VALUES],
            sums32: [0; 8],
            sums16: [0; 16],
            scale: 1.0,
        };
        #[cfg(target_arch = "x86_64")]
        let rounded = cpu_has_kernel_here() && {
            // SAFETY: the CPU has AVX-512 F and BW (checked just before).
            block.scale = unsafe { round_to_bytes(x, &mut block.natural, &mut block.sums16) };
            true
        };
        #[cfg(not(target_arch = "x86_64"))]
        let rounded = false;
        if !rounded {
            let largest = x.iter().fold(0f32, |m, v| m.max(v.abs()));
            block.scale = scale_of(largest);
            let inverse = 1.0 / block.scale;
            for (q, v) in block.natural.iter_mut().zip(x) {
                *q = (v * inverse).round().clamp(-127.0, 127.0) as i8;
            }
            for (s, sum) in block.sums16.iter_mut().enumerate() {
                *sum = block.natural[16 * s..16 * s + 16]
                    .iter()
                    .map(|&v| v as i16)
                    .sum();
            }
        }
        let q = &block.natural;
        for half in 0..2 {
            let p = 128 * half;
            let order = [p, p + 64, p + 32, p + 96];
            for (slot, from) in order.into_iter().enumerate() {
                block.q4k_order[p + 32 * slot..p + 32 * slot + 32]
                    .copy_from_slice(&q[from..from + 32]);
            }
        }
        for (s, sum) in block.sums32.iter_mut().enumerate() {
            *sum = block.sums16[2 * s] + block.sums16[2 * s + 1];
        }
        block
    }
}

/// The scale that takes a block's largest magnitude to 127.
fn scale_of(largest: f32) -> f32 {
    if largest > 0.0 { largest / 127.0 } else { 1.0 }
}

/// `out[i] = round(x[i] / scale)` within ±127 with the block's scale (returned), rounded half
/// away from zero as `f32::round` does, and each 16 values' sum in `sums`: the scalar loops'
/// results, bit for bit. A prompt's chunk quantises ~10⁷ values a layer (the scalar `roundf`
/// calls were 1–2 % of a prefill's profile; the largest magnitude, a chain of dependent
/// `maxss`, is four independent chains of 16 lanes here).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw")]
fn round_to_bytes(x: &[f32], out: &mut [i8; BLOCK_VALUES], sums: &mut [i16; 16]) -> f32 {
    use std::arch::x86_64::*;
    assert_eq!(x.len(), BLOCK_VALUES, "an activation block");
    // Four chains of maxima; `max(|v|, m)` gives m for a NaN, as `f32::max` does.
    let mut largest = [_mm512_setzero_ps(); 4];
    for (i, values) in x.chunks_exact(16).enumerate() {
        // SAFETY: 16 floats.
        let v = unsafe { _mm512_loadu_ps(values.as_ptr()) };
        largest[i % 4] = _mm512_max_ps(_mm512_abs_ps(v), largest[i % 4]);
    }
    let largest = _mm512_max_ps(
        _mm512_max_ps(largest[0], largest[1]),
        _mm512_max_ps(largest[2], largest[3]),
    );
    let scale = scale_of(_mm512_reduce_max_ps(largest));
    let inverse = _mm512_set1_ps(1.0 / scale);
    let half = _mm512_set1_ps(0.5);
    let one = _mm512_set1_ps(1.0);
    let limit = _mm512_set1_ps(127.0);
    for ((values, bytes), sum) in x
        .chunks_exact(16)
        .zip(out.chunks_exact_mut(16))
        .zip(sums.iter_mut())
    {
        // SAFETY: 16 floats in, 16 bytes out.
        unsafe {
            let v = _mm512_mul_ps(_mm512_loadu_ps(values.as_ptr()), inverse);
            let whole = _mm512_roundscale_ps::<{ _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC }>(v);
            // |v − trunc(v)| is exact; at a half or more, one more away from zero.
            let away =
                _mm512_cmp_ps_mask::<_CMP_GE_OQ>(_mm512_abs_ps(_mm512_sub_ps(v, whole)), half);
            let signed_one = _mm512_or_ps(one, _mm512_and_ps(v, _mm512_set1_ps(-0.0)));
            let rounded = _mm512_mask_add_ps(whole, away, whole, signed_one);
            let clamped = _mm512_max_ps(
                _mm512_min_ps(rounded, limit),
                _mm512_sub_ps(_mm512_setzero_ps(), limit),
            );
            let whole = _mm512_cvttps_epi32(clamped);
            _mm_storeu_si128(bytes.as_mut_ptr() as *mut _, _mm512_cvtepi32_epi8(whole));
            *sum = _mm512_reduce_add_epi32(whole) as i16;
        }
    }
    scale
}

/// A Q4_K or Q6_K matrix (rows × columns, columns a multiple of 256) whose products with a
/// few rows run on this module's kernels.
pub struct DecodeMatrix {
    /// Holds the blocks (candle's storage of the GGUF's bytes); read through [`QTensor::data`].
    tensor: Arc<QTensor>,
    format: Format,
    rows: usize,
    columns: usize,
}

impl DecodeMatrix {
    /// The matrix of `tensor` when these products can take it: Q4_K or Q6_K, two dimensions,
    /// columns a multiple of 256, its bytes where they should be, and a CPU with the kernels'
    /// features.
    pub fn new(tensor: &Arc<QTensor>) -> Option<DecodeMatrix> {
        let format = Format::of(tensor.dtype())?;
        if !enabled() {
            return None;
        }
        let (rows, columns) = tensor.shape().dims2().ok()?;
        if columns == 0 || !columns.is_multiple_of(BLOCK_VALUES) {
            return None;
        }
        let bytes = tensor.data().ok()?;
        if bytes.len() != rows * columns / BLOCK_VALUES * format.block_bytes() {
            return None;
        }
        Some(DecodeMatrix {
            tensor: tensor.clone(),
            format,
            rows,
            columns,
        })
    }

    /// Whether [`DecodeMatrix::product`] takes `m` activation rows: up to [`MAX_FEED`], any
    /// number where the AMX products run.
    pub fn takes(&self, m: usize) -> bool {
        (1..=MAX_FEED).contains(&m) || (m > 0 && amx_here())
    }

    /// `out[i][r - rows.start] = Σ_c x[i][c] · W[r][c]` for the output rows `rows` and the
    /// `x.len() / columns` rows of `x` (see [`DecodeMatrix::takes`]); `out` holds as many rows
    /// of `rows.len()` values.
    pub fn product(
        &self,
        x: &[f32],
        rows: Range<usize>,
        out: &mut [f32],
    ) -> candle_core::Result<()> {
        let m = x.len() / self.columns;
        let n = rows.len();
        if !self.takes(m)
            || x.len() != m * self.columns
            || rows.end > self.rows
            || out.len() != m * n
        {
            candle_core::bail!(
                "a product of {} values into {} for rows {rows:?} of a {}×{} matrix",
                x.len(),
                out.len(),
                self.rows,
                self.columns
            );
        }
        let weights = self.tensor.data()?;
        let blocks = self.columns / BLOCK_VALUES;
        let row_bytes = blocks * self.format.block_bytes();
        let format = self.format;
        let target = Shared(out.as_mut_ptr());
        let first_row = rows.start;
        #[cfg(target_arch = "x86_64")]
        if amx_here() && m >= AMX_MIN_ROWS && n.is_multiple_of(amx::TILE_ROWS) {
            let packed = amx::PackedActivations::new(x, m, blocks, format);
            candle_core::utils::barrier_pool().execute_chunked(n / amx::TILE_ROWS, |groups| {
                // SAFETY: `amx_here()` said yes; `out` holds m rows of n (checked above), and
                // each thread writes only the columns of its own groups.
                unsafe {
                    amx::product(
                        format,
                        &weights,
                        row_bytes,
                        first_row,
                        groups,
                        &packed,
                        target.at(0),
                        n,
                    )
                }
            });
            return Ok(());
        }
        let activations: Vec<ActivationBlock> = x
            .chunks_exact(BLOCK_VALUES)
            .map(ActivationBlock::quantise)
            .collect();
        candle_core::utils::barrier_pool().execute_chunked(n.div_ceil(ROWS_PER_GRAB), |grabs| {
            let end = (grabs.end * ROWS_PER_GRAB).min(n);
            for r in grabs.start * ROWS_PER_GRAB..end {
                let at = (first_row + r) * row_bytes;
                let row = &weights[at..at + row_bytes];
                for (c, chunk) in activations.chunks(MAX_ROWS * blocks).enumerate() {
                    let rows_here = chunk.len() / blocks;
                    let mut dots = [0f32; MAX_ROWS];
                    row_products(format, row, chunk, rows_here, &mut dots);
                    for (i, dot) in dots[..rows_here].iter().enumerate() {
                        // SAFETY: `(c * MAX_ROWS + i) * n + r` is inside `out` (checked above:
                        // m rows of n), and each `r` is written by the one grab that holds it:
                        // the grabs' ranges do not overlap.
                        unsafe { target.write((c * MAX_ROWS + i) * n + r, &[*dot]) };
                    }
                }
            }
        });
        Ok(())
    }
}

/// The dot products of one weight row (its blocks' bytes) with `m` activation rows
/// (`activations`: `m` rows of the same number of blocks). Sizes are checked: a mismatch panics.
fn row_products(
    format: Format,
    row: &[u8],
    activations: &[ActivationBlock],
    m: usize,
    dots: &mut [f32; MAX_ROWS],
) {
    let blocks = row.len() / format.block_bytes();
    assert!(
        (1..=MAX_ROWS).contains(&m)
            && row.len() == blocks * format.block_bytes()
            && activations.len() == m * blocks,
        "a {format:?} row of {} bytes against {} activation blocks in {m} rows",
        row.len(),
        activations.len()
    );
    #[cfg(target_arch = "x86_64")]
    match format {
        Format::Q4K => rows_of::<Q4kKernel>(m, row, activations, blocks, dots),
        Format::Q6K => rows_of::<Q6kKernel>(m, row, activations, blocks, dots),
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (row, activations, blocks, dots);
        unreachable!("DecodeMatrix::new gives no matrix off x86-64");
    }
}

/// A kernel for `M` activation rows at a time, `M` fixed when compiled.
#[cfg(target_arch = "x86_64")]
trait Kernel {
    /// # Safety
    /// The CPU has the kernels' features (AVX-512 F, BW and VNNI, FMA, F16C).
    unsafe fn rows<const M: usize>(
        row: &[u8],
        activations: &[ActivationBlock],
        blocks: usize,
        dots: &mut [f32; MAX_ROWS],
    );
}

#[cfg(target_arch = "x86_64")]
struct Q4kKernel;
#[cfg(target_arch = "x86_64")]
struct Q6kKernel;

#[cfg(target_arch = "x86_64")]
impl Kernel for Q4kKernel {
    unsafe fn rows<const M: usize>(
        row: &[u8],
        activations: &[ActivationBlock],
        blocks: usize,
        dots: &mut [f32; MAX_ROWS],
    ) {
        // SAFETY: the features are the caller's promise.
        unsafe { q4k::rows_of::<M>(row, activations, blocks, dots) }
    }
}

#[cfg(target_arch = "x86_64")]
impl Kernel for Q6kKernel {
    unsafe fn rows<const M: usize>(
        row: &[u8],
        activations: &[ActivationBlock],
        blocks: usize,
        dots: &mut [f32; MAX_ROWS],
    ) {
        // SAFETY: the features are the caller's promise.
        unsafe { q6k::rows_of::<M>(row, activations, blocks, dots) }
    }
}

/// `K`'s kernel for the `m` (1..=[`MAX_ROWS`]) known only at run time.
#[cfg(target_arch = "x86_64")]
fn rows_of<K: Kernel>(
    m: usize,
    row: &[u8],
    activations: &[ActivationBlock],
    blocks: usize,
    dots: &mut [f32; MAX_ROWS],
) {
    // SAFETY: `enabled()` (checked by `DecodeMatrix::new`, the only way here) found the
    // kernels' CPU features.
    unsafe {
        match m {
            1 => K::rows::<1>(row, activations, blocks, dots),
            2 => K::rows::<2>(row, activations, blocks, dots),
            3 => K::rows::<3>(row, activations, blocks, dots),
            4 => K::rows::<4>(row, activations, blocks, dots),
            5 => K::rows::<5>(row, activations, blocks, dots),
            6 => K::rows::<6>(row, activations, blocks, dots),
            7 => K::rows::<7>(row, activations, blocks, dots),
            _ => K::rows::<8>(row, activations, blocks, dots),
        }
    }
}

/// A block's integer dot product with one activation row, each group of values times its
/// scale: 16 lanes to add up. `weights[k]` (unsigned, below 64) against the activation's `k`-th
/// 64 values in the same order (`vpdpbusd`: 16 sums of four products each, at most 4 · 63 · 127
/// = 32,004 in size); two such vectors pack into one of 16-bit lanes, which `vpmaddwd` multiplies
/// by `pair_scales` (each kernel's layout of its scales to match) and adds in pairs. Two packs
/// and two multiplies where four 32-bit multiplies took eight micro-operations of the port the
/// dot products need too.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
fn scaled_block_dot(
    weights: &[std::arch::x86_64::__m512i; 4],
    pair_scales: &[std::arch::x86_64::__m512i; 2],
    values: &[i8; BLOCK_VALUES],
) -> std::arch::x86_64::__m512i {
    use std::arch::x86_64::*;
    let zero = _mm512_setzero_si512();
    let mut dots = [zero; 4];
    for ((dot, w), x) in dots.iter_mut().zip(weights).zip(values.as_chunks::<64>().0) {
        // SAFETY: `x` is 64 bytes.
        let xs = unsafe { _mm512_loadu_si512(x.as_ptr() as *const _) };
        *dot = _mm512_dpbusd_epi32(zero, *w, xs);
    }
    let first = _mm512_madd_epi16(_mm512_packs_epi32(dots[0], dots[1]), pair_scales[0]);
    let second = _mm512_madd_epi16(_mm512_packs_epi32(dots[2], dots[3]), pair_scales[1]);
    _mm512_add_epi32(first, second)
}

/// How far ahead of the block being read the kernels ask for the weights.
///
/// Why: a decode step streams ~1 GB of weights and the kernels stalled on each block's first
/// load: the hardware prefetcher alone gave ~7 GB/s a core. Asking for the bytes 4 KB ahead
/// took a single-token step of Qwen2.5-Coder-1.5B at 2,400 positions from ~98 to ~64 ms and
/// the models bench's cached Coordinator call from ~11 to ~8 s (2 KB and 8 KB measured alike,
/// 1 KB ~69 ms).
const PREFETCH_BYTES: usize = 4096;

/// Asks for the `bytes` (a block's length) [`PREFETCH_BYTES`] after `block`, the rows that
/// follow it, a cache line (64 bytes) at a time: called for each block in turn, every line is
/// asked for.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn prefetch_ahead(block: *const u8, bytes: usize) {
    use std::arch::x86_64::*;
    let ahead = block.wrapping_add(PREFETCH_BYTES);
    for at in (0..bytes).step_by(64) {
        // SAFETY: a prefetch is a hint: it neither faults (past the matrix's end included)
        // nor changes what the program reads.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(ahead.wrapping_add(at) as *const i8) };
    }
}

/// Whether this product runs here: the CPU's features, and not turned off.
fn enabled() -> bool {
    static ENABLED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ENABLED.get_or_init(|| {
        let off = std::env::var("TACOS_EMBEDDED_MATVEC").is_ok_and(|v| v == "candle");
        !off && cpu_has_kernel_here()
    })
}

/// Whether the AMX products run here: the CPU has them, Linux grants the tiles, and
/// `TACOS_EMBEDDED_MATVEC` is neither `candle` nor `vnni` (the VNNI kernels alone, to compare).
fn amx_here() -> bool {
    static HERE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *HERE.get_or_init(|| {
        let vnni_only = std::env::var("TACOS_EMBEDDED_MATVEC").is_ok_and(|v| v == "vnni");
        #[cfg(target_arch = "x86_64")]
        let amx = amx::available();
        #[cfg(not(target_arch = "x86_64"))]
        let amx = false;
        enabled() && !vnni_only && amx
    })
}

/// [`cpu_has_kernel`], asked once.
fn cpu_has_kernel_here() -> bool {
    static HAS: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *HAS.get_or_init(cpu_has_kernel)
}

#[cfg(target_arch = "x86_64")]
fn cpu_has_kernel() -> bool {
    std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512bw")
        && std::arch::is_x86_feature_detected!("avx512vnni")
        && std::arch::is_x86_feature_detected!("fma")
        && std::arch::is_x86_feature_detected!("f16c")
}

#[cfg(not(target_arch = "x86_64"))]
fn cpu_has_kernel() -> bool {
    false
}

#[cfg(test)]
mod tests;

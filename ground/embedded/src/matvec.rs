//! Q4_K matrix products for decode steps (one to [`MAX_ROWS`] activation rows), read straight
//! from the GGUF's 144-byte blocks.
//!
//! Why not candle's: for a few rows candle repacks Q4_K into tiles of 16 rows with f32 scales
//! and mins, 1.33× the GGUF's bytes, and its tile kernel does per activation row nearly all
//! the work it does per weight tile, so a step of two or three tokens (the grammar's forced
//! tokens fed with the sampled one) costs nearly two or three steps. A decode step reads every
//! weight once; on two cores that read is the step's time. This product reads the blocks as
//! stored (candle keeps them: no memory is added), unpacks each block's nibbles and scales once
//! for all the rows, and splits the matrix's rows over candle's own thread pool (the one its
//! other products use, so no thread competes with it). Measured with the `speed` example and
//! the models bench: see the README's model figures.
//!
//! Used only where the CPU has AVX-512 with VNNI ([`Q4kMatrix::new`] says `None` elsewhere and
//! the caller keeps candle's product); `TACOS_EMBEDDED_MATVEC=candle` turns it off, to compare.
//! The activation rows are quantised to 8 bits per 256 values (one f32 scale each), as
//! candle's and llama.cpp's Q4_K products do.

use std::sync::Arc;

use candle_core::quantized::{GgmlDType, QMatMul, QTensor};
use candle_core::{Module, Tensor};

#[cfg(target_arch = "x86_64")]
mod avx512;

/// Values per Q4_K block.
pub const BLOCK_VALUES: usize = 256;
/// Bytes per Q4_K block: f16 scale, f16 min scale, 12 bytes of 6-bit sub-block scales and
/// mins, 128 bytes of 4-bit values.
pub const BLOCK_BYTES: usize = 144;
/// The most activation rows one product takes; more rows (a prompt) go to candle's product.
pub const MAX_ROWS: usize = 4;
/// Output rows a thread takes at a time.
const ROWS_PER_GRAB: usize = 16;

/// A layer's weight matrix: its products with a few rows (a decode step) by [`Q4kMatrix`] when
/// it is Q4_K and the CPU has the kernel, every other product by candle's.
pub struct Linear {
    candle: QMatMul,
    q4k: Option<Q4kMatrix>,
}

impl Linear {
    pub fn new(weights: QTensor) -> candle_core::Result<Linear> {
        let weights = Arc::new(weights);
        Ok(Linear {
            q4k: Q4kMatrix::new(&weights),
            candle: QMatMul::from_arc(weights)?,
        })
    }

    /// `x` (…, columns) times the matrix's transpose: (…, rows).
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let Some(q4k) = &self.q4k else {
            return self.candle.forward(x);
        };
        let m = x.elem_count() / q4k.columns.max(1);
        if m > MAX_ROWS || x.dims().last() != Some(&q4k.columns) {
            return self.candle.forward(x);
        }
        let input = x.flatten_all()?.to_vec1::<f32>()?;
        let mut out = vec![0f32; m * q4k.rows];
        q4k.product(&input, &mut out)?;
        let mut dims = x.dims().to_vec();
        if let Some(last) = dims.last_mut() {
            *last = q4k.rows;
        }
        Tensor::from_vec(out, dims, x.device())
    }
}

/// One activation block quantised for the kernel: 256 signed bytes in the order the kernel
/// reads them (see [`ActivationBlock::quantise`]), the sums of each 32-value sub-block (for
/// the mins) and the scale.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
pub struct ActivationBlock {
    /// Per 128 values `p`: `[x[p..p+32], x[p+64..p+96], x[p+32..p+64], x[p+96..p+128]]`, the
    /// order of a 64-byte load of the weights' low nibbles then high nibbles.
    values: [i8; BLOCK_VALUES],
    /// Sum of the quantised values of each 32-value sub-block, in natural order.
    sums: [i16; 8],
    scale: f32,
}

impl ActivationBlock {
    /// Quantises 256 values to bytes with one scale (largest magnitude to 127).
    pub fn quantise(x: &[f32]) -> ActivationBlock {
        debug_assert_eq!(x.len(), BLOCK_VALUES);
        let largest = x.iter().fold(0f32, |m, v| m.max(v.abs()));
        let scale = if largest > 0.0 { largest / 127.0 } else { 1.0 };
        let inverse = 1.0 / scale;
        let mut q = [0i8; BLOCK_VALUES];
        for (q, v) in q.iter_mut().zip(x) {
            *q = (v * inverse).round().clamp(-127.0, 127.0) as i8;
        }
        let mut block = ActivationBlock {
            values: [0; BLOCK_VALUES],
            sums: [0; 8],
            scale,
        };
        for half in 0..2 {
            let p = 128 * half;
            let order = [p, p + 64, p + 32, p + 96];
            for (slot, from) in order.into_iter().enumerate() {
                block.values[p + 32 * slot..p + 32 * slot + 32]
                    .copy_from_slice(&q[from..from + 32]);
            }
        }
        for (s, sum) in block.sums.iter_mut().enumerate() {
            *sum = q[32 * s..32 * s + 32].iter().map(|&v| v as i16).sum();
        }
        block
    }
}

/// A Q4_K matrix (rows × columns, columns a multiple of 256) whose products with a few rows
/// run on [`avx512`]'s kernel.
pub struct Q4kMatrix {
    /// Holds the blocks (candle's storage of the GGUF's bytes); read through [`QTensor::data`].
    tensor: Arc<QTensor>,
    rows: usize,
    columns: usize,
}

impl Q4kMatrix {
    /// The matrix of `tensor` when this product can take it: Q4_K, two dimensions, columns a
    /// multiple of 256, its bytes where they should be, and a CPU with the kernel's features.
    pub fn new(tensor: &Arc<QTensor>) -> Option<Q4kMatrix> {
        if !enabled() || tensor.dtype() != GgmlDType::Q4K {
            return None;
        }
        let (rows, columns) = tensor.shape().dims2().ok()?;
        if columns == 0 || !columns.is_multiple_of(BLOCK_VALUES) {
            return None;
        }
        let bytes = tensor.data().ok()?;
        if bytes.len() != rows * columns / BLOCK_VALUES * BLOCK_BYTES {
            return None;
        }
        Some(Q4kMatrix {
            tensor: tensor.clone(),
            rows,
            columns,
        })
    }

    /// `out[i][r] = Σ_c x[i][c] · W[r][c]` for the `x.len() / columns` rows of `x`
    /// (1..=[`MAX_ROWS`]); `out` holds as many rows of `rows` values.
    pub fn product(&self, x: &[f32], out: &mut [f32]) -> candle_core::Result<()> {
        let m = x.len() / self.columns;
        if m == 0 || m > MAX_ROWS || x.len() != m * self.columns || out.len() != m * self.rows {
            candle_core::bail!(
                "a Q4_K product of {} values into {} for a {}×{} matrix",
                x.len(),
                out.len(),
                self.rows,
                self.columns
            );
        }
        let blocks = self.columns / BLOCK_VALUES;
        let activations: Vec<ActivationBlock> = x
            .chunks_exact(BLOCK_VALUES)
            .map(ActivationBlock::quantise)
            .collect();
        let weights = self.tensor.data()?;
        let row_bytes = blocks * BLOCK_BYTES;
        let rows = self.rows;
        let target = OutputRows(out.as_mut_ptr());
        let grabs = rows.div_ceil(ROWS_PER_GRAB);
        candle_core::utils::barrier_pool().execute_chunked(grabs, |range| {
            let first = range.start * ROWS_PER_GRAB;
            let end = (range.end * ROWS_PER_GRAB).min(rows);
            for r in first..end {
                let row = &weights[r * row_bytes..(r + 1) * row_bytes];
                let mut dots = [0f32; MAX_ROWS];
                row_products(row, &activations, m, &mut dots);
                for (i, dot) in dots[..m].iter().enumerate() {
                    // SAFETY: `i * rows + r` is inside `out` (checked above: m rows of
                    // `rows`), and each output row `r` is written by the one grab that holds
                    // it: the grabs' ranges do not overlap.
                    unsafe { target.write(i * rows + r, *dot) };
                }
            }
        });
        Ok(())
    }
}

/// `out`'s pointer shared by the pool's threads, each writing its own elements.
#[derive(Clone, Copy)]
struct OutputRows(*mut f32);

// SAFETY: the threads write disjoint elements (see `Q4kMatrix::product`), and the pool's call
// returns only when every thread is done.
unsafe impl Send for OutputRows {}
unsafe impl Sync for OutputRows {}

impl OutputRows {
    /// # Safety
    /// `at` is inside the buffer and no other thread touches it during the call.
    unsafe fn write(self, at: usize, value: f32) {
        unsafe { *self.0.add(at) = value };
    }
}

/// The dot products of one weight row (its blocks' bytes) with `m` activation rows
/// (`activations`: `m` rows of the same number of blocks).
fn row_products(row: &[u8], activations: &[ActivationBlock], m: usize, dots: &mut [f32; MAX_ROWS]) {
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: `enabled()` (checked by `Q4kMatrix::new`, the only way here) found the
        // kernel's CPU features; the slices' sizes are checked by the kernel's caller above.
        unsafe { avx512::row_products(row, activations, m, dots) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (row, activations, m, dots);
        unreachable!("Q4kMatrix::new gives no matrix off x86-64");
    }
}

/// Whether this product runs here: the CPU's features, and not turned off.
fn enabled() -> bool {
    static ENABLED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ENABLED.get_or_init(|| {
        let off = std::env::var("TACOS_EMBEDDED_MATVEC").is_ok_and(|v| v == "candle");
        !off && cpu_has_kernel()
    })
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

/// The 6-bit scales and mins of a block's eight sub-blocks, from its 12 packed bytes: bytes
/// 0–3 hold scales 0–3 (low 6 bits), 4–7 mins 0–3; bytes 8–11 the low 4 bits of scales 4–7
/// (low nibble) and of mins 4–7 (high nibble), whose top 2 bits are the top bits of bytes 0–3
/// (scales) and 4–7 (mins). Four bytes at a time, as little-endian words.
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

#[cfg(test)]
mod tests;

//! The output projection (the last hidden state → one logit per vocabulary row), computed whole
//! or only over the blocks of rows that hold the tokens a grammar allows.
//!
//! Why: the output matrix is the largest one a step reads (Qwen2.5-Coder-1.5B: 151,936 × 1,536
//! in Q6_K, 190 MB, about a fifth of a step's weights), yet in a JSON reply most sampled steps
//! outside free text allow a handful of tokens (a drone's name, a digit, a comma or a bracket).
//! The logits of tokens the mask refuses are never used, so those steps compute only the row
//! blocks their allowed tokens fall in. Free-text steps, which allow nearly everything, use the
//! whole matrix in one product.

use std::sync::Arc;

use candle_core::quantized::{QMatMul, QTensor, ggml_file::qtensor_from_ggml};
use candle_core::{DType, Module, Result, Tensor};

use crate::matvec::DecodeMatrix;

/// Rows per block: small enough that a few allowed tokens cost a few hundredths of the matrix,
/// large enough that the per-product overhead stays small beside the product.
pub const BLOCK_ROWS: usize = 1024;

/// Use the blocks only while they cover at most this fraction of the rows (1 / n).
const BLOCKS_UP_TO_ONE_IN: usize = 4;

pub struct OutputProjection {
    whole: QMatMul,
    /// The matrix for [`crate::matvec`]'s products, which take any range of rows, when the CPU
    /// has their kernels; then `blocks` is empty.
    decode: Option<DecodeMatrix>,
    /// The same rows, `block_rows` at a time, in order (candle's products of a block).
    blocks: Vec<QMatMul>,
    block_rows: usize,
    rows: usize,
}

impl OutputProjection {
    /// Splits `weight` (rows × width, as stored in the GGUF) into blocks of `block_rows` rows.
    /// Without [`crate::matvec`]'s kernels the blocks are copies for candle's products (the
    /// matrix is held twice: 190 MB more for Qwen2.5-Coder-1.5B); with them, ranges of rows.
    pub fn new(weight: QTensor, block_rows: usize) -> Result<OutputProjection> {
        let (rows, width) = weight.shape().dims2()?;
        let dtype = weight.dtype();
        let device = weight.device();
        if block_rows == 0 || width % dtype.block_size() != 0 {
            candle_core::bail!(
                "cannot split a {rows} × {width} {dtype:?} matrix into blocks of {block_rows} rows"
            );
        }
        let row_bytes = width / dtype.block_size() * dtype.type_size();
        let weight = Arc::new(weight);
        let decode = DecodeMatrix::new(&weight);
        let blocks = if decode.is_some() {
            Vec::new()
        } else {
            let data = weight.data()?;
            if data.len() != rows * row_bytes {
                candle_core::bail!(
                    "the output matrix holds {} bytes, not {rows} rows of {row_bytes}",
                    data.len()
                );
            }
            (0..rows)
                .step_by(block_rows)
                .map(|start| {
                    let n = block_rows.min(rows - start);
                    let bytes = &data[start * row_bytes..(start + n) * row_bytes];
                    QMatMul::from_qtensor(qtensor_from_ggml(dtype, bytes, vec![n, width], &device)?)
                })
                .collect::<Result<Vec<_>>>()?
        };
        Ok(OutputProjection {
            whole: QMatMul::from_arc(weight)?,
            decode,
            blocks,
            block_rows,
            rows,
        })
    }

    /// The logits of `hidden` (1 × width), one per row. With `only`, the rows of the blocks
    /// holding those rows, every other row `-inf`, when those blocks are few enough; otherwise
    /// (and without `only`) every row. Rows in `only` beyond the matrix are ignored.
    pub fn logits(&self, hidden: &Tensor, only: Option<&[usize]>) -> Result<Vec<f32>> {
        let input = match &self.decode {
            Some(_) => hidden.flatten_all()?.to_vec1::<f32>()?,
            None => Vec::new(),
        };
        if let Some(only) = only {
            let mut wanted = vec![false; self.rows.div_ceil(self.block_rows)];
            for &row in only.iter().filter(|r| **r < self.rows) {
                wanted[row / self.block_rows] = true;
            }
            let n_wanted = wanted.iter().filter(|w| **w).count();
            if n_wanted * self.block_rows * BLOCKS_UP_TO_ONE_IN <= self.rows {
                let mut logits = vec![f32::NEG_INFINITY; self.rows];
                for i in (0..wanted.len()).filter(|i| wanted[*i]) {
                    let start = i * self.block_rows;
                    let end = (start + self.block_rows).min(self.rows);
                    match (&self.decode, self.blocks.get(i)) {
                        (Some(matrix), _) => {
                            matrix.product(&input, start..end, &mut logits[start..end])?
                        }
                        (None, Some(block)) => {
                            let part = row_of(block.forward(hidden)?)?;
                            logits[start..start + part.len()].copy_from_slice(&part);
                        }
                        (None, None) => candle_core::bail!("no block {i} of the output matrix"),
                    }
                }
                return Ok(logits);
            }
        }
        match &self.decode {
            Some(matrix) => {
                let mut logits = vec![0f32; self.rows];
                matrix.product(&input, 0..self.rows, &mut logits)?;
                Ok(logits)
            }
            None => row_of(self.whole.forward(hidden)?),
        }
    }
}

fn row_of(t: Tensor) -> Result<Vec<f32>> {
    t.squeeze(0)?.to_dtype(DType::F32)?.to_vec1::<f32>()
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use candle_core::quantized::GgmlDType;

    fn projection(rows: usize, block_rows: usize) -> (OutputProjection, Tensor) {
        let device = Device::Cpu;
        let w = Tensor::randn(0f32, 1.0, (rows, 256), &device).expect("weights");
        let q = QTensor::quantize(&w, GgmlDType::Q6K).expect("Q6_K");
        let hidden = Tensor::randn(0f32, 1.0, (1, 256), &device).expect("hidden");
        (
            OutputProjection::new(q, block_rows).expect("blocks"),
            hidden,
        )
    }

    #[test]
    fn the_allowed_rows_have_the_logits_of_the_whole_matrix() {
        // 1,000 rows in blocks of 50 (the last one 50 too), then 1,010 (a last block of 10).
        for rows in [1000, 1010] {
            let (out, hidden) = projection(rows, 50);
            let whole = out.logits(&hidden, None).expect("whole");
            assert_eq!(whole.len(), rows);
            let only = [3, 250, 251, rows - 1, rows + 5];
            let part = out.logits(&hidden, Some(&only)).expect("part");
            assert_eq!(part.len(), rows);
            for row in 0..rows {
                let block = row / 50;
                if [0, 5, (rows - 1) / 50].contains(&block) {
                    let (a, b) = (part[row], whole[row]);
                    assert!(
                        (a - b).abs() <= 1e-4 * b.abs().max(1.0),
                        "row {row}: {a} vs {b}"
                    );
                } else {
                    assert_eq!(part[row], f32::NEG_INFINITY, "row {row} computed");
                }
            }
        }
    }

    #[test]
    fn many_allowed_rows_or_none_mean_the_whole_matrix() {
        let (out, hidden) = projection(1000, 100);
        let whole = out.logits(&hidden, None).expect("whole");
        // Three blocks of ten is more than a quarter of the rows: every row is computed.
        let spread = out.logits(&hidden, Some(&[0, 500, 900])).expect("spread");
        assert_eq!(spread, whole);
        // Nothing allowed computes nothing (the sampler then finds no token).
        let none = out.logits(&hidden, Some(&[])).expect("none");
        assert!(none.iter().all(|l| *l == f32::NEG_INFINITY));
    }

    #[test]
    fn a_matrix_that_cannot_be_split_is_refused() {
        let device = Device::Cpu;
        let w = Tensor::randn(0f32, 1.0, (10, 256), &device).expect("weights");
        let q = QTensor::quantize(&w, GgmlDType::Q6K).expect("Q6_K");
        assert!(OutputProjection::new(q, 0).is_err());
    }
}

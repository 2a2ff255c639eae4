//! What the attention kernels (`decode_attention`, `prompt_attention`) read and write: the new
//! tokens' queries, the key/value cache's bf16 rows in place (no copy), and where each query
//! row's output goes.

use candle_core::{CpuStorage, Result, Storage, Tensor};
use half::slice::HalfFloatSliceExt;

/// The attention's sizes. Query rows are counted per key/value head: row `r` is that head's
/// query head `r / seq`, new token `r % seq`.
pub struct Shape {
    pub n_head: usize,
    pub n_kv_head: usize,
    /// Query heads per key/value head.
    pub n_rep: usize,
    /// New tokens: the last positions.
    pub seq: usize,
    /// Positions, the new tokens' included.
    pub total: usize,
    pub head_dim: usize,
    /// The scores' scale, 1 / √head_dim.
    pub scale: f32,
}

impl Shape {
    /// Positions query row `r` sees: those before its token, and its token.
    pub fn visible(&self, r: usize) -> usize {
        self.total - self.seq + r % self.seq + 1
    }

    /// Query rows per key/value head.
    pub fn rows(&self) -> usize {
        self.n_rep * self.seq
    }

    /// Where query row `r` of key/value head `g` starts in the output (1, new tokens, heads ×
    /// head size).
    pub fn out_at(&self, g: usize, r: usize) -> usize {
        let (head, token) = (g * self.n_rep + r / self.seq, r % self.seq);
        (token * self.n_head + head) * self.head_dim
    }
}

/// A key or value buffer: `n_heads` heads of `total` rows of `head_dim`, rows contiguous.
pub struct CacheView<'a, T> {
    data: &'a [T],
    head_stride: usize,
    total: usize,
    head_dim: usize,
}

impl<'a, T> CacheView<'a, T> {
    /// The view of `data` laid out by `layout` (candle's, in elements), or `None` when its
    /// rows are not contiguous or it is too short.
    fn of(
        data: &'a [T],
        layout: &candle_core::Layout,
        n_heads: usize,
        total: usize,
        head_dim: usize,
    ) -> Option<CacheView<'a, T>> {
        let &[_, head_stride, row_stride, 1] = layout.stride() else {
            return None;
        };
        let last = (n_heads - 1) * head_stride + total * head_dim;
        let data = data.get(layout.start_offset()..)?;
        (row_stride == head_dim && head_stride >= total * head_dim && last <= data.len()).then_some(
            CacheView {
                data,
                head_stride,
                total,
                head_dim,
            },
        )
    }

    /// Head `h`'s rows, contiguous.
    pub fn head(&self, h: usize) -> &'a [T] {
        let start = h * self.head_stride;
        &self.data[start..start + self.total * self.head_dim]
    }
}

/// The attention of `q` (1, heads, new tokens, head size; f32) over `k`, `v` (1, key/value
/// heads, positions, head size; bf16 views of the cache's buffers, the new tokens last) by
/// `attend`, which gets the shape, the queries (per head, per token) and the two views, and
/// returns the output (new tokens × heads × head size). `None`, nothing computed, when the
/// tensors are not of these forms or `applies` says no to the shape.
pub fn attend_in_place(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    applies: impl Fn(&Shape) -> bool,
    attend: impl FnOnce(&Shape, &[f32], &CacheView<u16>, &CacheView<u16>) -> Vec<f32>,
) -> Result<Option<Tensor>> {
    let (b, n_head, seq, head_dim) = q.dims4()?;
    let (kb, n_kv_head, total, k_dim) = k.dims4()?;
    if b != 1
        || kb != 1
        || seq == 0
        || seq > total
        || k_dim != head_dim
        || v.dims4()? != k.dims4()?
        || n_kv_head == 0
        || !n_head.is_multiple_of(n_kv_head)
    {
        return Ok(None);
    }
    let shape = Shape {
        n_head,
        n_kv_head,
        n_rep: n_head / n_kv_head,
        seq,
        total,
        head_dim,
        scale: 1.0 / (head_dim as f32).sqrt(),
    };
    if !applies(&shape) {
        return Ok(None);
    }
    let queries = q.flatten_all()?.to_vec1::<f32>()?;
    let (k_storage, k_layout) = k.storage_and_layout();
    let (v_storage, v_layout) = v.storage_and_layout();
    let (Storage::Cpu(CpuStorage::BF16(k_data)), Storage::Cpu(CpuStorage::BF16(v_data))) =
        (&*k_storage, &*v_storage)
    else {
        return Ok(None);
    };
    let view = |data, layout| CacheView::of(data, layout, n_kv_head, total, head_dim);
    let (Some(keys), Some(values)) = (
        view(k_data.reinterpret_cast(), k_layout),
        view(v_data.reinterpret_cast(), v_layout),
    ) else {
        return Ok(None);
    };
    let out = attend(&shape, &queries, &keys, &values);
    drop((k_storage, v_storage));
    Tensor::from_vec(out, (1, seq, n_head * head_dim), q.device()).map(Some)
}

/// Inputs for the attention kernels' tests.
#[cfg(test)]
pub mod test_inputs {
    use candle_core::{Device, Tensor};

    /// Values in [-1, 1], spread by a multiplicative hash of the index and `seed`.
    pub fn filled(dims: (usize, usize, usize, usize), seed: usize) -> Tensor {
        let n = dims.0 * dims.1 * dims.2 * dims.3;
        let values: Vec<f32> = (0..n)
            .map(|i| (((i + seed) * 2654435761) % 2001) as f32 / 1000.0 - 1.0)
            .collect();
        Tensor::from_vec(values, dims, &Device::Cpu).expect("tensor")
    }

    /// Keys and values as the cache holds them: bf16 views of the first `total` rows of
    /// buffers with room for more.
    pub fn cache_views(n_kv: usize, total: usize, d: usize) -> (Tensor, Tensor) {
        let view = |seed| {
            filled((1, n_kv, total + 13, d), seed)
                .to_dtype(crate::decoder::KV_DTYPE)
                .and_then(|t| t.narrow(2, 0, total))
                .expect("view")
        };
        (view(1), view(2))
    }
}

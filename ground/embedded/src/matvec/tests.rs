use super::*;
use candle_core::quantized::QMatMul;
use candle_core::{Device, Module, Tensor};

/// A random rows × columns matrix, quantised to `dtype` by candle.
fn quantised_matrix(dtype: GgmlDType, rows: usize, columns: usize, seed: u64) -> Arc<QTensor> {
    let mut state = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let values: Vec<f32> = (0..rows * columns)
        .map(|_| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
        })
        .collect();
    let w = Tensor::from_vec(values, (rows, columns), &Device::Cpu).expect("weights");
    Arc::new(QTensor::quantize(&w, dtype).expect("quantised"))
}

fn activations(m: usize, columns: usize) -> Vec<f32> {
    (0..m * columns)
        .map(|i| ((i * 7919 % 1000) as f32 / 500.0 - 1.0) * (1.0 + (i % 13) as f32))
        .collect()
}

const FORMATS: [GgmlDType; 2] = [GgmlDType::Q4K, GgmlDType::Q6K];

/// The numbers of activation rows to check: every one the VNNI kernels take (from
/// `AMX_MIN_ROWS` on, the AMX products where they run), and where AMX runs, a prompt's sizes
/// too: past `MAX_FEED`, past one pass of eight tiles (128), a partial last tile.
fn feeds() -> Vec<usize> {
    let mut feeds: Vec<usize> = (1..=MAX_FEED).collect();
    if amx_here() {
        feeds.extend([MAX_FEED + 1, 40, 129, 300]);
    } else {
        eprintln!("no AMX here (or TACOS_EMBEDDED_MATVEC): products of up to {MAX_FEED} rows");
    }
    feeds
}

/// This machine's kernel, or `None` (and a line saying why) on a CPU without AVX-512 VNNI.
fn matrix_here(tensor: &Arc<QTensor>) -> Option<DecodeMatrix> {
    let matrix = DecodeMatrix::new(tensor);
    if matrix.is_none() {
        eprintln!("this CPU has no AVX-512 VNNI (or TACOS_EMBEDDED_MATVEC=candle): not checked");
    }
    matrix
}

#[test]
fn the_product_is_the_dequantised_weights_times_the_quantised_activations() {
    for dtype in FORMATS {
        dequantised_weights_times_quantised_activations(dtype);
    }
}

fn dequantised_weights_times_quantised_activations(dtype: GgmlDType) {
    let (rows, columns) = (48, 768);
    let tensor = quantised_matrix(dtype, rows, columns, 1);
    let Some(matrix) = matrix_here(&tensor) else {
        return;
    };
    let weights = tensor
        .dequantize(&Device::Cpu)
        .and_then(|t| t.to_vec2::<f32>())
        .expect("dequantised");
    for m in feeds() {
        let x = activations(m, columns);
        let mut out = vec![0f32; m * rows];
        matrix.product(&x, 0..rows, &mut out).expect("product");
        for i in 0..m {
            // What the kernel computes exactly: the activations as quantised.
            let quantised: Vec<f64> = x[i * columns..(i + 1) * columns]
                .chunks_exact(BLOCK_VALUES)
                .flat_map(|chunk| {
                    let block = ActivationBlock::quantise(chunk);
                    block.natural.map(|q| q as f64 * block.scale as f64)
                })
                .collect();
            for (r, w) in weights.iter().enumerate() {
                let expected: f64 = w.iter().zip(&quantised).map(|(w, x)| *w as f64 * x).sum();
                let got = out[i * rows + r] as f64;
                assert!(
                    (got - expected).abs() <= 1e-4 * expected.abs().max(1.0),
                    "{dtype:?} row {i}, output {r}: {got} against {expected}"
                );
            }
        }
    }
}

#[test]
fn the_product_agrees_with_candles_own() {
    for dtype in FORMATS {
        agrees_with_candle(dtype);
    }
}

fn agrees_with_candle(dtype: GgmlDType) {
    let (rows, columns) = (64, 1536);
    let tensor = quantised_matrix(dtype, rows, columns, 2);
    let Some(matrix) = matrix_here(&tensor) else {
        return;
    };
    let candle = QMatMul::from_arc(tensor.clone()).expect("candle's product");
    // From 32 rows on candle's Q4_K product runs on AMX tiles too, configured once per thread:
    // ours, on the same pool's threads, must leave that configuration as it found it.
    for m in feeds() {
        let x = activations(m, columns);
        let mut out = vec![0f32; m * rows];
        matrix.product(&x, 0..rows, &mut out).expect("product");
        let input = Tensor::from_vec(x, (m, columns), &Device::Cpu).expect("input");
        let theirs = candle
            .forward(&input)
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_vec1::<f32>())
            .expect("candle's result");
        let scale = theirs.iter().fold(0f32, |s, v| s.max(v.abs()));
        for (ours, theirs) in out.iter().zip(&theirs) {
            // Both quantise the activations to 8 bits, each its own way: ~1 % of the largest.
            assert!(
                (ours - theirs).abs() <= 0.02 * scale,
                "{dtype:?}: {ours} against candle's {theirs} (largest {scale})"
            );
        }
    }
}

#[test]
fn a_product_of_the_wrong_size_is_an_error() {
    let tensor = quantised_matrix(GgmlDType::Q4K, 16, 256, 3);
    let Some(matrix) = matrix_here(&tensor) else {
        return;
    };
    let mut out = vec![0f32; 16];
    assert!(matrix.product(&[0.0; 255], 0..16, &mut out).is_err());
    assert!(matrix.product(&[0.0; 256], 0..16, &mut out[..15]).is_err());
    assert!(
        matrix.product(&[0.0; 256], 8..24, &mut out).is_err(),
        "rows past the matrix"
    );
    let too_many = MAX_FEED + 1;
    let mut out_of_too_many = vec![0f32; 16 * too_many];
    let of_too_many = matrix.product(&vec![0.0; 256 * too_many], 0..16, &mut out_of_too_many);
    assert_eq!(
        of_too_many.is_ok(),
        amx_here(),
        "more rows than MAX_FEED: taken only by the AMX products"
    );
    assert!(matrix.product(&[], 0..16, &mut []).is_err(), "no rows");
    assert!(matrix.product(&[0.0; 256], 0..16, &mut out).is_ok());
}

#[test]
fn a_range_of_rows_is_those_rows_of_the_whole_product() {
    let (rows, columns) = (100, 512);
    for dtype in FORMATS {
        let tensor = quantised_matrix(dtype, rows, columns, 4);
        let Some(matrix) = matrix_here(&tensor) else {
            return;
        };
        let x = activations(2, columns);
        let mut whole = vec![0f32; 2 * rows];
        matrix.product(&x, 0..rows, &mut whole).expect("whole");
        let mut part = vec![0f32; 2 * 30];
        matrix.product(&x, 37..67, &mut part).expect("part");
        for i in 0..2 {
            assert_eq!(
                part[i * 30..(i + 1) * 30],
                whole[i * rows + 37..i * rows + 67]
            );
        }
    }
}

#[test]
fn only_k_quant_matrices_are_taken() {
    let device = Device::Cpu;
    let w = Tensor::zeros((16, 256), candle_core::DType::F32, &device).expect("zeros");
    let q8 = Arc::new(QTensor::quantize(&w, GgmlDType::Q8_0).expect("q8_0"));
    assert!(DecodeMatrix::new(&q8).is_none());
}

#[test]
fn an_activation_block_keeps_its_values_and_sums() {
    let x: Vec<f32> = (0..BLOCK_VALUES).map(|i| i as f32 - 100.0).collect();
    let block = ActivationBlock::quantise(&x);
    let natural = block.natural;
    for half in 0..2 {
        let p = 128 * half;
        for (slot, from) in [p, p + 64, p + 32, p + 96].into_iter().enumerate() {
            let at = p + 32 * slot;
            assert_eq!(block.q4k_order[at..at + 32], natural[from..from + 32]);
        }
    }
    assert!((block.scale - 155.0 / 127.0).abs() < 1e-6);
    for (q, v) in natural.iter().zip(&x) {
        assert!((*q as f32 * block.scale - v).abs() <= block.scale / 2.0 + 1e-4);
    }
    for s in 0..8 {
        let sum: i16 = natural[32 * s..32 * s + 32].iter().map(|&v| v as i16).sum();
        assert_eq!(block.sums32[s], sum);
    }
    for s in 0..16 {
        let sum: i16 = natural[16 * s..16 * s + 16].iter().map(|&v| v as i16).sum();
        assert_eq!(block.sums16[s], sum);
    }
    let zeros = ActivationBlock::quantise(&[0.0; BLOCK_VALUES]);
    assert_eq!((zeros.sums32, zeros.sums16), ([0; 8], [0; 16]));
}

/// The GGUF's `get_scale_min_k4`, one sub-block at a time.
fn scale_and_min(j: usize, q: &[u8; 12]) -> (u8, u8) {
    if j < 4 {
        (q[j] & 63, q[j + 4] & 63)
    } else {
        (
            (q[j + 4] & 0xF) | ((q[j - 4] >> 6) << 4),
            (q[j + 4] >> 4) | ((q[j] >> 6) << 4),
        )
    }
}

#[cfg(target_arch = "x86_64")]
#[test]
fn scales_unpack_as_the_format_defines_them() {
    use super::q4k::unpack_scales;
    let mut state = 99u64;
    for _ in 0..1000 {
        let mut packed = [0u8; 12];
        for byte in packed.iter_mut() {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *byte = (state >> 56) as u8;
        }
        let (scales, mins) = unpack_scales(&packed);
        for j in 0..8 {
            let (scale, min) = scale_and_min(j, &packed);
            assert_eq!((scales >> (8 * j)) as u8, scale, "scale {j} of {packed:?}");
            assert_eq!((mins >> (8 * j)) as u8, min, "min {j} of {packed:?}");
        }
    }
}

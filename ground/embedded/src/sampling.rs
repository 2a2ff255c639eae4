//! Choosing the next token from the logits: the repetition penalty, greedy or seeded sampling
//! within llguidance's mask, and the small generator the sampling draws from.

/// The usual repetition penalty (as in llama.cpp and transformers): each token among `recent`
/// has its logit divided by `penalty` when positive, multiplied when negative. Greedy decoding
/// of a small model otherwise falls into loops ("so it's a new day, so it's a new day, …").
pub(crate) fn penalise_repeats(logits: &mut [f32], recent: &[u32], penalty: f32) {
    if penalty <= 1.0 || !penalty.is_finite() {
        return;
    }
    let mut seen = std::collections::HashSet::new();
    for &t in recent {
        if !seen.insert(t) {
            continue;
        }
        if let Some(l) = logits.get_mut(t as usize) {
            *l = if *l > 0.0 { *l / penalty } else { *l * penalty };
        }
    }
}

/// The next token: argmax at temperature ≤ 0.01, otherwise a draw from the softmax at that
/// temperature, over the tokens the mask allows (all when no mask) among the first
/// `real_vocab`: the output may have more rows than the vocabulary (Qwen: 151,936 logits for
/// 151,665 tokens), and a padding row is never a token.
pub(crate) fn sample(
    logits: &[f32],
    real_vocab: usize,
    mask: Option<&llguidance::toktrie::SimpleVob>,
    temperature: f32,
    rng: &mut SplitMix64,
) -> Option<u32> {
    let limit = real_vocab.min(logits.len());
    let mut allowed: Vec<usize> = Vec::new();
    match mask {
        Some(m) => m.iter_set_entries(|i| {
            if i < limit && logits[i].is_finite() {
                allowed.push(i)
            }
        }),
        None => allowed.extend((0..limit).filter(|i| logits[*i].is_finite())),
    }
    let best = allowed
        .iter()
        .copied()
        .max_by(|a, b| logits[*a].total_cmp(&logits[*b]))?;
    // NaN and tiny temperatures mean greedy.
    if temperature.is_nan() || temperature <= 0.01 {
        return Some(best as u32);
    }
    let max = logits[best];
    let weights: Vec<f64> = allowed
        .iter()
        .map(|i| (((logits[*i] - max) / temperature) as f64).exp())
        .collect();
    let total: f64 = weights.iter().sum();
    let mut r = rng.next_f64() * total;
    for (i, w) in allowed.iter().zip(&weights) {
        if r < *w {
            return Some(*i as u32);
        }
        r -= w;
    }
    Some(best as u32)
}

pub(crate) fn time_seed() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0x5eed)
}

/// A small deterministic generator (SplitMix64) for seeded sampling.
pub(crate) struct SplitMix64(u64);

impl SplitMix64 {
    pub(crate) fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    pub(crate) fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use llguidance::toktrie::SimpleVob;

    #[test]
    fn greedy_respects_the_mask() {
        let logits = [0.1, 5.0, 2.0, 3.0];
        let mut rng = SplitMix64::new(1);
        assert_eq!(sample(&logits, 4, None, 0.0, &mut rng), Some(1));
        // A padding row (beyond the vocabulary) is never chosen, however high its logit.
        assert_eq!(sample(&logits, 1, None, 0.0, &mut rng), Some(0));
        let mut mask = SimpleVob::alloc(4);
        mask.allow_token(2);
        mask.allow_token(3);
        assert_eq!(sample(&logits, 4, Some(&mask), 0.0, &mut rng), Some(3));
        assert_eq!(sample(&logits, 3, Some(&mask), 0.0, &mut rng), Some(2));
        let empty = SimpleVob::alloc(4);
        assert_eq!(sample(&logits, 4, Some(&empty), 0.0, &mut rng), None);
    }

    #[test]
    fn repeats_are_penalised_once_each_and_only_above_one() {
        let mut logits = vec![2.0, -2.0, 1.0];
        penalise_repeats(&mut logits, &[0, 1, 0], 2.0);
        assert_eq!(logits, vec![1.0, -4.0, 1.0]);
        penalise_repeats(&mut logits, &[0, 1], 1.0);
        assert_eq!(logits, vec![1.0, -4.0, 1.0]);
        // A token id beyond the vocabulary is ignored.
        penalise_repeats(&mut logits, &[7], 2.0);
        assert_eq!(logits, vec![1.0, -4.0, 1.0]);
    }

    #[test]
    fn sampling_is_seeded_and_stays_in_the_mask() {
        let logits = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0];
        let mut mask = SimpleVob::alloc(6);
        mask.allow_token(1);
        mask.allow_token(4);
        let draw = |seed| {
            let mut rng = SplitMix64::new(seed);
            (0..32)
                .map(|_| sample(&logits, 6, Some(&mask), 1.0, &mut rng))
                .collect::<Vec<_>>()
        };
        let a = draw(7);
        assert_eq!(a, draw(7));
        assert!(a.iter().all(|t| *t == Some(1) || *t == Some(4)));
        assert!(a.contains(&Some(1)) && a.contains(&Some(4)));
    }
}

//! Which key/value cache a prompt starts from: the caches of the last few calls kept in memory
//! (the Coordinator's and the Supervisor's prompts each begin with their own fixed part), and the
//! fixed beginnings kept on disk across restarts ([`PromptStore`]).

use std::sync::{Arc, Mutex};

use crate::decoder::KvCache;
use crate::lock;
use crate::prompt_store::{self, PromptStore, shared};

/// How many key/value caches are kept in memory (each up to the window: ~115 MB for a
/// 2,000-token prompt on Qwen2.5-Coder-1.5B).
const KEPT_CACHES: usize = 4;

/// A stored beginning is read back only when it spares this many more tokens than a kept cache.
const MIN_STORED_GAIN: usize = 32;

/// Feeds tokens through the decoder into a cache (the engine's forward pass).
pub type Feed<'a> = &'a dyn Fn(&[u32], &mut KvCache) -> Result<(), String>;

#[derive(Default)]
pub struct PromptCaches {
    /// The caches of the last few calls, most recent last.
    kept: Mutex<Vec<KvCache>>,
    /// The prompts' fixed beginnings kept on disk, if any.
    store: Option<Arc<PromptStore>>,
    /// Beginnings a skipped warm-up asked to store: stored once a call has computed them.
    to_store: Mutex<Vec<Vec<u32>>>,
}

impl PromptCaches {
    /// Keeps the fixed beginnings in `store` too, and reads them back from it.
    pub fn with_store(store: PromptStore) -> PromptCaches {
        PromptCaches {
            store: Some(Arc::new(store)),
            ..PromptCaches::default()
        }
    }

    /// The kept cache sharing the longest beginning with `prompt`, cut back to that beginning
    /// (never the whole prompt: the last prompt token is fed again for its logits). A fresh one
    /// when none shares anything. A cache the prompt extends is taken out (the new one supersedes
    /// it); from one it shares only part of, that part is copied and the kept one stays, so that
    /// the Supervisor's prompt, which shares a few tokens with the Coordinator's, does not cut the
    /// Coordinator's cache down to them.
    fn take_kept(&self, prompt: &[u32]) -> KvCache {
        let mut kept = lock(&self.kept);
        let Some((best, n)) = best_kept(&kept, prompt) else {
            return KvCache::default();
        };
        if n == kept[best].tokens().len() {
            return kept.remove(best);
        }
        kept[best].prefix_copy(n).unwrap_or_default()
    }

    /// How many of `prompt`'s tokens [`PromptCaches::take_kept`] would start from.
    fn kept_share(&self, prompt: &[u32]) -> usize {
        best_kept(&lock(&self.kept), prompt).map_or(0, |(_, n)| n)
    }

    /// The cache to start `prompt` from: the stored beginning of `prompt` when that spares
    /// [`MIN_STORED_GAIN`] tokens more than a kept one, else a kept one
    /// ([`PromptCaches::take_kept`]).
    pub fn take(&self, prompt: &[u32], feed: Feed<'_>) -> KvCache {
        if let Some(store) = &self.store {
            let stored = store.longest_prefix(prompt);
            let usable = stored.min(prompt.len().saturating_sub(1));
            if usable >= self.kept_share(prompt) + MIN_STORED_GAIN {
                match stored_cache(store, prompt, stored, feed) {
                    Ok(cache) => return cache,
                    Err(e) => tracing::warn!(error = %e, "a stored prompt beginning was not used"),
                }
            }
        }
        self.take_kept(prompt)
    }

    /// Writes `cache`'s first `n` tokens to the store, on a thread of its own, unless stored.
    pub fn store_beginning(&self, cache: &KvCache, n: usize) {
        let Some(store) = &self.store else {
            return;
        };
        if store.holds(&cache.tokens()[..n.min(cache.tokens().len())]) {
            return;
        }
        let copy = match cache.prefix_copy(n) {
            Ok(copy) => copy,
            Err(e) => return tracing::warn!(error = %e, "a prompt beginning was not stored"),
        };
        let store = store.clone();
        std::thread::spawn(move || {
            if let Err(e) = store.save(&copy) {
                tracing::warn!(error = %e, "a prompt beginning was not stored");
            }
        });
    }

    /// Stores the beginnings asked for by [`PromptCaches::store_when_computed`] that `cache` holds.
    pub fn store_asked(&self, cache: &KvCache) {
        let held: Vec<usize> = {
            let mut asked = lock(&self.to_store);
            let (held, rest) = asked
                .drain(..)
                .partition(|b: &Vec<u32>| cache.tokens().starts_with(b));
            *asked = rest;
            held.iter().map(Vec::len).collect()
        };
        for n in held {
            self.store_beginning(cache, n);
        }
    }

    /// Asks for `tokens` (a prompts' fixed beginning) to be stored once a call has computed them:
    /// a warm-up that gives way to a waiting call.
    pub fn store_when_computed(&self, tokens: Vec<u32>) {
        let Some(store) = &self.store else {
            return;
        };
        if !tokens.is_empty() && !store.holds(&tokens) {
            let mut asked = lock(&self.to_store);
            if !asked.contains(&tokens) {
                asked.push(tokens);
            }
        }
    }

    /// Keeps `cache` as the most recent, dropping the oldest beyond [`KEPT_CACHES`].
    pub fn keep(&self, cache: KvCache) {
        let mut kept = lock(&self.kept);
        kept.push(cache);
        while kept.len() > KEPT_CACHES {
            kept.remove(0);
        }
    }
}

/// The kept cache sharing most of `prompt`'s beginning and how many tokens of it to start from
/// (never the whole prompt: its last token is fed again for its logits); `None` when none
/// shares any.
fn best_kept(kept: &[KvCache], prompt: &[u32]) -> Option<(usize, usize)> {
    let (best, shared) = (kept.iter().enumerate())
        .map(|(i, c)| (i, shared(c.tokens(), prompt)))
        .max_by_key(|(_, n)| *n)?;
    let n = shared.min(prompt.len().saturating_sub(1));
    (n > 0).then_some((best, n))
}

/// The stored beginning of `prompt` it shares `len` tokens of, trusted once its last position,
/// computed again by this decoder from the positions before it (one decoding step), comes out
/// as stored ([`prompt_store::Difference::same_decoder`]; else removed from the store); cut back
/// so that the prompt's last token is still to feed.
fn stored_cache(
    store: &PromptStore,
    prompt: &[u32],
    len: usize,
    feed: Feed<'_>,
) -> Result<KvCache, String> {
    let mut cache = store.load(prompt, len)?;
    let stored_last = prompt_store::last_position(&cache)?;
    cache.truncate(len - 1);
    feed(&prompt[len - 1..len], &mut cache)?;
    let difference = prompt_store::difference(&stored_last, &prompt_store::last_position(&cache)?);
    if difference.same_decoder() {
        tracing::debug!(len, %difference, "a stored prompt beginning read back");
        cache.truncate(len.min(prompt.len() - 1));
        return Ok(cache);
    }
    store.forget_shared(prompt, len);
    Err(format!(
        "its last position computed again differs from the stored one by {difference} of its \
         norm (another decoder or other weights): removed"
    ))
}

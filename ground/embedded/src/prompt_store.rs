//! The key/value caches of prompt beginnings (the fixed part of the mission prompts: system
//! text, few-shot turns, the map) kept on disk, so that a ground station started again with the
//! same model and map does not compute them again: on two cores that part is 20–30 s of a
//! mission's first Coordinator call, and reading it back well under a second.
//!
//! One entry is two files named by the model, the weights' format and a hash of the tokens:
//! `NAME.safetensors` (each layer's keys `k.I` and values `v.I`, bf16 as the cache holds them,
//! exactly the held positions)
//! and `NAME.tokens` (the token ids, u32 little-endian), written after the tensors, so a
//! `.tokens` file means a whole entry. Both are written to a temporary name and renamed. An
//! entry is trusted only once its last position, computed again by this decoder from the rest,
//! matches what was stored within the rounding of Qwen's 8-bit activations ([`Difference`]): a
//! file from another decoder or other weights is dropped.
//! At most [`MAX_ENTRIES`] are kept, the least recently used removed first.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::SystemTime;

use candle_core::{DType, Device, Tensor};
use sha2::{Digest, Sha256};

use crate::decoder::KvCache;
use crate::lock;

/// Entries kept in the directory (Qwen2.5-Coder-1.5B: ~28 KB a token, so ~57 MB for a
/// 2,000-token beginning; a mission uses two, the Coordinator's and the Supervisor's).
pub const MAX_ENTRIES: usize = 6;

/// Bumped when the files' layout changes.
const LAYOUT: &str = "kv2";

/// The largest relative difference (see [`Difference`]) of the first layer's keys and values at
/// a stored position from the same position computed again: they depend only on the token, the
/// first layer's weights and the position, and come out the same however the position is
/// computed (0 with candle's product, 4e-7 with `matvec`'s; a position shifted by one, 6e-3).
pub const FIRST_LAYER_TOLERANCE: f32 = 1e-4;

/// The largest relative difference over every layer that still counts as the same decoder.
/// Qwen's products round the activations to 8 bits, so a position computed again from other
/// rows (a decoding step, or a prompt chunk starting elsewhere) lands 4–6 % away from the third
/// layer on (measured); the same position shifted by one and missing one token of its context
/// lands 19 % away, values scaled by 1.2 17 %.
pub const TOLERANCE: f32 = 0.12;

/// One entry on disk.
struct Stored {
    /// Its files' path without the extension. The names hold dots (`qwen2.5-…`): an extension
    /// is added with [`file`], never `Path::with_extension`, which would replace `.5-…`.
    stem: PathBuf,
    tokens: Vec<u32>,
}

/// `stem` + `.` + `extension`.
fn file(stem: &Path, extension: &str) -> PathBuf {
    let mut name = stem.as_os_str().to_owned();
    name.push(".");
    name.push(extension);
    PathBuf::from(name)
}

/// The entries of one model and weight format in one directory.
pub struct PromptStore {
    dir: PathBuf,
    /// Starts every entry's file name: the model, its file's hash, the weights' format, the layout.
    tag: String,
    index: Mutex<Vec<Stored>>,
}

fn tokens_hash(tokens: &[u32]) -> String {
    let mut h = Sha256::new();
    for t in tokens {
        h.update(t.to_le_bytes());
    }
    crate::fetch::hex(&h.finalize()[..8])
}

fn read_tokens(path: &Path) -> std::io::Result<Vec<u32>> {
    let bytes = std::fs::read(path)?;
    if bytes.len() % 4 != 0 {
        return Err(std::io::Error::other("not a whole number of token ids"));
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

/// Writes `path` by way of a temporary file renamed over it.
fn write_atomically(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<(), String> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(format!(".tmp{}", std::process::id()));
    let tmp = PathBuf::from(tmp);
    write(&tmp)
        .and_then(|()| std::fs::rename(&tmp, path).map_err(|e| e.to_string()))
        .inspect_err(|_| {
            let _ = std::fs::remove_file(&tmp);
        })
}

impl PromptStore {
    /// The store in `dir` (made if missing) for entries tagged `tag`; reads their token lists.
    pub fn open(dir: &Path, tag: &str) -> Result<PromptStore, String> {
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        let tag = format!("{tag}-{LAYOUT}-");
        let mut index = Vec::new();
        let listing = std::fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        for entry in listing.flatten() {
            let path = entry.path();
            let is_ours = path.extension().is_some_and(|e| e == "tokens")
                && path
                    .file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with(&tag));
            if !is_ours {
                continue;
            }
            match read_tokens(&path) {
                Ok(tokens) if !tokens.is_empty() => index.push(Stored {
                    stem: path.with_extension(""),
                    tokens,
                }),
                _ => remove_entry(&path.with_extension("")),
            }
        }
        Ok(PromptStore {
            dir: dir.to_owned(),
            tag,
            index: Mutex::new(index),
        })
    }

    /// How many tokens of `prompt`'s beginning the stored entry sharing most of it holds (0:
    /// none). Shared, not whole: a beginning stored with the opening of a user turn may end in
    /// a token that the whole turn, tokenized at once, spells otherwise.
    pub fn longest_prefix(&self, prompt: &[u32]) -> usize {
        lock(&self.index)
            .iter()
            .map(|s| shared(&s.tokens, prompt))
            .max()
            .unwrap_or(0)
    }

    /// Whether an entry holds all of `tokens`.
    pub fn holds(&self, tokens: &[u32]) -> bool {
        lock(&self.index)
            .iter()
            .any(|s| s.tokens.starts_with(tokens))
    }

    /// The stored entry sharing `len` tokens with `prompt`'s beginning, read back and cut to
    /// them (not yet checked against the decoder). A file that cannot be read is removed with
    /// its entry.
    pub fn load(&self, prompt: &[u32], len: usize) -> Result<KvCache, String> {
        let (stem, tokens) = {
            let index = lock(&self.index);
            let found = index
                .iter()
                .find(|s| len > 0 && shared(&s.tokens, prompt) == len);
            match found {
                Some(s) => (s.stem.clone(), s.tokens.clone()),
                None => return Err(format!("no stored beginning shares {len} tokens")),
            }
        };
        let read = || -> Result<KvCache, String> {
            let tensors = candle_core::safetensors::load(file(&stem, "safetensors"), &Device::Cpu)
                .map_err(|e| e.to_string())?;
            let mut cache = from_tensors(tensors, tokens)?;
            cache.truncate(len);
            Ok(cache)
        };
        match read() {
            Ok(cache) => {
                // Most recently used: the last to go.
                let _ = std::fs::File::options()
                    .append(true)
                    .open(file(&stem, "tokens"))
                    .and_then(|f| f.set_modified(SystemTime::now()));
                Ok(cache)
            }
            Err(e) => {
                self.forget(&stem);
                Err(format!("{}: {e}", stem.display()))
            }
        }
    }

    /// Drops the entry sharing `len` tokens with `prompt` (a stale one) from the index and the
    /// disk.
    pub fn forget_shared(&self, prompt: &[u32], len: usize) {
        let stem = lock(&self.index)
            .iter()
            .find(|s| shared(&s.tokens, prompt) == len)
            .map(|s| s.stem.clone());
        if let Some(stem) = stem {
            self.forget(&stem);
        }
    }

    fn forget(&self, stem: &Path) {
        lock(&self.index).retain(|s| s.stem != stem);
        remove_entry(stem);
    }

    /// Writes `cache` as an entry (blocking: run it off the model's thread), then removes the
    /// least recently used beyond [`MAX_ENTRIES`].
    pub fn save(&self, cache: &KvCache) -> Result<(), String> {
        let tokens = cache.tokens().to_vec();
        if tokens.is_empty() || self.holds(&tokens) {
            return Ok(());
        }
        let stem = self
            .dir
            .join(format!("{}{}", self.tag, tokens_hash(&tokens)));
        let tensors = to_tensors(cache)?;
        write_atomically(&file(&stem, "safetensors"), |tmp| {
            candle_core::safetensors::save(&tensors, tmp).map_err(|e| e.to_string())
        })?;
        let bytes: Vec<u8> = tokens.iter().flat_map(|t| t.to_le_bytes()).collect();
        write_atomically(&file(&stem, "tokens"), |tmp| {
            std::fs::write(tmp, &bytes).map_err(|e| e.to_string())
        })?;
        // Entries the new one extends are of no more use.
        let extended: Vec<PathBuf> = lock(&self.index)
            .iter()
            .filter(|s| tokens.starts_with(&s.tokens))
            .map(|s| s.stem.clone())
            .collect();
        for stem in extended {
            self.forget(&stem);
        }
        lock(&self.index).push(Stored { stem, tokens });
        self.evict();
        Ok(())
    }

    /// Removes the least recently used entries beyond [`MAX_ENTRIES`].
    fn evict(&self) {
        let mut index = lock(&self.index);
        if index.len() <= MAX_ENTRIES {
            return;
        }
        let used = |s: &Stored| {
            std::fs::metadata(file(&s.stem, "tokens"))
                .and_then(|m| m.modified())
                .unwrap_or(SystemTime::UNIX_EPOCH)
        };
        index.sort_by_key(|s| std::cmp::Reverse(used(s)));
        for gone in index.split_off(MAX_ENTRIES) {
            remove_entry(&gone.stem);
        }
    }
}

/// How many tokens `a` and `b` begin with in common.
pub fn shared(a: &[u32], b: &[u32]) -> usize {
    a.iter().zip(b).take_while(|(x, y)| x == y).count()
}

fn remove_entry(stem: &Path) {
    // The `.tokens` file first: without it the entry is not whole, whatever remains.
    let _ = std::fs::remove_file(file(stem, "tokens"));
    let _ = std::fs::remove_file(file(stem, "safetensors"));
}

fn to_tensors(cache: &KvCache) -> Result<HashMap<String, Tensor>, String> {
    let n = cache.tokens().len();
    let mut tensors = HashMap::new();
    for (i, layer) in cache.layers().iter().enumerate() {
        let Some((k, v)) = layer else {
            return Err(format!("layer {i} holds nothing"));
        };
        let held = |t: &Tensor| t.narrow(2, 0, n).and_then(|t| t.contiguous());
        tensors.insert(format!("k.{i}"), held(k).map_err(|e| e.to_string())?);
        tensors.insert(format!("v.{i}"), held(v).map_err(|e| e.to_string())?);
    }
    Ok(tensors)
}

fn from_tensors(mut tensors: HashMap<String, Tensor>, tokens: Vec<u32>) -> Result<KvCache, String> {
    let n_layers = tensors.len() / 2;
    let mut layers = Vec::with_capacity(n_layers);
    for i in 0..n_layers {
        let (Some(k), Some(v)) = (
            tensors.remove(&format!("k.{i}")),
            tensors.remove(&format!("v.{i}")),
        ) else {
            return Err(format!("layer {i} is missing"));
        };
        for t in [&k, &v] {
            let positions = t.dims4().map_err(|e| e.to_string())?.2;
            if positions != tokens.len() || t.dtype() != crate::decoder::KV_DTYPE {
                return Err(format!(
                    "layer {i}: {positions} positions of {:?} for {} tokens",
                    t.dtype(),
                    tokens.len()
                ));
            }
        }
        layers.push(Some((k, v)));
    }
    if n_layers == 0 || !tensors.is_empty() {
        return Err("not a key/value cache".into());
    }
    Ok(KvCache::from_layers(layers, tokens))
}

/// Each layer's keys and values at the cache's last position (copies).
pub fn last_position(cache: &KvCache) -> Result<Vec<(Tensor, Tensor)>, String> {
    let last = cache
        .tokens()
        .len()
        .checked_sub(1)
        .ok_or("an empty cache")?;
    cache
        .layers()
        .iter()
        .map(|layer| {
            let Some((k, v)) = layer else {
                return Err("a layer holds nothing".to_string());
            };
            let at = |t: &Tensor| t.narrow(2, last, 1).and_then(|t| t.copy());
            Ok((
                at(k).map_err(|e| e.to_string())?,
                at(v).map_err(|e| e.to_string())?,
            ))
        })
        .collect()
}

/// How far apart two sets of positions (each layer's keys and values) are: norms of the
/// differences relative to the norms of the first set's. Norms, not the largest element: one
/// element's rounding is not a different model.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Difference {
    /// The first layer's.
    pub first_layer: f32,
    /// The largest of every layer's.
    pub largest: f32,
}

impl Difference {
    /// Whether the two sets come from the same decoder and weights (see [`TOLERANCE`]).
    pub fn same_decoder(&self) -> bool {
        self.first_layer <= FIRST_LAYER_TOLERANCE && self.largest <= TOLERANCE
    }
}

impl std::fmt::Display for Difference {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:.1e} in the first layer and up to {:.1e}",
            self.first_layer, self.largest
        )
    }
}

/// How far `b` is from `a` (infinite when they cannot be compared).
pub fn difference(a: &[(Tensor, Tensor)], b: &[(Tensor, Tensor)]) -> Difference {
    let relative = |x: &Tensor, y: &Tensor| -> candle_core::Result<f32> {
        let norm = |t: &Tensor| -> candle_core::Result<f32> {
            Ok(t.sqr()?.sum_all()?.to_scalar::<f32>()?.sqrt())
        };
        let (x, y) = (x.to_dtype(DType::F32)?, y.to_dtype(DType::F32)?);
        Ok(norm(&(&x - &y)?)? / norm(&x)?.max(1e-12))
    };
    let apart = Difference {
        first_layer: f32::INFINITY,
        largest: f32::INFINITY,
    };
    if a.len() != b.len() || a.is_empty() {
        return apart;
    }
    let layers: Vec<f32> = a
        .iter()
        .zip(b)
        .map(|((ka, va), (kb, vb))| {
            let k = relative(ka, kb).unwrap_or(f32::INFINITY);
            let v = relative(va, vb).unwrap_or(f32::INFINITY);
            k.max(v)
        })
        .collect();
    Difference {
        first_layer: layers[0],
        largest: layers.iter().copied().fold(0.0, f32::max),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cache(tokens: Vec<u32>, fill: f32) -> KvCache {
        let n = tokens.len();
        let layer = || {
            let t = Tensor::full(fill, (1, 2, n, 4), &Device::Cpu).expect("tensor");
            let kv = |t: Tensor| t.to_dtype(crate::decoder::KV_DTYPE).expect("bf16");
            Some((kv(t.clone()), kv((t * 2.0).expect("scaled"))))
        };
        KvCache::from_layers(vec![layer(), layer()], tokens)
    }

    /// One layer's keys and values at one position, every element `fill`.
    fn position(fill: f32) -> (Tensor, Tensor) {
        let t = Tensor::full(fill, (1, 2, 1, 4), &Device::Cpu).expect("tensor");
        (t.clone(), t)
    }

    #[test]
    fn deep_layers_may_round_apart_but_the_first_layer_may_not() {
        let stored = [position(1.0), position(1.0), position(1.0)];
        // Deep layers 5 % apart: the rounding of another computation of the position.
        let rounded = [position(1.0), position(1.0), position(1.05)];
        let d = difference(&stored, &rounded);
        assert!(d.same_decoder(), "{d}");
        assert!(
            (d.largest - 0.05).abs() < 1e-4 && d.first_layer == 0.0,
            "{d}"
        );
        // The first layer 0.1 % apart: another token, position or weights.
        let moved = [position(1.001), position(1.0), position(1.0)];
        assert!(!difference(&stored, &moved).same_decoder());
        // Every layer 20 % apart.
        let other = [position(1.2), position(1.2), position(1.2)];
        assert!(!difference(&stored, &other).same_decoder());
        // Nothing to compare.
        assert!(!difference(&stored, &stored[..2]).same_decoder());
        assert!(!difference(&[], &[]).same_decoder());
    }

    fn dir(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("tacos-prompt-store-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn a_saved_beginning_is_found_for_a_longer_prompt_after_a_restart() {
        let d = dir("restart");
        let store = PromptStore::open(&d, "m2.5-1.5b").expect("open");
        store.save(&cache(vec![1, 2, 3], 0.5)).expect("save");
        let again = PromptStore::open(&d, "m2.5-1.5b").expect("reopen");
        assert_eq!(again.longest_prefix(&[1, 2, 3, 4, 5]), 3);
        assert_eq!(again.longest_prefix(&[7, 2, 3]), 0);
        let loaded = again.load(&[1, 2, 3, 4], 3).expect("load");
        assert_eq!(loaded.tokens(), &[1, 2, 3]);
        // A prompt that parts from the entry before its end shares what it shares.
        assert_eq!(again.longest_prefix(&[1, 2, 4]), 2);
        assert_eq!(again.load(&[1, 2, 4], 2).expect("load").tokens(), &[1, 2]);
        assert!(again.holds(&[1, 2]) && !again.holds(&[1, 2, 3, 4]));
        let original = last_position(&cache(vec![1, 2, 3], 0.5)).expect("positions");
        let read_back = last_position(&loaded).expect("positions");
        let same = difference(&original, &read_back);
        assert_eq!((same.first_layer, same.largest), (0.0, 0.0));
        assert!(same.same_decoder());
        let other = last_position(&cache(vec![1, 2, 3], 0.6)).expect("positions");
        assert!(!difference(&original, &other).same_decoder());
        // Another model's tag sees nothing.
        assert_eq!(
            PromptStore::open(&d, "m2.5-0.5b")
                .expect("open")
                .longest_prefix(&[1, 2, 3]),
            0
        );
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn a_broken_file_is_a_miss_and_is_removed() {
        let d = dir("broken");
        let store = PromptStore::open(&d, "m2.5-1.5b").expect("open");
        store.save(&cache(vec![7, 8], 1.0)).expect("save");
        let tensors = std::fs::read_dir(&d)
            .expect("dir")
            .flatten()
            .map(|e| e.path())
            .find(|p| p.extension().is_some_and(|e| e == "safetensors"))
            .expect("the tensors file");
        std::fs::write(&tensors, b"not safetensors").expect("overwrite");
        assert!(store.load(&[7, 8, 9], 2).is_err());
        assert_eq!(store.longest_prefix(&[7, 8, 9]), 0);
        assert_eq!(std::fs::read_dir(&d).expect("dir").count(), 0, "files left");
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn no_more_than_the_limit_is_kept_the_least_recently_used_going_first() {
        let d = dir("evict");
        let store = PromptStore::open(&d, "m2.5-1.5b").expect("open");
        for t in 0..MAX_ENTRIES as u32 {
            store.save(&cache(vec![100 + t], 1.0)).expect("save");
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        // The first is used again, so the second is the least recently used.
        store.load(&[100, 5], 1).expect("load");
        store.save(&cache(vec![999], 1.0)).expect("save");
        assert_eq!(
            store.longest_prefix(&[100]),
            1,
            "the one used again was removed"
        );
        assert_eq!(
            store.longest_prefix(&[101]),
            0,
            "the least recently used is kept"
        );
        assert_eq!(store.longest_prefix(&[999]), 1);
        let files = std::fs::read_dir(&d).expect("dir").count();
        assert_eq!(files, 2 * MAX_ENTRIES);
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn an_entry_that_a_longer_one_extends_is_replaced() {
        let d = dir("extend");
        let store = PromptStore::open(&d, "m2.5-1.5b").expect("open");
        store.save(&cache(vec![1, 2], 1.0)).expect("save");
        store.save(&cache(vec![1, 2, 3, 4], 1.0)).expect("save");
        assert_eq!(store.longest_prefix(&[1, 2, 3, 4, 5]), 4);
        let files = std::fs::read_dir(&d).expect("dir").count();
        assert_eq!(files, 2, "the shorter entry was kept");
        let _ = std::fs::remove_dir_all(&d);
    }
}

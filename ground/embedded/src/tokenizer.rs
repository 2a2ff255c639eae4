//! The tokenizer, built from the GGUF metadata alone (no `tokenizer.json`, no network), and its
//! byte-level view for llguidance.
//!
//! Both models use a GPT-2 style byte-level BPE (`tokenizer.ggml.model = gpt2`); they differ in
//! the pre-tokenizer (`tokenizer.ggml.pre`), rebuilt here as the models' `tokenizer.json` on the
//! Hub has it:
//! - `smollm` (SmolLM2): digits split one by one, then the GPT-2 regex:
//!   `Sequence[Digits(individual), ByteLevel]`;
//! - `qwen2` (Qwen2.5): NFC normalisation, then Qwen2's split regex (single digits, letters with
//!   one leading non-letter, …), then the byte-level mapping without its own regex.

use std::str::FromStr;

use candle_core::quantized::gguf_file::{Content, Value};
use llguidance::toktrie::TokEnv;
use serde_json::{Map, json};
use tokenizers::Tokenizer;

use crate::byte_view::{self, TOKEN_TYPE_CONTROL, TOKEN_TYPE_UNUSED, TOKEN_TYPE_USER_DEFINED};
use crate::catalogue::EmbeddedModel;
use crate::template::Segment;

/// Qwen2's pre-tokenizer split (its `tokenizer.json`; llama.cpp's `LLAMA_VOCAB_PRE_TYPE_QWEN2`).
const QWEN2_SPLIT: &str = r"(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*|\s*[\r\n]+|\s+(?!\S)|\s+";

/// The tokenizer of the loaded model.
pub struct ModelTokenizer {
    /// Encodes message text: control tokens written in the text are *not* recognised, so a
    /// message cannot forge a turn.
    text: Tokenizer,
    pub im_start: u32,
    pub im_end: u32,
    pub end_of_text: u32,
    /// Tokens `0..real_vocab` are the vocabulary; logits beyond are padding rows.
    pub real_vocab: usize,
    pub tok_env: TokEnv,
}

fn md<'a>(ct: &'a Content, key: &str) -> Result<&'a Value, String> {
    ct.metadata
        .get(key)
        .ok_or_else(|| format!("GGUF metadata has no `{key}`"))
}

fn md_strings(ct: &Content, key: &str) -> Result<Vec<String>, String> {
    let arr = md(ct, key)?.to_vec().map_err(|e| format!("`{key}`: {e}"))?;
    arr.iter()
        .map(|v| v.to_string().cloned().map_err(|e| format!("`{key}`: {e}")))
        .collect()
}

fn md_i32s(ct: &Content, key: &str) -> Result<Vec<i32>, String> {
    let arr = md(ct, key)?.to_vec().map_err(|e| format!("`{key}`: {e}"))?;
    arr.iter()
        .map(|v| v.to_i32().map_err(|e| format!("`{key}`: {e}")))
        .collect()
}

/// The GGUF's token list and each token's type, read once for the three views built from them
/// (the tokenizer, llguidance's bytes, the real vocabulary's size).
struct Vocabulary {
    tokens: Vec<String>,
    types: Vec<i32>,
}

impl Vocabulary {
    fn read(ct: &Content) -> Result<Vocabulary, String> {
        let tokens = md_strings(ct, "tokenizer.ggml.tokens")?;
        let types = md_i32s(ct, "tokenizer.ggml.token_type")?;
        if types.len() != tokens.len() {
            return Err(format!(
                "{} tokens but {} token types",
                tokens.len(),
                types.len()
            ));
        }
        Ok(Vocabulary { tokens, types })
    }
}

/// The `tokenizer.json` equivalent of the GGUF tokenizer metadata (`vocabulary` read from it).
fn tokenizer_json(ct: &Content, vocabulary: &Vocabulary) -> Result<serde_json::Value, String> {
    let model = md(ct, "tokenizer.ggml.model")?
        .to_string()
        .map_err(|e| e.to_string())?;
    if model != "gpt2" {
        return Err(format!(
            "unsupported tokenizer model `{model}` (only byte-level BPE `gpt2`)"
        ));
    }
    let pre = match ct.metadata.get("tokenizer.ggml.pre") {
        Some(v) => v.to_string().map_err(|e| e.to_string())?.clone(),
        None => "default".to_string(),
    };
    let byte_level = json!({
        "type": "ByteLevel", "add_prefix_space": false, "trim_offsets": true, "use_regex": true
    });
    let (normalizer, pre_tokenizer) = match pre.as_str() {
        "smollm" => (
            json!(null),
            json!({
                "type": "Sequence",
                "pretokenizers": [{"type": "Digits", "individual_digits": true}, byte_level]
            }),
        ),
        "qwen2" => (
            json!({"type": "NFC"}),
            json!({
                "type": "Sequence",
                "pretokenizers": [
                    {"type": "Split", "pattern": {"Regex": QWEN2_SPLIT},
                     "behavior": "Isolated", "invert": false},
                    {"type": "ByteLevel", "add_prefix_space": false, "trim_offsets": false,
                     "use_regex": false}
                ]
            }),
        ),
        "gpt2" | "default" => (json!(null), byte_level),
        other => return Err(format!("unsupported pre-tokenizer `{other}`")),
    };
    let Vocabulary { tokens, types } = vocabulary;
    let merges = md_strings(ct, "tokenizer.ggml.merges")?;
    let mut vocab = Map::with_capacity(tokens.len());
    let mut added = Vec::new();
    for (id, (tok, ty)) in tokens.iter().zip(types).enumerate() {
        vocab.insert(tok.clone(), json!(id));
        if *ty == TOKEN_TYPE_CONTROL || *ty == TOKEN_TYPE_USER_DEFINED {
            added.push(json!({
                "id": id, "content": tok, "single_word": false, "lstrip": false, "rstrip": false,
                "normalized": false, "special": *ty == TOKEN_TYPE_CONTROL,
            }));
        }
    }
    Ok(json!({
        "version": "1.0",
        "truncation": null,
        "padding": null,
        "added_tokens": added,
        "normalizer": normalizer,
        "pre_tokenizer": pre_tokenizer,
        "post_processor": null,
        "decoder": {"type": "ByteLevel", "add_prefix_space": true, "trim_offsets": true, "use_regex": true},
        "model": {
            "type": "BPE", "dropout": null, "unk_token": null, "continuing_subword_prefix": null,
            "end_of_word_suffix": null, "fuse_unk": false, "byte_fallback": false,
            "ignore_merges": false, "vocab": vocab, "merges": merges,
        },
    }))
}

/// How many tokens are real: the list without its trailing unused or `[PAD…]` entries (GGUF
/// files may pad the vocabulary to the output matrix's size).
fn real_vocab(Vocabulary { tokens, types }: &Vocabulary) -> usize {
    let mut n = tokens.len();
    while n > 0
        && (types.get(n - 1) == Some(&TOKEN_TYPE_UNUSED) || tokens[n - 1].starts_with("[PAD"))
    {
        n -= 1;
    }
    n
}

impl ModelTokenizer {
    /// Builds the tokenizer from the GGUF metadata; `n_vocab` is the model's output size.
    pub fn from_gguf(
        ct: &Content,
        model: EmbeddedModel,
        n_vocab: usize,
    ) -> Result<ModelTokenizer, String> {
        let vocabulary = Vocabulary::read(ct)?;
        let spec = tokenizer_json(ct, &vocabulary)?;
        let real_vocab = real_vocab(&vocabulary);
        let hf = Tokenizer::from_str(&spec.to_string()).map_err(|e| format!("tokenizer: {e}"))?;
        let id = |t: &str| {
            hf.token_to_id(t)
                .ok_or_else(|| format!("the vocabulary has no {t}"))
        };
        let im_start = id(crate::template::IM_START)?;
        let im_end = id(crate::template::IM_END)?;
        let end_of_text = id("<|endoftext|>")?;
        if n_vocab < hf.get_vocab_size(true) {
            return Err(format!(
                "the model's output has {n_vocab} logits but the tokenizer {} tokens",
                hf.get_vocab_size(true)
            ));
        }
        let mut text = hf.clone();
        text.set_encode_special_tokens(true);

        let bytes = byte_view::token_bytes(&vocabulary.tokens, &vocabulary.types, n_vocab);
        // The chat turn ends with <|im_end|>; <|endoftext|> also ends a generation.
        let tok_env = byte_view::tok_env(&bytes, end_of_text, im_end, hf)
            .map_err(|e| format!("{}: {e}", model.display_name()))?;
        Ok(ModelTokenizer {
            text,
            im_start,
            im_end,
            end_of_text,
            real_vocab,
            tok_env,
        })
    }

    /// Token ids of plain text (control-token spellings are encoded as text).
    pub fn encode_text(&self, s: &str) -> Result<Vec<u32>, String> {
        let enc = self
            .text
            .encode(s, false)
            .map_err(|e| format!("tokenizer: {e}"))?;
        Ok(enc.get_ids().to_vec())
    }

    /// Token ids of a rendered prompt.
    pub fn encode_segments(&self, segments: &[Segment]) -> Result<Vec<u32>, String> {
        let mut ids = Vec::new();
        for s in segments {
            match s {
                Segment::ImStart => ids.push(self.im_start),
                Segment::ImEnd => ids.push(self.im_end),
                Segment::Text(t) => ids.extend(self.encode_text(t)?),
            }
        }
        Ok(ids)
    }

    /// Text of generated tokens (control tokens dropped, invalid UTF-8 replaced).
    pub fn decode(&self, ids: &[u32]) -> String {
        let bytes = self.tok_env.tok_trie().decode_ext(ids, false);
        String::from_utf8_lossy(&bytes).into_owned()
    }

    pub fn is_end(&self, id: u32) -> bool {
        id == self.im_end || id == self.end_of_text
    }
}

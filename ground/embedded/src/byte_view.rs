//! The vocabulary as llguidance sees it: every token's bytes in a [`TokTrie`] (control tokens
//! marked special), and text tokenized by the model's own tokenizer.
//!
//! Built from the GGUF token list directly. `toktrie_hf_tokenizers` builds the same view from a
//! `tokenizers::Tokenizer`, but pins tokenizers 0.21, a second copy of that crate beside the 0.23
//! candle needs (40 s of a cold build, issue 19 item 6).

use std::collections::HashMap;
use std::sync::Arc;

use llguidance::toktrie::{TokEnv, TokRxInfo, TokTrie, TokenId, TokenizerEnv};
use tokenizers::Tokenizer;

/// GGUF token types (llama.cpp `llama_token_type`).
pub(crate) const TOKEN_TYPE_CONTROL: i32 = 3;
pub(crate) const TOKEN_TYPE_USER_DEFINED: i32 = 4;
pub(crate) const TOKEN_TYPE_UNUSED: i32 = 5;

/// GPT-2's byte-level alphabet, read backwards: the byte each character of a token's spelling
/// stands for. The printable bytes (`!`..=`~`, `¡`..=`¬`, `®`..=`ÿ`) stand for themselves; the
/// other 68 are written as the characters from U+0100 on, in byte order.
fn byte_of_char() -> HashMap<char, u8> {
    let mut map = HashMap::with_capacity(256);
    let mut shifted = 0u32;
    for byte in 0..=255u8 {
        let printable = matches!(byte, b'!'..=b'~' | 0xA1..=0xAC | 0xAE..=0xFF);
        let c = if printable {
            Some(char::from(byte))
        } else {
            shifted += 1;
            char::from_u32(0xFF + shifted)
        };
        if let Some(c) = c {
            map.insert(c, byte);
        }
    }
    map
}

/// The bytes of each token of a byte-level BPE vocabulary (`tokens` with their GGUF `types`),
/// padded to `n_vocab` with special placeholders. A control token, or a user-defined one written
/// `<…>`, is special: its name behind [`TokTrie::SPECIAL_TOKEN_MARKER`], so no grammar can spell
/// it as text; another user-defined token is its text as it is; a token with a character outside
/// the byte alphabet has no bytes (it can never be allowed).
pub(crate) fn token_bytes(tokens: &[String], types: &[i32], n_vocab: usize) -> Vec<Vec<u8>> {
    let alphabet = byte_of_char();
    let mut out: Vec<Vec<u8>> = tokens
        .iter()
        .zip(types)
        .map(|(token, kind)| {
            let named = token.starts_with('<') && token.ends_with('>');
            match *kind {
                TOKEN_TYPE_CONTROL => special(token),
                TOKEN_TYPE_USER_DEFINED if named => special(token),
                TOKEN_TYPE_USER_DEFINED => token.as_bytes().to_vec(),
                _ => token
                    .chars()
                    .map(|c| alphabet.get(&c).copied())
                    .collect::<Option<Vec<u8>>>()
                    .unwrap_or_default(),
            }
        })
        .collect();
    while out.len() < n_vocab {
        let placeholder = format!("<[{}]>", out.len());
        out.push(special(&placeholder));
    }
    out
}

fn special(name: &str) -> Vec<u8> {
    let mut bytes = vec![TokTrie::SPECIAL_TOKEN_MARKER];
    bytes.extend_from_slice(name.as_bytes());
    bytes
}

/// llguidance's view of the model: the trie of `token_bytes`, generation ending at any of
/// `eos`, and `tokenizer` for the text a grammar forces.
pub(crate) fn tok_env(
    token_bytes: &[Vec<u8>],
    end_of_text: TokenId,
    end_of_turn: TokenId,
    tokenizer: Tokenizer,
) -> Result<TokEnv, String> {
    let n_vocab = u32::try_from(token_bytes.len()).map_err(|e| format!("vocabulary: {e}"))?;
    let mut info = TokRxInfo::new(n_vocab, end_of_text);
    info.tok_end_of_turn = Some(end_of_turn);
    let trie = TokTrie::from(&info, token_bytes).with_eos_tokens(&[end_of_turn, end_of_text]);
    Ok(Arc::new(ByteView { trie, tokenizer }))
}

struct ByteView {
    trie: TokTrie,
    tokenizer: Tokenizer,
}

impl TokenizerEnv for ByteView {
    fn tok_trie(&self) -> &TokTrie {
        &self.trie
    }

    /// Text as the model's tokenizer splits it; bytes that are not UTF-8, or text the
    /// tokenizer fails on, greedily by the trie.
    fn tokenize_bytes(&self, s: &[u8]) -> Vec<TokenId> {
        self.trie.tokenize_with_greedy_fallback(s, |text| {
            match self.tokenizer.encode(text, false) {
                Ok(encoding) => encoding.get_ids().to_vec(),
                Err(_) => self.trie.greedy_tokenize(text.as_bytes()),
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_byte_alphabet_is_gpt2_s() {
        let alphabet = byte_of_char();
        assert_eq!(alphabet.len(), 256);
        // A space is written Ġ (U+0120), a newline Ċ (U+010A), a tab ĉ (U+0109).
        assert_eq!(alphabet[&'Ġ'], b' ');
        assert_eq!(alphabet[&'Ċ'], b'\n');
        assert_eq!(alphabet[&'ĉ'], b'\t');
        assert_eq!(alphabet[&'a'], b'a');
        assert_eq!(alphabet[&'\u{100}'], 0);
        assert_eq!(alphabet[&'ÿ'], 0xFF);
        // The soft hyphen (0xAD) is not printable: the last shifted byte.
        assert_eq!(alphabet[&'\u{143}'], 0xAD);
    }

    #[test]
    fn control_tokens_are_special_and_the_rest_is_bytes() {
        let tokens: Vec<String> = ["ĠHello", "<|im_end|>", "<tool>", "plain", "Ã©", "€"]
            .map(String::from)
            .to_vec();
        let user = TOKEN_TYPE_USER_DEFINED;
        let types = [1, TOKEN_TYPE_CONTROL, user, user, 1, 1];
        let bytes = token_bytes(&tokens, &types, 8);
        assert_eq!(bytes[0], b" Hello");
        assert_eq!(bytes[1], special("<|im_end|>"));
        assert_eq!(bytes[2], special("<tool>"));
        assert_eq!(bytes[3], b"plain");
        // "é" in UTF-8, spelt in the byte alphabet.
        assert_eq!(bytes[4], "é".as_bytes());
        // "€" is not a character of the alphabet: no bytes.
        assert!(bytes[5].is_empty(), "{:?}", bytes[5]);
        assert_eq!(bytes[6], special("<[6]>"));
        assert_eq!(bytes.len(), 8);
    }
}

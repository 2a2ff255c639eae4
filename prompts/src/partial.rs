//! A reply read while it is being written: the `reasoning` text so far and the calls complete so
//! far, from a JSON object that may stop anywhere. What the pilot sees while a model writes;
//! the reply is judged only once whole (`reply`).

use crate::Call;

/// What a reply being written says so far.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PartialReply {
    /// The `reasoning` field so far (also while its string is still open).
    pub reasoning: Option<String>,
    /// The complete calls of the `plan` (Coordinator) or `actions` (Supervisor, monolithic)
    /// list so far, in order; one that does not parse as a call is left out.
    pub calls: Vec<Call>,
}

/// Reads `text`, the start of a reply object, as far as it goes.
pub fn partial_reply(text: &str) -> PartialReply {
    let mut out = PartialReply::default();
    let b = text.as_bytes();
    let Some(mut i) = skip_ws(b, 0).filter(|&i| b[i] == b'{').map(|i| i + 1) else {
        return out;
    };
    loop {
        let Some(k) = skip_ws(b, i) else { return out };
        if b[k] == b'}' || b[k] != b'"' {
            return out;
        }
        let Some(key_end) = string_end(b, k) else {
            return out;
        };
        let key = &text[k + 1..key_end - 1];
        let Some(colon) = skip_ws(b, key_end).filter(|&c| b[c] == b':') else {
            return out;
        };
        let Some(v) = skip_ws(b, colon + 1) else {
            return out;
        };
        match (key, b[v]) {
            ("reasoning", b'"') => match string_end(b, v) {
                Some(end) => {
                    out.reasoning = serde_json::from_str(&text[v..end]).ok();
                    i = end;
                }
                None => {
                    out.reasoning = Some(open_string(&text[v + 1..]));
                    return out;
                }
            },
            ("plan" | "actions", b'[') => {
                let mut j = v + 1;
                loop {
                    let Some(e) = skip_ws(b, j) else { return out };
                    match b[e] {
                        b',' => j = e + 1,
                        b']' => {
                            i = e + 1;
                            break;
                        }
                        _ => {
                            let Some(end) = value_end(b, e).filter(|&end| end > e) else {
                                return out;
                            };
                            if let Ok(call) = serde_json::from_str::<Call>(&text[e..end]) {
                                out.calls.push(call);
                            }
                            j = end;
                        }
                    }
                }
            }
            _ => match value_end(b, v) {
                Some(end) => i = end,
                None => return out,
            },
        }
        match skip_ws(b, i) {
            Some(c) if b[c] == b',' => i = c + 1,
            _ => return out,
        }
    }
}

/// The first non-whitespace position from `i`, if any.
fn skip_ws(b: &[u8], i: usize) -> Option<usize> {
    (i..b.len()).find(|&j| !b[j].is_ascii_whitespace())
}

/// Just past the string that opens at `start` (a `"`), if it is closed.
fn string_end(b: &[u8], start: usize) -> Option<usize> {
    let mut j = start + 1;
    while j < b.len() {
        match b[j] {
            b'\\' => j += 2,
            b'"' => return Some(j + 1),
            _ => j += 1,
        }
    }
    None
}

/// Just past the JSON value that starts at `start`, if it is complete.
fn value_end(b: &[u8], start: usize) -> Option<usize> {
    match b[start] {
        b'"' => string_end(b, start),
        b'{' | b'[' => {
            let mut depth = 0usize;
            let mut j = start;
            while j < b.len() {
                match b[j] {
                    b'"' => {
                        j = string_end(b, j)?;
                        continue;
                    }
                    b'{' | b'[' => depth += 1,
                    b'}' | b']' => {
                        depth = depth.saturating_sub(1);
                        if depth == 0 {
                            return Some(j + 1);
                        }
                    }
                    _ => {}
                }
                j += 1;
            }
            None
        }
        // A number or a literal ends where a delimiter follows it; at the end of the text it
        // may still be growing.
        _ => (start..b.len())
            .find(|&j| matches!(b[j], b',' | b'}' | b']') || b[j].is_ascii_whitespace()),
    }
}

/// The text of a string still open: its escapes decoded as far as they are complete.
fn open_string(raw: &str) -> String {
    let mut out = String::with_capacity(raw.len());
    let mut chars = raw.chars();
    while let Some(c) = chars.next() {
        if c != '\\' {
            out.push(c);
            continue;
        }
        match chars.next() {
            Some('n') => out.push('\n'),
            Some('t') => out.push('\t'),
            Some('r') => {}
            Some('u') => {
                let hex: String = chars.by_ref().take(4).collect();
                match u32::from_str_radix(&hex, 16).ok().and_then(char::from_u32) {
                    Some(c) if hex.len() == 4 => out.push(c),
                    _ => break,
                }
            }
            Some(other) => out.push(other),
            None => break,
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const WHOLE: &str = r#"{"reasoning": "Alfa is \"closest\"\nto car_11.", "plan": [{"task": "T1", "drone": "alfa", "action": "goto", "target": "car_11", "xyz": null}, {"task": "T2", "drone": "bravo", "action": "arm_takeoff", "target": "none", "xyz": null}], "refusal": ""}"#;

    #[test]
    fn every_prefix_of_a_reply_reads_as_far_as_it_goes() {
        let mut last = PartialReply::default();
        for cut in 0..=WHOLE.len() {
            if !WHOLE.is_char_boundary(cut) {
                continue;
            }
            let now = partial_reply(&WHOLE[..cut]);
            assert!(
                now.calls.len() >= last.calls.len(),
                "calls never go away: {cut}"
            );
            if let (Some(before), Some(after)) = (&last.reasoning, &now.reasoning) {
                assert!(
                    after.starts_with(before.as_str()) || before.ends_with('\\'),
                    "{cut}"
                );
            }
            last = now;
        }
        assert_eq!(
            last.reasoning.as_deref(),
            Some("Alfa is \"closest\"\nto car_11.")
        );
        let calls: Vec<String> = last.calls.iter().map(|c| c.to_string()).collect();
        assert_eq!(calls.len(), 2, "{calls:?}");
        assert!(
            calls[0].contains("alfa") && calls[0].contains("car_11"),
            "{calls:?}"
        );
        let mid = partial_reply(&WHOLE[..WHOLE.find("T2").unwrap_or(0)]);
        assert_eq!(mid.calls.len(), 1, "the second call is not complete yet");
        let open = partial_reply(r#"{"reasoning": "Alfa is \"clo"#);
        assert_eq!(open.reasoning.as_deref(), Some("Alfa is \"clo"));
    }

    #[test]
    fn a_supervisor_reply_and_text_that_is_no_reply_read_too() {
        let cycle = r#"{"reasoning":"start T1","actions":[{"task":"T1","drone":"alfa","action":"land","target":"none","xyz":null}],"plan_complete":fa"#;
        let read = partial_reply(cycle);
        assert_eq!(read.reasoning.as_deref(), Some("start T1"));
        assert_eq!(read.calls.len(), 1);
        assert_eq!(partial_reply("Sure! Here is"), PartialReply::default());
        assert_eq!(partial_reply(""), PartialReply::default());
        let odd = partial_reply(r#"{"other": {"x": [1, "]"]}, "reasoning": "after"}"#);
        assert_eq!(odd.reasoning.as_deref(), Some("after"));
    }
}

//! Drones the pilot addresses that the swarm does not have.
//!
//! "zulu, take off" in a swarm without zulu went to the Coordinator, which answered "Zulu is
//! already flying" and planned take-offs for the others; the pilot was never told there is no
//! zulu. Before any model call, an instruction that addresses a drone the swarm does not have
//! is refused with the swarm's drones.
//!
//! A word counts as a drone's name when it is one (a drone slot of the map, or a word of the
//! phonetic alphabet the drones are named from) and the sentence uses it as one: it opens the
//! instruction or a clause and is followed by a comma or a colon ("zulu, take off",
//! "alfa and zulu, land"), or it follows the word "drone". Elsewhere ("fly over the hotel") it
//! is left to the model: refusing a valid instruction would be worse than asking a model.

/// The phonetic alphabet's words, as drones are named (both spellings where two are common).
const PHONETIC: [&str; 29] = [
    "alfa", "alpha", "bravo", "charlie", "delta", "echo", "foxtrot", "golf", "hotel", "india",
    "juliett", "juliet", "kilo", "lima", "mike", "november", "oscar", "papa", "quebec", "romeo",
    "sierra", "tango", "uniform", "victor", "whiskey", "whisky", "xray", "yankee", "zulu",
];

/// The drone names `text` addresses that are not in `swarm`, each once, in order. `slots`: the
/// map's drone ids (a drone name even when not flying today); `places`: the map's landmark and
/// target names, never taken for a drone.
pub fn unknown_drones(
    text: &str,
    swarm: &[String],
    slots: &[String],
    places: &[String],
) -> Vec<String> {
    let lower = text.to_lowercase();
    let words = tokens(&lower);
    let is_name = |word: &str| {
        !places.iter().any(|p| p == word)
            && (swarm.iter().any(|s| s == word)
                || slots.iter().any(|s| s == word)
                || PHONETIC.contains(&word))
    };
    let mut out: Vec<String> = Vec::new();
    for (i, (word, _)) in words.iter().enumerate() {
        if !is_name(word) || swarm.iter().any(|s| s == word) || out.contains(word) {
            continue;
        }
        let before = i.checked_sub(1).map(|j| &words[j]);
        let opens_clause = match before {
            None => true,
            Some((prev, sep)) => matches!(sep, ',' | ';' | '.' | ':') || prev == "and",
        };
        let after_drone = before.is_some_and(|(prev, _)| prev == "drone");
        if after_drone || (opens_clause && addressed_list(&words, i, &is_name)) {
            out.push(word.clone());
        }
    }
    out
}

/// Whether the names from position `i` on ("delta", "delta and zulu", "delta, zulu") end with
/// a comma or a colon before the next word that is no name: the list is addressed.
fn addressed_list(words: &[(String, char)], mut i: usize, is_name: &dyn Fn(&str) -> bool) -> bool {
    loop {
        let (_, after) = &words[i];
        let next = words.get(i + 1).map(|(w, _)| w.as_str());
        match next {
            Some("and") if words.get(i + 2).is_some_and(|(w, _)| is_name(w)) => i += 2,
            Some(w) if *after == ',' && is_name(w) => i += 1,
            _ => return matches!(after, ',' | ':'),
        }
    }
}

/// The words of `text` (letters, digits, `_`, `-`) with the punctuation that follows each
/// (' ' when none).
fn tokens(text: &str) -> Vec<(String, char)> {
    let mut out: Vec<(String, char)> = Vec::new();
    let mut word = String::new();
    for c in text.chars() {
        if c.is_alphanumeric() || c == '_' || c == '-' {
            word.push(c);
            continue;
        }
        if !word.is_empty() {
            out.push((std::mem::take(&mut word), ' '));
        }
        if !c.is_whitespace()
            && let Some(last) = out.last_mut()
            && last.1 == ' '
        {
            last.1 = c;
        }
    }
    if !word.is_empty() {
        out.push((word, ' '));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn a_drone_addressed_by_a_name_the_swarm_lacks_is_found() {
        let swarm = names(&["alfa", "bravo", "charlie"]);
        let slots = names(&["alfa", "bravo", "charlie", "delta", "echo", "hotel"]);
        let places = names(&["villa", "car_1", "small_park"]);
        let unknown = |text: &str| unknown_drones(text, &swarm, &slots, &places);
        assert_eq!(unknown("zulu, take off"), ["zulu"]);
        assert_eq!(unknown("Zulu: land"), ["zulu"]);
        assert_eq!(unknown("alfa and delta, take off"), ["delta"]);
        assert_eq!(
            unknown("alfa, delta and zulu, go to the villa"),
            ["delta", "zulu"]
        );
        assert_eq!(unknown("take off. echo, go to car_1"), ["echo"]);
        assert_eq!(unknown("send drone hotel to the villa"), ["hotel"]);
        // The swarm's own drones, and names not used as a drone's.
        assert!(unknown("alfa, take off").is_empty());
        assert!(unknown("all drones take off").is_empty());
        assert!(unknown("fly alfa over the hotel, then land").is_empty());
        assert!(unknown("alfa, look for the golf course near echo street").is_empty());
        // A place that happens to be such a word is a place.
        let places = names(&["hotel"]);
        assert!(unknown_drones("hotel, then villa", &swarm, &slots, &places).is_empty());
        // Each once.
        assert_eq!(unknown("zulu, take off; zulu, land"), ["zulu"]);
    }
}

//! The pilot's direct commands, recognised before any model is called and executed at once:
//! `land all`, `hold all`, `<drone> land`, `<drone> hold`, `cancel` (end the current plan and
//! hold the drones it moves) and `undo` (fly the drones the last instruction moved back to where
//! they were before it).

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Directive {
    LandAll,
    HoldAll,
    Land(String),
    Hold(String),
    Cancel,
    Undo,
}

/// Recognises a direct command; anything else is for the models.
pub fn parse(text: &str, drones: &[String]) -> Option<Directive> {
    let cleaned: String = text
        .to_lowercase()
        .chars()
        .map(|c| {
            if c.is_alphanumeric() || c == '_' || c == '-' {
                c
            } else {
                ' '
            }
        })
        .collect();
    let words: Vec<&str> = cleaned
        .split_whitespace()
        .filter(|w| !matches!(*w, "now" | "please" | "drones" | "the"))
        .collect();
    let is_drone = |w: &str| drones.iter().any(|d| d == w);
    match words.as_slice() {
        ["land", "all"] | ["all", "land"] | ["everyone", "land"] | ["land", "everyone"] => {
            Some(Directive::LandAll)
        }
        ["hold", "all"]
        | ["all", "hold"]
        | ["everyone", "hold"]
        | ["hold", "everyone"]
        | ["stop", "all"]
        | ["all", "stop"] => Some(Directive::HoldAll),
        ["cancel"] | ["cancel", "that" | "it" | "plan" | "mission"] => Some(Directive::Cancel),
        ["undo"] | ["undo", "that" | "it"] => Some(Directive::Undo),
        [d, "land"] | ["land", d] if is_drone(d) => Some(Directive::Land((*d).to_owned())),
        [d, "hold"] | ["hold", d] | [d, "stop"] if is_drone(d) => {
            Some(Directive::Hold((*d).to_owned()))
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recognises_the_direct_commands_only() {
        let drones = vec!["alfa".to_owned(), "bravo".to_owned()];
        assert_eq!(parse("Land all!", &drones), Some(Directive::LandAll));
        assert_eq!(
            parse("land all drones now", &drones),
            Some(Directive::LandAll)
        );
        assert_eq!(parse("hold all", &drones), Some(Directive::HoldAll));
        assert_eq!(
            parse("Alfa, land.", &drones),
            Some(Directive::Land("alfa".into()))
        );
        assert_eq!(
            parse("bravo hold", &drones),
            Some(Directive::Hold("bravo".into()))
        );
        assert_eq!(parse("zulu land", &drones), None);
        assert_eq!(parse("alfa, land at the villa", &drones), None);
        assert_eq!(parse("all drones take off", &drones), None);
        assert_eq!(parse("Cancel!", &drones), Some(Directive::Cancel));
        assert_eq!(parse("cancel the plan", &drones), Some(Directive::Cancel));
        assert_eq!(parse("undo", &drones), Some(Directive::Undo));
        assert_eq!(parse("Undo that, please.", &drones), Some(Directive::Undo));
        // The paper's "go back to the last location" is for the models.
        assert_eq!(parse("alfa, go back to the last location", &drones), None);
        assert_eq!(parse("cancel alfa's goto and land it", &drones), None);
    }
}

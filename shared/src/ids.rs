//! Names of drones and swarms. They become parts of zenoh keys and iceoryx2 service names, so
//! they are restricted to characters that are literal in both (no `/`, `*`, `$`, `?`, `#`).

use serde::{Deserialize, Serialize};
use std::fmt;

/// Longest id accepted; keeps keys and service names short.
pub const MAX_ID_LEN: usize = 32;

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IdError {
    #[error("an id may not be empty")]
    Empty,
    #[error("id {0:?} is longer than {MAX_ID_LEN} characters")]
    TooLong(String),
    #[error(
        "id {0:?} may hold only lowercase letters, digits, '_' and '-', and must start with a letter"
    )]
    BadCharacter(String),
}

fn validate(raw: &str) -> Result<(), IdError> {
    if raw.is_empty() {
        return Err(IdError::Empty);
    }
    if raw.len() > MAX_ID_LEN {
        return Err(IdError::TooLong(raw.to_owned()));
    }
    let mut chars = raw.chars();
    let first_ok = chars.next().is_some_and(|c| c.is_ascii_lowercase());
    let rest_ok =
        chars.all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_' || c == '-');
    if first_ok && rest_ok {
        Ok(())
    } else {
        Err(IdError::BadCharacter(raw.to_owned()))
    }
}

macro_rules! id_type {
    ($(#[$meta:meta])* $name:ident) => {
        $(#[$meta])*
        #[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
        #[serde(try_from = "String", into = "String")]
        pub struct $name(String);

        impl $name {
            /// Validates and wraps `raw`.
            pub fn new(raw: impl Into<String>) -> Result<Self, IdError> {
                let raw = raw.into();
                validate(&raw)?;
                Ok(Self(raw))
            }

            pub fn as_str(&self) -> &str {
                &self.0
            }
        }

        impl TryFrom<String> for $name {
            type Error = IdError;
            fn try_from(raw: String) -> Result<Self, IdError> {
                Self::new(raw)
            }
        }

        impl From<$name> for String {
            fn from(id: $name) -> String {
                id.0
            }
        }

        impl std::str::FromStr for $name {
            type Err = IdError;
            fn from_str(raw: &str) -> Result<Self, IdError> {
                Self::new(raw)
            }
        }

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(&self.0)
            }
        }
    };
}

id_type!(
    /// A drone's name, e.g. `alfa`.
    DroneId
);
id_type!(
    /// A swarm's name: the second level of every zenoh key, so several swarms (or test runs)
    /// share one network without seeing each other.
    SwarmId
);

/// The NATO phonetic alphabet, used to name simulated drones in order.
pub const PHONETIC: [&str; 26] = [
    "alfa", "bravo", "charlie", "delta", "echo", "foxtrot", "golf", "hotel", "india", "juliett",
    "kilo", "lima", "mike", "november", "oscar", "papa", "quebec", "romeo", "sierra", "tango",
    "uniform", "victor", "whiskey", "xray", "yankee", "zulu",
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accepts_plain_names() {
        assert!(DroneId::new("alfa").is_ok());
        assert!(DroneId::new("drone_12-b").is_ok());
        for name in PHONETIC {
            assert!(DroneId::new(name).is_ok(), "{name}");
        }
    }

    #[test]
    fn rejects_key_breaking_names() {
        for bad in [
            "",
            "Alfa",
            "a/b",
            "a*",
            "1abc",
            "a b",
            "a$",
            &"x".repeat(33),
        ] {
            assert!(DroneId::new(bad).is_err(), "{bad:?} was accepted");
        }
    }

    #[test]
    fn deserialising_validates() {
        let err = serde_json::from_str::<DroneId>("\"a/b\"");
        assert!(err.is_err());
    }
}

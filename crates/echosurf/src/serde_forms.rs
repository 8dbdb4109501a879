//! Serde forms the option structs share with the `--config` TOML: an optional number written as
//! `"auto"` when absent (TOML has no null), and unit-like enums as lower-case words.

/// `Option<f64>` as a number or `"auto"` (TOML has no null).
pub(crate) mod auto_f64 {
    use serde::{Deserialize, Deserializer, Serialize, Serializer, de::Error};

    #[derive(Serialize, Deserialize)]
    #[serde(untagged)]
    enum AutoOr {
        Value(f64),
        Word(String),
    }

    pub fn serialize<S: Serializer>(value: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
        match value {
            Some(v) => AutoOr::Value(*v),
            None => AutoOr::Word("auto".into()),
        }
        .serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
        match AutoOr::deserialize(d)? {
            AutoOr::Value(v) => Ok(Some(v)),
            AutoOr::Word(w) if w.eq_ignore_ascii_case("auto") => Ok(None),
            AutoOr::Word(w) => Err(D::Error::custom(format!(
                "expected a number or \"auto\", got \"{w}\""
            ))),
        }
    }
}

/// A unit-like enum as one of a few lower-case words.
macro_rules! word_serde {
    ($module:ident, $type:ty, [$($word:literal => $value:expr),+ $(,)?]) => {
        pub(crate) mod $module {
            use serde::{Deserialize, Deserializer, Serializer, de::Error};

            #[allow(unused_imports)]
            use super::*;

            pub fn serialize<S: Serializer>(value: &$type, s: S) -> Result<S::Ok, S::Error> {
                $(if *value == $value {
                    return s.serialize_str($word);
                })+
                unreachable!("every value has a word")
            }

            pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<$type, D::Error> {
                let word = String::deserialize(d)?;
                $(if word.eq_ignore_ascii_case($word) {
                    return Ok($value);
                })+
                Err(D::Error::custom(format!(
                    "expected one of {}, got \"{word}\"",
                    [$($word),+].join(", ")
                )))
            }
        }
    };
}

pub(crate) use word_serde;

//! Reading a Hugging Face `config.json`: one key at a time, with `transformers`' default when
//! the key is absent (or `null`), and a typed error that names the key when it is malformed.
//!
//! Why it exists: the CLIP and DINOv3 configs each had a hand-written copy of these readers
//! returning `Result<_, String>`. Real files carry many keys a model does not use, and
//! `transformers` accepts some values in two shapes (a size as `n` or `[n, n]`), so the models
//! read the keys they need through [`Section`] rather than deserialising the whole file.

use serde_json::{Map, Value};

/// What is wrong with a model's `config.json`; each names the key (dotted within a section).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum HfConfigError {
    /// The text is not JSON.
    #[error("not JSON: {0}")]
    NotJson(String),
    /// The JSON is not an object (or a section is not).
    #[error("{key} is {found}, expected an object")]
    NotAnObject {
        /// The key (`"the file"` for the root).
        key: String,
        /// The value found.
        found: String,
    },
    /// A value of the wrong type or range.
    #[error("{key} is {found}, expected {expected}")]
    Invalid {
        /// The key.
        key: String,
        /// The value found.
        found: String,
        /// What the key must hold.
        expected: &'static str,
    },
    /// A well-formed value that describes a model vlem does not run.
    #[error("{key} is {found}; {reason}")]
    Unsupported {
        /// The key.
        key: String,
        /// The value found.
        found: String,
        /// What is supported instead.
        reason: String,
    },
    /// Values that do not fit together (a width not divisible by the head count …).
    #[error("{0}")]
    Inconsistent(String),
}

/// Result of reading a config.
pub type Result<T> = std::result::Result<T, HfConfigError>;

/// A JSON object whose keys are read with defaults; `prefix` (`"text_config."`) is put before
/// each key in errors.
#[derive(Clone, Debug)]
pub struct Section {
    map: Map<String, Value>,
    prefix: String,
}

impl Section {
    /// The root object of a `config.json` text.
    ///
    /// # Errors
    /// [`HfConfigError::NotJson`], [`HfConfigError::NotAnObject`].
    pub fn parse(text: &str) -> Result<Self> {
        let root: Value =
            serde_json::from_str(text).map_err(|e| HfConfigError::NotJson(e.to_string()))?;
        match root {
            Value::Object(map) => Ok(Self {
                map,
                prefix: String::new(),
            }),
            other => Err(HfConfigError::NotAnObject {
                key: "the file".to_owned(),
                found: other.to_string(),
            }),
        }
    }

    /// The sub-object `key` (empty when absent), overridden key by key by `key_dict`, as
    /// `transformers` reads the legacy `text_config_dict` / `vision_config_dict`.
    ///
    /// # Errors
    /// [`HfConfigError::NotAnObject`] for either that is not an object.
    pub fn section(&self, key: &str) -> Result<Self> {
        let object = |key: String| -> Result<Map<String, Value>> {
            match self.map.get(&key) {
                None | Some(Value::Null) => Ok(Map::new()),
                Some(Value::Object(m)) => Ok(m.clone()),
                Some(v) => Err(HfConfigError::NotAnObject {
                    key: format!("{}{key}", self.prefix),
                    found: v.to_string(),
                }),
            }
        };
        let mut map = object(key.to_owned())?;
        map.extend(object(format!("{key}_dict"))?);
        Ok(Self {
            map,
            prefix: format!("{}{key}.", self.prefix),
        })
    }

    /// `key` with this section's prefix, as errors name it.
    pub fn name(&self, key: &str) -> String {
        format!("{}{key}", self.prefix)
    }

    /// The raw value of `key`, when present and not `null`.
    pub fn get(&self, key: &str) -> Option<&Value> {
        self.map.get(key).filter(|v| !v.is_null())
    }

    fn invalid(&self, key: &str, found: &Value, expected: &'static str) -> HfConfigError {
        HfConfigError::Invalid {
            key: self.name(key),
            found: found.to_string(),
            expected,
        }
    }

    /// A non-negative integer.
    ///
    /// # Errors
    /// [`HfConfigError::Invalid`].
    pub fn usize(&self, key: &str, default: usize) -> Result<usize> {
        match self.get(key) {
            None => Ok(default),
            Some(v) => v
                .as_u64()
                .and_then(|n| usize::try_from(n).ok())
                .ok_or_else(|| self.invalid(key, v, "a non-negative integer")),
        }
    }

    /// A finite positive number.
    ///
    /// # Errors
    /// [`HfConfigError::Invalid`].
    pub fn positive(&self, key: &str, default: f64) -> Result<f64> {
        match self.get(key) {
            None => Ok(default),
            Some(v) => v
                .as_f64()
                .filter(|x| x.is_finite() && *x > 0.0)
                .ok_or_else(|| self.invalid(key, v, "a positive number")),
        }
    }

    /// A boolean.
    ///
    /// # Errors
    /// [`HfConfigError::Invalid`].
    pub fn bool(&self, key: &str, default: bool) -> Result<bool> {
        match self.get(key) {
            None => Ok(default),
            Some(v) => v
                .as_bool()
                .ok_or_else(|| self.invalid(key, v, "true or false")),
        }
    }

    /// A string.
    ///
    /// # Errors
    /// [`HfConfigError::Invalid`].
    pub fn string(&self, key: &str, default: &str) -> Result<String> {
        match self.get(key) {
            None => Ok(default.to_owned()),
            Some(Value::String(s)) => Ok(s.clone()),
            Some(v) => Err(self.invalid(key, v, "a string")),
        }
    }

    /// An integer id.
    ///
    /// # Errors
    /// [`HfConfigError::Invalid`].
    pub fn integer(&self, key: &str, default: i64) -> Result<i64> {
        match self.get(key) {
            None => Ok(default),
            Some(v) => v
                .as_i64()
                .ok_or_else(|| self.invalid(key, v, "one integer")),
        }
    }

    /// A size `transformers` accepts as an integer or a `[height, width]` pair; only square
    /// sizes are supported.
    ///
    /// # Errors
    /// [`HfConfigError::Invalid`], and [`HfConfigError::Unsupported`] for a pair of two sides.
    pub fn square(&self, key: &str, default: usize) -> Result<usize> {
        let side = |v: &Value| v.as_u64().and_then(|n| usize::try_from(n).ok());
        match self.get(key) {
            None => Ok(default),
            Some(Value::Array(pair)) => match pair.iter().map(side).collect::<Option<Vec<_>>>() {
                Some(sides) if sides.len() == 2 && sides[0] == sides[1] => Ok(sides[0]),
                Some(sides) if sides.len() == 2 => Err(HfConfigError::Unsupported {
                    key: self.name(key),
                    found: format!("{sides:?}"),
                    reason: "only square sizes are supported".to_owned(),
                }),
                _ => Err(self.invalid(
                    key,
                    &Value::Array(pair.clone()),
                    "an integer or a square [n, n] pair",
                )),
            },
            Some(v) => side(v).ok_or_else(|| self.invalid(key, v, "an integer")),
        }
    }

    /// `model_type`, when present, must be `expected`; `reason` says what the model reads.
    ///
    /// # Errors
    /// [`HfConfigError::Unsupported`].
    pub fn expect_model_type(&self, expected: &str, reason: &str) -> Result<()> {
        match self.get("model_type").and_then(Value::as_str) {
            Some(kind) if kind != expected => Err(HfConfigError::Unsupported {
                key: self.name("model_type"),
                found: format!("{kind:?}"),
                reason: reason.to_owned(),
            }),
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    #[test]
    fn absent_and_null_keys_take_the_default_and_bad_ones_are_named() {
        let root =
            Section::parse(r#"{"a": null, "b": -1, "s": {"c": [3, 4]}, "s_dict": {"d": 2}}"#)
                .unwrap();
        assert_eq!(root.usize("a", 7).unwrap(), 7);
        assert_eq!(root.usize("missing", 7).unwrap(), 7);
        assert_eq!(
            root.usize("b", 7).unwrap_err().to_string(),
            "b is -1, expected a non-negative integer"
        );
        let s = root.section("s").unwrap();
        assert_eq!(s.usize("d", 0).unwrap(), 2);
        assert_eq!(
            s.square("c", 0).unwrap_err().to_string(),
            "s.c is [3, 4]; only square sizes are supported"
        );
        assert!(matches!(
            Section::parse("[1]"),
            Err(HfConfigError::NotAnObject { .. })
        ));
        assert!(matches!(
            Section::parse("{"),
            Err(HfConfigError::NotJson(_))
        ));
    }
}

//! A bounded cache of text embeddings, so that asking the same text again costs a lookup.
//!
//! Why it exists: an encoder with prompt ensembling embeds a query in every template (NARADIO
//! and RayFronts: 80 templates, i.e. 80 passes of the text tower per query), and a robot asks the
//! same few texts over and over (a live map re-queried every second, a study's label set per
//! scene). The cache keeps the most recently used texts, a bounded number of them, so memory stays
//! small (1,024 texts × 1,152 f32 ≈ 4.7 MB) however many different texts arrive.

use std::collections::VecDeque;
use std::sync::{Mutex, PoisonError};

/// The most recently used text embeddings, at most `capacity` of them.
#[derive(Debug)]
pub struct TextEmbeddingCache {
    capacity: usize,
    /// Least recently used first.
    entries: Mutex<VecDeque<(String, Vec<f32>)>>,
}

impl TextEmbeddingCache {
    /// Texts kept by [`TextEmbeddingCache::default`].
    pub const DEFAULT_CAPACITY: usize = 1024;

    /// A cache of at most `capacity` texts (0: nothing is kept).
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity,
            entries: Mutex::new(VecDeque::new()),
        }
    }

    /// The embedding of `text`: the cached one, or `embed(text)` remembered when it succeeds.
    /// The lock is not held while embedding, so two threads asking for the same new text may both
    /// embed it; the result is the same.
    ///
    /// # Errors
    /// Those of `embed`.
    pub fn get_or_embed<E>(
        &self,
        text: &str,
        embed: impl FnOnce(&str) -> Result<Vec<f32>, E>,
    ) -> Result<Vec<f32>, E> {
        if let Some(hit) = self.get(text) {
            return Ok(hit);
        }
        let embedding = embed(text)?;
        self.insert(text, &embedding);
        Ok(embedding)
    }

    /// The cached embedding of `text`, marked as just used.
    pub fn get(&self, text: &str) -> Option<Vec<f32>> {
        // A panic elsewhere while holding the lock leaves whole entries: still usable.
        let mut entries = self.entries.lock().unwrap_or_else(PoisonError::into_inner);
        let at = entries.iter().position(|(t, _)| t == text)?;
        let entry = entries.remove(at)?;
        let embedding = entry.1.clone();
        entries.push_back(entry);
        Some(embedding)
    }

    /// Remembers `embedding` for `text`, dropping the least recently used text when full.
    pub fn insert(&self, text: &str, embedding: &[f32]) {
        if self.capacity == 0 {
            return;
        }
        let mut entries = self.entries.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(at) = entries.iter().position(|(t, _)| t == text) {
            entries.remove(at);
        }
        while entries.len() >= self.capacity {
            entries.pop_front();
        }
        entries.push_back((text.to_owned(), embedding.to_vec()));
    }

    /// How many texts are cached.
    pub fn len(&self) -> usize {
        self.entries
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .len()
    }

    /// Whether nothing is cached.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl Default for TextEmbeddingCache {
    fn default() -> Self {
        Self::new(Self::DEFAULT_CAPACITY)
    }
}

#[cfg(test)]
mod tests {
    use std::cell::Cell;

    use super::*;

    #[test]
    fn a_text_is_embedded_once_and_the_least_recently_used_goes_first() {
        let cache = TextEmbeddingCache::new(2);
        let calls = Cell::new(0);
        let embed = |t: &str| -> Result<Vec<f32>, ()> {
            calls.set(calls.get() + 1);
            Ok(vec![t.len() as f32])
        };
        assert_eq!(cache.get_or_embed("chair", embed), Ok(vec![5.0]));
        assert_eq!(cache.get_or_embed("chair", embed), Ok(vec![5.0]));
        assert_eq!(calls.get(), 1);
        cache.get_or_embed("sofa", embed).unwrap_or_default();
        // "chair" used last: "sofa" is the least recently used and goes when "lamp" comes.
        cache.get_or_embed("chair", embed).unwrap_or_default();
        cache.get_or_embed("lamp", embed).unwrap_or_default();
        assert_eq!(cache.len(), 2);
        assert!(cache.get("sofa").is_none());
        assert_eq!(cache.get("chair"), Some(vec![5.0]));
        assert_eq!(calls.get(), 3);
    }

    #[test]
    fn failures_are_not_cached_and_capacity_zero_keeps_nothing() {
        let cache = TextEmbeddingCache::new(4);
        assert_eq!(
            cache.get_or_embed("x", |_| Err::<Vec<f32>, _>("no")),
            Err("no")
        );
        assert!(cache.is_empty());
        let none = TextEmbeddingCache::new(0);
        assert_eq!(
            none.get_or_embed("x", |_| Ok::<_, ()>(vec![1.0])),
            Ok(vec![1.0])
        );
        assert!(none.is_empty());
    }
}

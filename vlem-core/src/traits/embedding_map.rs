//! `EmbeddingMap`: the 3D map of points (or voxels, or segments) with embeddings.
//!
//! Why it exists: comparing map representations is one of vlem's reasons to exist (the paper's
//! point cloud against RayFronts' voxels and Open-Fusion's segments). A map owns its storage, its
//! fusion rule and its memory budget; it answers queries and exports a [`MapSnapshot`] that the map
//! file stores, so `vlem query` works the same on every map.

use crate::embeddings::PixelEmbeddings;
use crate::error::{CoreError, Result};
use crate::mapfile::MapSnapshot;
use crate::types::{ColouredMesh, Frame, Pose};

/// One tracked frame and its embeddings, ready to integrate.
#[derive(Clone, Copy, Debug)]
pub struct Observation<'a> {
    /// The RGB-D frame.
    pub frame: &'a Frame,
    /// Camera-to-world pose from the tracker.
    pub pose: &'a Pose,
    /// Pixel embeddings, `None` for a geometry-only pipeline.
    pub embeddings: Option<&'a PixelEmbeddings>,
}

/// What one integration did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct IntegrationStats {
    /// Points (pixels) of the frame that were used.
    pub observed: usize,
    /// Map elements whose embedding was fused with an observation.
    pub fused: usize,
    /// Map elements added.
    pub inserted: usize,
    /// Map elements removed by budget enforcement.
    pub removed: usize,
}

/// The cap on a map's element count, and the `[map]` parameter that sets it.
///
/// A caller that holds a map to its budget (`vlem soak`, memory reports) asks the map for it
/// instead of knowing which parameter each map kind reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MapBudget {
    /// The `[map]` parameter that sets the budget (`max_points`, `max_voxels`, ...).
    pub parameter: &'static str,
    /// The most elements ([`EmbeddingMap::len`]) the map holds after an integration.
    pub elements: usize,
}

/// A map of 3D elements that carry embeddings, integrated frame by frame.
pub trait EmbeddingMap: Send + Sync {
    /// The registered name.
    fn name(&self) -> &'static str;

    /// Embedding dimension (0 for a geometry-only map).
    fn dim(&self) -> usize;

    /// Integrates one observation.
    ///
    /// # Errors
    /// Inconsistent inputs (e.g. embeddings of another dimension or image size).
    fn integrate(&mut self, observation: &Observation<'_>) -> Result<IntegrationStats>;

    /// Number of elements (points, voxels, ...).
    fn len(&self) -> usize;

    /// Whether the map is empty.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Host bytes of map storage (positions, colours, embeddings and indices), for memory
    /// reports; what the map keeps on a device is [`EmbeddingMap::device_memory_bytes`].
    fn memory_bytes(&self) -> usize;

    /// Device bytes the map has allocated (its embedding table with `[map] device = "cuda"`); 0
    /// (the default) for a map that keeps everything in host memory.
    fn device_memory_bytes(&self) -> usize {
        0
    }

    /// The map's element budget, `None` (the default) for a map without one.
    fn budget(&self) -> Option<MapBudget> {
        None
    }

    /// The normalised cosine similarity `(e_text . e + 1) / 2` of every element, into `out`
    /// (resized to [`EmbeddingMap::len`]), in the order of [`EmbeddingMap::snapshot`].
    ///
    /// # Errors
    /// [`CoreError::DimensionMismatch`] when `text` has the wrong length.
    fn similarity(&self, text: &[f32], out: &mut Vec<f32>) -> Result<()>;

    /// [`EmbeddingMap::similarity`] for several texts at once: `out[t]` for `texts[t]` (`out` is
    /// resized to `texts.len()`). Maps whose embeddings sit in one table override it with one
    /// pass over the table for all texts, which is what bounds how long a query holds the live
    /// map's read lock; the default scores one text after another.
    ///
    /// # Errors
    /// As [`EmbeddingMap::similarity`].
    fn similarity_many(&self, texts: &[&[f32]], out: &mut Vec<Vec<f32>>) -> Result<()> {
        out.resize_with(texts.len(), Vec::new);
        for (text, scores) in texts.iter().zip(out.iter_mut()) {
            self.similarity(text, scores)?;
        }
        Ok(())
    }

    /// Every element as point, colour and embedding, for saving and querying.
    ///
    /// # Errors
    /// A map whose embeddings live on a device fails when copying them to the host fails.
    fn snapshot(&self) -> Result<MapSnapshot>;

    /// Every element's position and colour, without embeddings: what a viewer draws while the
    /// map grows. The default takes them from [`EmbeddingMap::snapshot`]; maps override it to
    /// skip copying the embeddings.
    /// A snapshot that fails draws nothing this time (the viewer asks again at the next frame;
    /// saves report the error themselves).
    fn coloured_points(&self) -> ColouredMesh {
        match self.snapshot() {
            Ok(snapshot) => ColouredMesh {
                vertices: snapshot.positions,
                colours: snapshot.colours,
                triangles: Vec::new(),
            },
            Err(_) => ColouredMesh::default(),
        }
    }

    /// Replaces the map content with a saved snapshot (continue mapping from a file).
    ///
    /// # Errors
    /// [`CoreError::Unsupported`] by default; mismatched snapshots otherwise.
    fn restore(&mut self, snapshot: MapSnapshot) -> Result<()> {
        let _ = snapshot;
        Err(CoreError::Unsupported {
            implementation: format!("map `{}`", self.name()),
            capability: "restoring from a snapshot",
        })
    }
}

//! Pixel-aligned embeddings without a dense `w x h x d` tensor.
//!
//! A dense 640x480x512 f32 tensor is 600 MB per frame, so no encoder produces one. Encoders hand back
//! embeddings in the layout they compute them in:
//! - [`EmbeddingLayout::Segments`]: a per-pixel segment index and a table of one unit-norm embedding
//!   per segment (segment encoders such as CLIP on SAM masks). Pixels in no segment have no embedding.
//! - [`EmbeddingLayout::PatchGrid`]: a low-resolution grid of patch embeddings (ViT patch encoders),
//!   bilinearly upsampled and L2-normalised only at the pixels that are looked up.
//!
//! [`PixelEmbeddings::embedding_at`] is the one lookup both layouts share.

use crate::error::{CoreError, Result};

/// Marks a pixel that belongs to no segment.
pub const NO_SEGMENT: u32 = u32::MAX;

/// How the embeddings of a frame are stored.
#[derive(Clone, Debug, PartialEq)]
pub enum EmbeddingLayout {
    /// One segment index per pixel (row-major, [`NO_SEGMENT`] for none) and a `segments x dim` table.
    Segments {
        /// Per-pixel segment index.
        index: Vec<u32>,
        /// Row-major table, one unit-norm row per segment.
        table: Vec<f32>,
    },
    /// A `grid_width x grid_height` grid of patch embeddings covering the whole image.
    PatchGrid {
        /// Patches per row.
        grid_width: u32,
        /// Patch rows.
        grid_height: u32,
        /// Row-major `grid_height x grid_width x dim` values.
        data: Vec<f32>,
    },
}

/// The embeddings of one image, in either layout.
#[derive(Clone, Debug, PartialEq)]
pub struct PixelEmbeddings {
    width: u32,
    height: u32,
    dim: usize,
    layout: EmbeddingLayout,
}

impl PixelEmbeddings {
    /// Segment layout. Table rows are L2-normalised here; a zero row is an error.
    ///
    /// # Errors
    /// [`CoreError::InvalidEmbeddings`] for inconsistent lengths, out-of-range indices, zero or
    /// non-finite rows.
    pub fn from_segments(
        width: u32,
        height: u32,
        dim: usize,
        index: Vec<u32>,
        mut table: Vec<f32>,
    ) -> Result<Self> {
        let fail = |reason: String| Err(CoreError::InvalidEmbeddings { reason });
        if dim == 0 {
            return fail("embedding dimension is 0".into());
        }
        if index.len() != width as usize * height as usize {
            return fail(format!(
                "segment index has {} entries for a {width}x{height} image",
                index.len()
            ));
        }
        if !table.len().is_multiple_of(dim) {
            return fail(format!(
                "segment table length {} is not a multiple of dim {dim}",
                table.len()
            ));
        }
        let segments = table.len() / dim;
        if let Some(bad) = index
            .iter()
            .find(|&&s| s != NO_SEGMENT && s as usize >= segments)
        {
            return fail(format!(
                "segment index {bad} but the table has {segments} rows"
            ));
        }
        for (row_index, row) in table.chunks_exact_mut(dim).enumerate() {
            if !normalise(row) {
                return fail(format!(
                    "segment {row_index} has a zero or non-finite embedding"
                ));
            }
        }
        Ok(Self {
            width,
            height,
            dim,
            layout: EmbeddingLayout::Segments { index, table },
        })
    }

    /// Patch-grid layout. Values are kept as given; lookups normalise after interpolation.
    ///
    /// # Errors
    /// [`CoreError::InvalidEmbeddings`] for an empty grid, a length mismatch or non-finite values.
    pub fn from_patch_grid(
        width: u32,
        height: u32,
        dim: usize,
        grid_width: u32,
        grid_height: u32,
        data: Vec<f32>,
    ) -> Result<Self> {
        let fail = |reason: String| Err(CoreError::InvalidEmbeddings { reason });
        if dim == 0 || grid_width == 0 || grid_height == 0 || width == 0 || height == 0 {
            return fail(format!(
                "empty patch grid ({grid_width}x{grid_height}, dim {dim}) or image ({width}x{height})"
            ));
        }
        let expected = grid_width as usize * grid_height as usize * dim;
        if data.len() != expected {
            return fail(format!(
                "patch grid {grid_width}x{grid_height}x{dim} needs {expected} values, got {}",
                data.len()
            ));
        }
        if data.iter().any(|x| !x.is_finite()) {
            return fail("patch grid holds non-finite values".into());
        }
        Ok(Self {
            width,
            height,
            dim,
            layout: EmbeddingLayout::PatchGrid {
                grid_width,
                grid_height,
                data,
            },
        })
    }

    /// Image width the embeddings cover.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height the embeddings cover.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Embedding dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The storage layout.
    pub fn layout(&self) -> &EmbeddingLayout {
        &self.layout
    }

    /// Bytes held by this value (for memory reports).
    pub fn memory_bytes(&self) -> usize {
        match &self.layout {
            EmbeddingLayout::Segments { index, table } => index.len() * 4 + table.len() * 4,
            EmbeddingLayout::PatchGrid { data, .. } => data.len() * 4,
        }
    }

    /// Whether pixel `(u, v)` has an embedding at all.
    pub fn has_embedding(&self, u: u32, v: u32) -> bool {
        if u >= self.width || v >= self.height {
            return false;
        }
        match &self.layout {
            EmbeddingLayout::Segments { index, .. } => {
                index[v as usize * self.width as usize + u as usize] != NO_SEGMENT
            }
            EmbeddingLayout::PatchGrid { .. } => true,
        }
    }

    /// The stored unit-norm row of pixel `(u, v)` in the segment layout, without copying.
    /// `None` in the patch layout, for pixels in no segment, and outside the image.
    #[inline]
    pub fn segment_row(&self, u: u32, v: u32) -> Option<&[f32]> {
        if u >= self.width || v >= self.height {
            return None;
        }
        match &self.layout {
            EmbeddingLayout::Segments { index, table } => {
                let s = index[v as usize * self.width as usize + u as usize];
                (s != NO_SEGMENT)
                    .then(|| &table[s as usize * self.dim..(s as usize + 1) * self.dim])
            }
            EmbeddingLayout::PatchGrid { .. } => None,
        }
    }

    /// Writes the unit-norm embedding of pixel `(u, v)` into `out` (length `dim`).
    ///
    /// Returns false, leaving `out` unspecified, for pixels without an embedding. In the patch
    /// layout the grid is sampled bilinearly at the pixel centre (patch centres at
    /// `(i + 0.5) * width / grid_width`, clamped at the borders) and then normalised.
    pub fn embedding_at(&self, u: u32, v: u32, out: &mut [f32]) -> bool {
        if out.len() != self.dim || u >= self.width || v >= self.height {
            return false;
        }
        match &self.layout {
            EmbeddingLayout::Segments { .. } => match self.segment_row(u, v) {
                Some(row) => {
                    out.copy_from_slice(row);
                    true
                }
                None => false,
            },
            EmbeddingLayout::PatchGrid {
                grid_width,
                grid_height,
                data,
            } => {
                let (gw, gh) = (*grid_width as usize, *grid_height as usize);
                let sample = |pixel: u32, size: u32, cells: usize| -> (usize, usize, f32) {
                    let x = (pixel as f32 + 0.5) * cells as f32 / size as f32 - 0.5;
                    let x = x.clamp(0.0, (cells - 1) as f32);
                    let i0 = x.floor() as usize;
                    let i1 = (i0 + 1).min(cells - 1);
                    (i0, i1, x - i0 as f32)
                };
                let (x0, x1, fx) = sample(u, self.width, gw);
                let (y0, y1, fy) = sample(v, self.height, gh);
                let d = self.dim;
                let cell = |x: usize, y: usize| &data[(y * gw + x) * d..(y * gw + x + 1) * d];
                let (a, b, c, e) = (cell(x0, y0), cell(x1, y0), cell(x0, y1), cell(x1, y1));
                let (wa, wb) = ((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy));
                let (wc, we) = ((1.0 - fx) * fy, fx * fy);
                for k in 0..d {
                    out[k] = wa * a[k] + wb * b[k] + wc * c[k] + we * e[k];
                }
                normalise(out)
            }
        }
    }
}

/// L2-normalises `v` in place; returns false (leaving `v` unchanged) for a zero or non-finite vector.
pub fn normalise(v: &mut [f32]) -> bool {
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if !(norm.is_finite() && norm > 0.0) {
        return false;
    }
    let inv = 1.0 / norm;
    v.iter_mut().for_each(|x| *x *= inv);
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segments_look_up_normalised_rows_and_skip_unsegmented_pixels() {
        let index = vec![0, 1, NO_SEGMENT, 1];
        let e = PixelEmbeddings::from_segments(2, 2, 2, index, vec![3.0, 4.0, 0.0, 2.0]).unwrap();
        let mut out = [0.0; 2];
        assert!(e.embedding_at(0, 0, &mut out));
        assert_eq!(out, [0.6, 0.8]);
        assert!(e.embedding_at(1, 1, &mut out));
        assert_eq!(out, [0.0, 1.0]);
        assert!(!e.embedding_at(0, 1, &mut out));
        assert!(!e.has_embedding(0, 1));
        assert_eq!(e.segment_row(1, 0), Some(&[0.0, 1.0][..]));
    }

    #[test]
    fn segments_reject_bad_tables() {
        let err = PixelEmbeddings::from_segments(2, 1, 2, vec![0, 2], vec![1.0, 0.0]).unwrap_err();
        assert!(
            err.to_string()
                .contains("segment index 2 but the table has 1 rows"),
            "{err}"
        );
        let err = PixelEmbeddings::from_segments(2, 1, 2, vec![0, 0], vec![0.0, 0.0]).unwrap_err();
        assert!(err.to_string().contains("zero or non-finite"), "{err}");
        let err = PixelEmbeddings::from_segments(3, 1, 2, vec![0, 0], vec![1.0, 0.0]).unwrap_err();
        assert!(
            err.to_string().contains("2 entries for a 3x1 image"),
            "{err}"
        );
    }

    #[test]
    fn patch_grid_interpolates_between_patch_centres() {
        // 2x1 grid over a 4x1 image: patch centres at x = 1.0 and 3.0 (pixel centres 0.5..3.5).
        let data = vec![1.0, 0.0, 0.0, 1.0];
        let e = PixelEmbeddings::from_patch_grid(4, 1, 2, 2, 1, data).unwrap();
        let mut out = [0.0; 2];
        // Pixel 0 is left of the first centre: clamped to the first patch.
        assert!(e.embedding_at(0, 0, &mut out));
        assert_eq!(out, [1.0, 0.0]);
        // Pixel 1 (centre 1.5) is a quarter of the way: (0.75, 0.25), normalised.
        assert!(e.embedding_at(1, 0, &mut out));
        let n = (0.75f32 * 0.75 + 0.25 * 0.25).sqrt();
        assert!((out[0] - 0.75 / n).abs() < 1e-6 && (out[1] - 0.25 / n).abs() < 1e-6);
        assert!(e.embedding_at(3, 0, &mut out));
        assert_eq!(out, [0.0, 1.0]);
        assert!(!e.embedding_at(4, 0, &mut out));
    }

    #[test]
    fn patch_grid_rejects_wrong_length_and_nan() {
        assert!(PixelEmbeddings::from_patch_grid(4, 4, 2, 2, 2, vec![0.0; 7]).is_err());
        let err = PixelEmbeddings::from_patch_grid(4, 4, 1, 1, 1, vec![f32::NAN]).unwrap_err();
        assert!(err.to_string().contains("non-finite"), "{err}");
    }
}

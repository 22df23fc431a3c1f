//! Pixel-aligned embeddings without a dense `w x h x d` tensor.
//!
//! A dense 640x480x512 f32 tensor is 600 MB per frame, so no encoder produces one. Encoders hand back
//! embeddings in the layout they compute them in:
//! - [`EmbeddingLayout::Regions`]: a per-pixel region index and a table of one unit-norm embedding
//!   per region (region encoders such as CLIP on SAM masks). Pixels in no region have no embedding.
//! - [`EmbeddingLayout::PatchGrid`]: a low-resolution grid of patch embeddings (ViT patch encoders),
//!   bilinearly upsampled and L2-normalised only at the pixels that are looked up.
//!
//! [`PixelEmbeddings::embedding_at`] is the one lookup both layouts share.

use crate::error::{CoreError, Result};

/// Marks a pixel that belongs to no region.
pub const NO_REGION: u32 = u32::MAX;

/// How the embeddings of a frame are stored.
#[derive(Clone, Debug, PartialEq)]
pub enum EmbeddingLayout {
    /// One region index per pixel (row-major, [`NO_REGION`] for none) and a `regions x dim` table.
    Regions {
        /// Per-pixel region index.
        index: Vec<u32>,
        /// Row-major table, one unit-norm row per region.
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
    /// Region layout. Table rows are L2-normalised here; a zero row is an error.
    ///
    /// # Errors
    /// [`CoreError::InvalidEmbeddings`] for inconsistent lengths, out-of-range indices, zero or
    /// non-finite rows.
    pub fn from_regions(
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
                "region index has {} entries for a {width}x{height} image",
                index.len()
            ));
        }
        if !table.len().is_multiple_of(dim) {
            return fail(format!(
                "region table length {} is not a multiple of dim {dim}",
                table.len()
            ));
        }
        let regions = table.len() / dim;
        if let Some(bad) = index
            .iter()
            .find(|&&s| s != NO_REGION && s as usize >= regions)
        {
            return fail(format!(
                "region index {bad} but the table has {regions} rows"
            ));
        }
        for (row_index, row) in table.chunks_exact_mut(dim).enumerate() {
            if !normalise(row) {
                return fail(format!(
                    "region {row_index} has a zero or non-finite embedding"
                ));
            }
        }
        Ok(Self {
            width,
            height,
            dim,
            layout: EmbeddingLayout::Regions { index, table },
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
            EmbeddingLayout::Regions { index, table } => index.len() * 4 + table.len() * 4,
            EmbeddingLayout::PatchGrid { data, .. } => data.len() * 4,
        }
    }

    /// Whether pixel `(u, v)` has an embedding at all.
    pub fn has_embedding(&self, u: u32, v: u32) -> bool {
        if u >= self.width || v >= self.height {
            return false;
        }
        match &self.layout {
            EmbeddingLayout::Regions { index, .. } => {
                index[v as usize * self.width as usize + u as usize] != NO_REGION
            }
            EmbeddingLayout::PatchGrid { .. } => true,
        }
    }

    /// The stored unit-norm row of pixel `(u, v)` in the region layout, without copying.
    /// `None` in the patch layout, for pixels in no region, and outside the image.
    #[inline]
    pub fn region_row(&self, u: u32, v: u32) -> Option<&[f32]> {
        if u >= self.width || v >= self.height {
            return None;
        }
        match &self.layout {
            EmbeddingLayout::Regions { index, table } => {
                let s = index[v as usize * self.width as usize + u as usize];
                (s != NO_REGION).then(|| &table[s as usize * self.dim..(s as usize + 1) * self.dim])
            }
            EmbeddingLayout::PatchGrid { .. } => None,
        }
    }

    /// [`PixelEmbeddings::region_row`] by the linear pixel index `v * width + u`, for loops
    /// that already hold it (no division per pixel).
    #[inline]
    pub fn region_row_at_index(&self, index: usize) -> Option<&[f32]> {
        match &self.layout {
            EmbeddingLayout::Regions {
                index: regions,
                table,
            } => {
                let s = *regions.get(index)?;
                (s != NO_REGION).then(|| &table[s as usize * self.dim..(s as usize + 1) * self.dim])
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
            EmbeddingLayout::Regions { .. } => match self.region_row(u, v) {
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

/// A patch grid's per-pixel embeddings as combinations of grid rows, so that a map adding up many
/// pixels' unit embeddings adds per pixel four weights instead of `dim`-long vectors, and the rows
/// once at the end.
///
/// Why: [`PixelEmbeddings::embedding_at`] interpolates and normalises a `dim`-long vector per pixel
/// (about 3·dim operations), which is most of a map's integration time on patch-encoder output. The
/// interpolated embedding is `Σ w_c g_c` over the (at most four) grid rows `g_c` around the pixel,
/// and its norm follows from the rows' dot products, computed once per grid: so the unit embedding
/// is `Σ (w_c / ‖Σ w g‖) g_c`, the same vector up to rounding.
#[derive(Debug)]
pub struct PatchSampler<'a> {
    data: &'a [f32],
    dim: usize,
    width: u32,
    height: u32,
    grid_width: usize,
    grid_height: usize,
    /// Per grid cell `c` (row-major): `g_c·g_c`, `g_c·g_right`, `g_c·g_down`, `g_c·g_down_right`
    /// and `g_right·g_down` (0 where a neighbour is outside the grid).
    dots: Vec<[f64; 5]>,
}

impl<'a> PatchSampler<'a> {
    fn new(e: &'a PixelEmbeddings) -> Option<Self> {
        let EmbeddingLayout::PatchGrid {
            grid_width,
            grid_height,
            data,
        } = &e.layout
        else {
            return None;
        };
        let (gw, gh, d) = (*grid_width as usize, *grid_height as usize, e.dim);
        let row = |x: usize, y: usize| &data[(y * gw + x) * d..(y * gw + x + 1) * d];
        let dot = |a: &[f32], b: &[f32]| -> f64 {
            a.iter()
                .zip(b)
                .map(|(x, y)| f64::from(*x) * f64::from(*y))
                .sum()
        };
        let mut dots = Vec::with_capacity(gw * gh);
        for y in 0..gh {
            for x in 0..gw {
                let c = row(x, y);
                let (right, down) = (x + 1 < gw, y + 1 < gh);
                dots.push([
                    dot(c, c),
                    if right { dot(c, row(x + 1, y)) } else { 0.0 },
                    if down { dot(c, row(x, y + 1)) } else { 0.0 },
                    if right && down {
                        dot(c, row(x + 1, y + 1))
                    } else {
                        0.0
                    },
                    if right && down {
                        dot(row(x + 1, y), row(x, y + 1))
                    } else {
                        0.0
                    },
                ]);
            }
        }
        Some(Self {
            data,
            dim: d,
            width: e.width,
            height: e.height,
            grid_width: gw,
            grid_height: gh,
            dots,
        })
    }

    /// The grid row of cell `cell` (as [`PatchSampler::weights`] names it).
    pub fn row(&self, cell: u32) -> &'a [f32] {
        let c = cell as usize;
        &self.data[c * self.dim..(c + 1) * self.dim]
    }

    /// Pixel `(u, v)`'s unit embedding as up to four `(cell, weight)` pairs (unused pairs have
    /// weight 0), sampled as [`PixelEmbeddings::embedding_at`] samples; `None` where that has no
    /// embedding (outside the image, or a zero or non-finite interpolation).
    pub fn weights(&self, u: u32, v: u32) -> Option<[(u32, f32); 4]> {
        if u >= self.width || v >= self.height {
            return None;
        }
        let sample = |pixel: u32, size: u32, cells: usize| -> (usize, bool, f32) {
            let x = (pixel as f32 + 0.5) * cells as f32 / size as f32 - 0.5;
            let x = x.clamp(0.0, (cells - 1) as f32);
            let i0 = x.floor() as usize;
            // At the last cell the second sample is the first again.
            (i0, i0 + 1 < cells, x - i0 as f32)
        };
        let (x0, has_x1, fx) = sample(u, self.width, self.grid_width);
        let (y0, has_y1, fy) = sample(v, self.height, self.grid_height);
        // Weights of the block's four cells; a missing neighbour's weight goes to the cell it
        // repeats, as the clamped lookup does.
        let (mut wa, mut wb) = ((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy));
        let (mut wc, mut we) = ((1.0 - fx) * fy, fx * fy);
        if !has_x1 {
            wa += wb;
            wc += we;
            wb = 0.0;
            we = 0.0;
        }
        if !has_y1 {
            wa += wc;
            wb += we;
            wc = 0.0;
            we = 0.0;
        }
        let a = y0 * self.grid_width + x0;
        let dots = |c: usize| self.dots[c];
        let da = dots(a);
        let (a2, b2, c2, e2) = (f64::from(wa), f64::from(wb), f64::from(wc), f64::from(we));
        let mut norm2 = a2 * a2 * da[0];
        if has_x1 {
            let db = dots(a + 1);
            norm2 += b2 * b2 * db[0] + 2.0 * a2 * b2 * da[1];
        }
        if has_y1 {
            let dc = dots(a + self.grid_width);
            norm2 += c2 * c2 * dc[0] + 2.0 * a2 * c2 * da[2];
            if has_x1 {
                let db = dots(a + 1);
                let de = dots(a + self.grid_width + 1);
                norm2 += e2 * e2 * de[0]
                    + 2.0 * (a2 * e2 * da[3] + b2 * c2 * da[4] + b2 * e2 * db[2] + c2 * e2 * dc[1]);
            }
        }
        if !(norm2.is_finite() && norm2 > 0.0) {
            return None;
        }
        let inv = (1.0 / norm2.sqrt()) as f32;
        let (right, down) = (
            u32::from(has_x1),
            if has_y1 { self.grid_width as u32 } else { 0 },
        );
        let a = a as u32;
        Some([
            (a, wa * inv),
            (a + right, wb * inv),
            (a + down, wc * inv),
            (a + down + right, we * inv),
        ])
    }
}

impl PixelEmbeddings {
    /// The patch sampler of a patch-grid layout (`None` for regions).
    pub fn patch_sampler(&self) -> Option<PatchSampler<'_>> {
        PatchSampler::new(self)
    }
}

/// L2-normalises `v` in place; returns false (leaving `v` unchanged) for a zero or non-finite vector.
pub fn normalise(v: &mut [f32]) -> bool {
    // `dot`'s independent accumulators: a plain `sum` is one chain of dependent additions, which
    // made renormalising a 512-d row the largest cost of the point-cloud map's fusion.
    let norm = crate::query::dot(v, v).sqrt();
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
    fn the_patch_sampler_gives_the_interpolated_unit_embeddings() {
        // A 5x3 grid of 7-d rows over a 37x23 image (uneven, so samples fall everywhere,
        // borders included), one row zero.
        let (gw, gh, dim) = (5u32, 3u32, 7usize);
        let mut data: Vec<f32> = (0..(gw * gh) as usize * dim)
            .map(|i| ((i * 7919 % 113) as f32 / 56.0) - 1.0)
            .collect();
        data[..dim].iter_mut().for_each(|x| *x = 0.0);
        let e = PixelEmbeddings::from_patch_grid(37, 23, dim, gw, gh, data).unwrap();
        let sampler = e.patch_sampler().unwrap();
        let (mut direct, mut combined) = (vec![0.0; dim], vec![0.0; dim]);
        for v in 0..23 {
            for u in 0..37 {
                let expected = e.embedding_at(u, v, &mut direct);
                let weights = sampler.weights(u, v);
                assert_eq!(weights.is_some(), expected, "pixel ({u}, {v})");
                let Some(weights) = weights else { continue };
                combined.iter_mut().for_each(|x| *x = 0.0);
                for (cell, w) in weights {
                    for (c, r) in combined.iter_mut().zip(sampler.row(cell)) {
                        *c += w * r;
                    }
                }
                for (a, b) in combined.iter().zip(&direct) {
                    assert!((a - b).abs() < 1e-5, "pixel ({u}, {v}): {a} against {b}");
                }
            }
        }
        assert!(sampler.weights(37, 0).is_none());
        let regions = PixelEmbeddings::from_regions(1, 1, 1, vec![0], vec![1.0]).unwrap();
        assert!(regions.patch_sampler().is_none());
    }

    #[test]
    fn regions_look_up_normalised_rows_and_skip_pixels_in_no_region() {
        let index = vec![0, 1, NO_REGION, 1];
        let e = PixelEmbeddings::from_regions(2, 2, 2, index, vec![3.0, 4.0, 0.0, 2.0]).unwrap();
        let mut out = [0.0; 2];
        assert!(e.embedding_at(0, 0, &mut out));
        assert_eq!(out, [0.6, 0.8]);
        assert!(e.embedding_at(1, 1, &mut out));
        assert_eq!(out, [0.0, 1.0]);
        assert!(!e.embedding_at(0, 1, &mut out));
        assert!(!e.has_embedding(0, 1));
        assert_eq!(e.region_row(1, 0), Some(&[0.0, 1.0][..]));
    }

    #[test]
    fn region_tables_are_checked() {
        let err = PixelEmbeddings::from_regions(2, 1, 2, vec![0, 2], vec![1.0, 0.0]).unwrap_err();
        assert!(
            err.to_string()
                .contains("region index 2 but the table has 1 rows"),
            "{err}"
        );
        let err = PixelEmbeddings::from_regions(2, 1, 2, vec![0, 0], vec![0.0, 0.0]).unwrap_err();
        assert!(err.to_string().contains("zero or non-finite"), "{err}");
        let err = PixelEmbeddings::from_regions(3, 1, 2, vec![0, 0], vec![1.0, 0.0]).unwrap_err();
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

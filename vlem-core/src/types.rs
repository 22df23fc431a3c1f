//! Plain data that flows through the pipeline: images, intrinsics, poses, frames, regions.
//!
//! Conventions (the same everywhere in vlem):
//! - images are row-major, origin top-left, `u` = column, `v` = row;
//! - depth is in metres; a depth of 0, a negative value or a non-finite value means "no measurement"
//!   and is never back-projected;
//! - a [`Pose`] maps camera coordinates to world (map) coordinates (camera-to-world), with the camera
//!   looking along +z, x to the right and y down (the OpenCV / Open3D convention).

use nalgebra::{Isometry3, Point3, Vector3};

use crate::error::{CoreError, Result};

/// Camera-to-world rigid transform.
pub type Pose = Isometry3<f64>;

/// An 8-bit RGB image, interleaved, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    width: u32,
    height: u32,
    data: Vec<u8>,
}

impl RgbImage {
    /// Wraps an interleaved RGB buffer of `width * height * 3` bytes.
    ///
    /// # Errors
    /// [`CoreError::BufferSize`] when the buffer length does not match the size.
    pub fn new(width: u32, height: u32, data: Vec<u8>) -> Result<Self> {
        let expected = width as usize * height as usize * 3;
        if data.len() != expected {
            return Err(CoreError::BufferSize {
                what: "RGB image",
                width,
                height,
                expected,
                actual: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// An image filled with one colour.
    pub fn filled(width: u32, height: u32, rgb: [u8; 3]) -> Self {
        let data = rgb
            .iter()
            .copied()
            .cycle()
            .take(width as usize * height as usize * 3)
            .collect();
        Self {
            width,
            height,
            data,
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The colour at pixel `(u, v)`; `None` outside the image.
    pub fn get(&self, u: u32, v: u32) -> Option<[u8; 3]> {
        if u >= self.width || v >= self.height {
            return None;
        }
        let i = (v as usize * self.width as usize + u as usize) * 3;
        Some([self.data[i], self.data[i + 1], self.data[i + 2]])
    }

    /// The colour of the pixel with linear index `i = v * width + u` (caller keeps `i` in range).
    #[inline]
    pub fn at_index(&self, i: usize) -> [u8; 3] {
        let i = i * 3;
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }

    /// The raw interleaved bytes.
    pub fn as_raw(&self) -> &[u8] {
        &self.data
    }

    /// Gives the buffer back.
    pub fn into_raw(self) -> Vec<u8> {
        self.data
    }
}

/// A depth image in metres. Invalid pixels are 0 or NaN (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    width: u32,
    height: u32,
    data: Vec<f32>,
}

impl DepthImage {
    /// Wraps a row-major buffer of `width * height` depths in metres.
    ///
    /// # Errors
    /// [`CoreError::BufferSize`] when the buffer length does not match the size.
    pub fn new(width: u32, height: u32, data: Vec<f32>) -> Result<Self> {
        let expected = width as usize * height as usize;
        if data.len() != expected {
            return Err(CoreError::BufferSize {
                what: "depth image",
                width,
                height,
                expected,
                actual: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Converts raw sensor units (e.g. 16-bit millimetres) with `scale` units per metre.
    pub fn from_raw_u16(width: u32, height: u32, raw: &[u16], scale: f32) -> Result<Self> {
        let data = raw
            .iter()
            .map(|&d| if d == 0 { 0.0 } else { f32::from(d) / scale })
            .collect();
        Self::new(width, height, data)
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The valid depth at `(u, v)` in metres, `None` for invalid pixels and outside the image.
    pub fn get(&self, u: u32, v: u32) -> Option<f32> {
        if u >= self.width || v >= self.height {
            return None;
        }
        valid_depth(self.data[v as usize * self.width as usize + u as usize])
    }

    /// The raw values (including invalid ones).
    pub fn as_raw(&self) -> &[f32] {
        &self.data
    }

    /// Number of pixels holding a valid depth.
    pub fn valid_count(&self) -> usize {
        self.data
            .iter()
            .filter(|d| valid_depth(**d).is_some())
            .count()
    }
}

/// The farthest a pose may place the camera from the map's origin, in metres: 100 km. Map
/// positions are `f32`, whose spacing at 100 km is 8 mm; a pose beyond it is a broken transform
/// (a tf of 1e300 m is finite in `f64`), whose points would be infinite or meaningless in the map.
pub const MAX_POSE_DISTANCE_M: f64 = 1e5;

/// Why the camera position `t` cannot be a pose's (not finite, or farther than
/// [`MAX_POSE_DISTANCE_M`] from the origin), or `None` when it can.
pub fn implausible_position(t: [f64; 3]) -> Option<String> {
    // `hypot`: the squares of 1e300 overflow, the distance does not.
    let distance = t.iter().fold(0.0f64, |d, x| d.hypot(*x));
    if !distance.is_finite() {
        return Some("the pose's translation is not finite".to_owned());
    }
    (distance > MAX_POSE_DISTANCE_M).then(|| {
        format!(
            "the pose places the camera {distance:.3e} m from the map's origin, beyond the \
             {MAX_POSE_DISTANCE_M:.0e} m vlem accepts (map positions are f32): a broken transform?"
        )
    })
}

/// `Some(d)` when `d` is a usable depth measurement (finite and > 0).
#[inline]
pub fn valid_depth(d: f32) -> Option<f32> {
    (d.is_finite() && d > 0.0).then_some(d)
}

/// Pinhole camera intrinsics for an image of `width` x `height` pixels.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Intrinsics {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, in pixels.
    pub fx: f64,
    /// Focal length along y, in pixels.
    pub fy: f64,
    /// Principal point x, in pixels.
    pub cx: f64,
    /// Principal point y, in pixels.
    pub cy: f64,
}

/// The focal lengths a camera can have, as multiples of its image's larger side: from a field of
/// view of 179° (0.005) to one of 0.06° (1000). A camera info with fx = 1e-30 is a broken message,
/// and a map built with it has points 1e32 m away.
pub const FOCAL_RANGE: (f64, f64) = (0.005, 1000.0);

impl Intrinsics {
    /// Validated intrinsics.
    ///
    /// # Errors
    /// [`CoreError::InvalidIntrinsics`] for an empty image, focal lengths that are not finite or
    /// not within [`FOCAL_RANGE`] times the image's larger side, or a principal point outside the
    /// image.
    pub fn new(width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64) -> Result<Self> {
        let k = Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
        };
        k.validate()?;
        Ok(k)
    }

    /// Checks the invariants that [`Intrinsics::new`] enforces (for values built by hand or
    /// deserialised).
    ///
    /// # Errors
    /// See [`Intrinsics::new`].
    pub fn validate(&self) -> Result<()> {
        let fail = |reason: String| Err(CoreError::InvalidIntrinsics { reason });
        if self.width == 0 || self.height == 0 {
            return fail(format!(
                "image size {}x{} is empty",
                self.width, self.height
            ));
        }
        if !(self.fx.is_finite() && self.fy.is_finite() && self.fx > 0.0 && self.fy > 0.0) {
            return fail(format!(
                "focal lengths must be positive, got fx = {}, fy = {}",
                self.fx, self.fy
            ));
        }
        let side = f64::from(self.width.max(self.height));
        let (low, high) = (FOCAL_RANGE.0 * side, FOCAL_RANGE.1 * side);
        if !(low..=high).contains(&self.fx) || !(low..=high).contains(&self.fy) {
            return fail(format!(
                "focal lengths fx = {}, fy = {} are not those of a camera with a {}x{} image: \
                 they must lie between {low} and {high} pixels ({} to {} times its larger side; \
                 a field of view between 0.06° and 179°)",
                self.fx, self.fy, self.width, self.height, FOCAL_RANGE.0, FOCAL_RANGE.1
            ));
        }
        let inside = |c: f64, size: u32| c.is_finite() && c >= 0.0 && c <= f64::from(size);
        if !inside(self.cx, self.width) || !inside(self.cy, self.height) {
            return fail(format!(
                "principal point ({}, {}) lies outside the {}x{} image",
                self.cx, self.cy, self.width, self.height
            ));
        }
        Ok(())
    }

    /// The same camera for an image resampled to `width` x `height`.
    pub fn scaled_to(&self, width: u32, height: u32) -> Self {
        let sx = f64::from(width) / f64::from(self.width);
        let sy = f64::from(height) / f64::from(self.height);
        Self {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            // Pixel centres: (c + 0.5) scales, not c.
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
        }
    }

    /// Back-projects pixel `(u, v)` at depth `z` (metres) into the camera frame.
    #[inline]
    pub fn back_project(&self, u: f64, v: f64, z: f64) -> Point3<f64> {
        Point3::new((u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z)
    }

    /// Projects a camera-frame point to continuous pixel coordinates; `None` behind the camera.
    #[inline]
    pub fn project(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        (p.z > 0.0).then(|| (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }
}

/// One RGB-D observation.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Position in the sequence (0-based, after any stride).
    pub index: usize,
    /// Sensor timestamp in seconds; datasets without timestamps use the frame index.
    pub timestamp: f64,
    /// Colour image, same size as `depth`.
    pub colour: RgbImage,
    /// Depth in metres.
    pub depth: DepthImage,
    /// Intrinsics of both images (they are registered).
    pub intrinsics: Intrinsics,
    /// Camera-to-world pose, where the dataset has one.
    pub pose: Option<Pose>,
    /// Ground-truth class per pixel, where the dataset is labelled (synthetic scenes, labelled
    /// datasets on disk); what label-driven encoders and the segmentation evaluation read.
    pub labels: Option<LabelImage>,
}

impl Frame {
    /// A validated frame: colour, depth and intrinsics agree in size and the pose is finite.
    ///
    /// # Errors
    /// [`CoreError::SizeMismatch`], [`CoreError::InvalidIntrinsics`] or [`CoreError::NonFinitePose`].
    pub fn new(
        index: usize,
        timestamp: f64,
        colour: RgbImage,
        depth: DepthImage,
        intrinsics: Intrinsics,
        pose: Option<Pose>,
    ) -> Result<Self> {
        intrinsics.validate()?;
        let (w, h) = (intrinsics.width, intrinsics.height);
        let check = |what, aw, ah| {
            if (aw, ah) != (w, h) {
                Err(CoreError::SizeMismatch {
                    frame: index,
                    what,
                    expected_width: w,
                    expected_height: h,
                    actual_width: aw,
                    actual_height: ah,
                })
            } else {
                Ok(())
            }
        };
        check("colour image", colour.width(), colour.height())?;
        check("depth image", depth.width(), depth.height())?;
        if let Some(pose) = &pose
            && !pose_is_finite(pose)
        {
            return Err(CoreError::NonFinitePose { frame: index });
        }
        Ok(Self {
            index,
            timestamp,
            colour,
            depth,
            intrinsics,
            pose,
            labels: None,
        })
    }

    /// The frame with ground-truth labels attached.
    ///
    /// # Errors
    /// [`CoreError::SizeMismatch`] when the label image is not the frame's size.
    pub fn with_labels(mut self, labels: LabelImage) -> Result<Self> {
        let (w, h) = (self.intrinsics.width, self.intrinsics.height);
        if (labels.width(), labels.height()) != (w, h) {
            return Err(CoreError::SizeMismatch {
                frame: self.index,
                what: "label image",
                expected_width: w,
                expected_height: h,
                actual_width: labels.width(),
                actual_height: labels.height(),
            });
        }
        self.labels = Some(labels);
        Ok(self)
    }
}

/// Class names of a labelled dataset, by class id (id 0 means "unlabelled" and has no entry).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LabelNames {
    names: std::collections::BTreeMap<u16, String>,
}

impl LabelNames {
    /// A table from `(id, name)` pairs; an entry for id 0 is dropped, since 0 means unlabelled.
    pub fn new(entries: impl IntoIterator<Item = (u16, String)>) -> Self {
        Self {
            names: entries.into_iter().filter(|(id, _)| *id != 0).collect(),
        }
    }

    /// The name of class `id`; `None` for 0 and unknown ids.
    pub fn name(&self, id: u16) -> Option<&str> {
        self.names.get(&id).map(String::as_str)
    }

    /// Every `(id, name)`, by increasing id.
    pub fn iter(&self) -> impl Iterator<Item = (u16, &str)> {
        self.names.iter().map(|(id, name)| (*id, name.as_str()))
    }

    /// Number of named classes.
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// Whether no class is named.
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }
}

/// Ground-truth class ids of an image's pixels, with the dataset's class names.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelImage {
    width: u32,
    height: u32,
    ids: Vec<u16>,
    names: std::sync::Arc<LabelNames>,
}

impl LabelImage {
    /// Wraps `width * height` row-major class ids (0 = unlabelled). Ids without a name are kept;
    /// users of the labels treat them like unlabelled pixels.
    ///
    /// # Errors
    /// [`CoreError::BufferSize`] when the buffer length does not match the size.
    pub fn new(
        width: u32,
        height: u32,
        ids: Vec<u16>,
        names: std::sync::Arc<LabelNames>,
    ) -> Result<Self> {
        let expected = width as usize * height as usize;
        if ids.len() != expected {
            return Err(CoreError::BufferSize {
                what: "label image",
                width,
                height,
                expected,
                actual: ids.len(),
            });
        }
        Ok(Self {
            width,
            height,
            ids,
            names,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Row-major class ids.
    pub fn ids(&self) -> &[u16] {
        &self.ids
    }

    /// The class id at `(u, v)`; `None` outside the image.
    pub fn id(&self, u: u32, v: u32) -> Option<u16> {
        (u < self.width && v < self.height)
            .then(|| self.ids[v as usize * self.width as usize + u as usize])
    }

    /// The dataset's class names.
    pub fn names(&self) -> &std::sync::Arc<LabelNames> {
        &self.names
    }
}

/// True when every entry of the pose is finite and the rotation is a unit quaternion.
pub fn pose_is_finite(pose: &Pose) -> bool {
    let t: &Vector3<f64> = &pose.translation.vector;
    let q = pose.rotation.quaternion();
    t.iter().all(|x| x.is_finite())
        && q.coords.iter().all(|x| x.is_finite())
        && (q.norm() - 1.0).abs() < 1e-6
}

/// An axis-aligned pixel rectangle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PixelRect {
    /// Left column.
    pub x: u32,
    /// Top row.
    pub y: u32,
    /// Width in pixels (> 0).
    pub width: u32,
    /// Height in pixels (> 0).
    pub height: u32,
}

/// An image region from a [`crate::RegionProposer`]: a bounding box and a binary mask inside it.
#[derive(Clone, Debug, PartialEq)]
pub struct Region {
    /// Bounding box in image pixels.
    pub bbox: PixelRect,
    /// Row-major `bbox.width * bbox.height` foreground flags.
    pub mask: Vec<bool>,
}

impl Region {
    /// Number of foreground pixels.
    pub fn area(&self) -> usize {
        self.mask.iter().filter(|m| **m).count()
    }

    /// Whether image pixel `(u, v)` is foreground.
    pub fn contains(&self, u: u32, v: u32) -> bool {
        let b = &self.bbox;
        if u < b.x || v < b.y || u >= b.x + b.width || v >= b.y + b.height {
            return false;
        }
        self.mask[((v - b.y) * b.width + (u - b.x)) as usize]
    }
}

/// Pinhole parameters in `f32` for per-pixel hot loops (intrinsics are `f64` everywhere else):
/// the one `f32` camera of the trackers' pyramids and TSDF, the maps' back-projection and the
/// point cloud's projective association.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PinholeF32 {
    /// Focal length along x (pixels).
    pub fx: f32,
    /// Focal length along y (pixels).
    pub fy: f32,
    /// Principal point x (pixels).
    pub cx: f32,
    /// Principal point y (pixels).
    pub cy: f32,
}

impl PinholeF32 {
    /// `k`'s focal lengths and principal point, rounded to `f32`.
    pub fn from_intrinsics(k: &Intrinsics) -> Self {
        Self {
            fx: k.fx as f32,
            fy: k.fy as f32,
            cx: k.cx as f32,
            cy: k.cy as f32,
        }
    }

    /// Every parameter times `factor` (0.5: one level down an image pyramid).
    pub fn scaled(&self, factor: f32) -> Self {
        Self {
            fx: self.fx * factor,
            fy: self.fy * factor,
            cx: self.cx * factor,
            cy: self.cy * factor,
        }
    }
}

/// A rigid transform in `f32` for per-pixel hot loops (poses are `f64` everywhere else): the
/// rotation as rows and the translation, so `apply` is `R p + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigidF32 {
    /// Row-major rotation.
    pub rotation: [[f32; 3]; 3],
    /// Translation.
    pub translation: [f32; 3],
}

impl RigidF32 {
    /// The transform of `pose`, rounded to `f32`.
    pub fn from_pose(pose: &Pose) -> Self {
        let m = pose.rotation.to_rotation_matrix();
        let m = m.matrix();
        let t = pose.translation.vector;
        Self {
            rotation: [0, 1, 2].map(|i| [0, 1, 2].map(|j| m[(i, j)] as f32)),
            translation: [t.x as f32, t.y as f32, t.z as f32],
        }
    }

    /// `R v`.
    #[inline(always)]
    pub fn rotate(&self, v: [f32; 3]) -> [f32; 3] {
        let r = &self.rotation;
        [
            r[0][0] * v[0] + r[0][1] * v[1] + r[0][2] * v[2],
            r[1][0] * v[0] + r[1][1] * v[1] + r[1][2] * v[2],
            r[2][0] * v[0] + r[2][1] * v[1] + r[2][2] * v[2],
        ]
    }

    /// `R p + t`.
    #[inline(always)]
    pub fn apply(&self, p: [f32; 3]) -> [f32; 3] {
        let q = self.rotate(p);
        let t = &self.translation;
        [q[0] + t[0], q[1] + t[1], q[2] + t[2]]
    }

    /// `Rᵀ v`.
    #[inline(always)]
    pub fn inverse_rotate(&self, v: [f32; 3]) -> [f32; 3] {
        let r = &self.rotation;
        [
            r[0][0] * v[0] + r[1][0] * v[1] + r[2][0] * v[2],
            r[0][1] * v[0] + r[1][1] * v[1] + r[2][1] * v[2],
            r[0][2] * v[0] + r[1][2] * v[1] + r[2][2] * v[2],
        ]
    }

    /// `Rᵀ (p − t)`: world to camera when the transform is camera-to-world.
    #[inline(always)]
    pub fn inverse_apply(&self, p: [f32; 3]) -> [f32; 3] {
        let t = &self.translation;
        self.inverse_rotate([p[0] - t[0], p[1] - t[1], p[2] - t[2]])
    }
}

/// A triangle mesh with one colour per vertex: the dense colour model a tracker can export
/// (e.g. marching cubes on its TSDF), shown beside the embedding map.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColouredMesh {
    /// Vertex positions in world coordinates (metres).
    pub vertices: Vec<[f32; 3]>,
    /// One RGB colour per vertex.
    pub colours: Vec<[u8; 3]>,
    /// Vertex indices of each triangle; empty for a point set.
    pub triangles: Vec<[u32; 3]>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intrinsics_reject_bad_values_with_reasons() {
        let err = Intrinsics::new(640, 480, 0.0, 525.0, 319.5, 239.5).unwrap_err();
        assert!(
            err.to_string().contains("focal lengths must be positive"),
            "{err}"
        );
        let err = Intrinsics::new(640, 480, 525.0, 525.0, 700.0, 239.5).unwrap_err();
        assert!(
            err.to_string()
                .contains("principal point (700, 239.5) lies outside"),
            "{err}"
        );
        let err = Intrinsics::new(0, 480, 525.0, 525.0, 0.0, 0.0).unwrap_err();
        assert!(err.to_string().contains("empty"), "{err}");
        assert!(Intrinsics::new(640, 480, 525.0, 525.0, 319.5, 239.5).is_ok());
        // A camera info with fx = fy = 1e-30 (positive, finite, and no camera's).
        for f in [1e-30, 3.0, 640_001.0] {
            let err = Intrinsics::new(640, 480, f, f, 319.5, 239.5).unwrap_err();
            assert!(err.to_string().contains("not those of a camera"), "{err}");
        }
        assert!(Intrinsics::new(640, 480, 3.2, 3.2, 319.5, 239.5).is_ok());
    }

    #[test]
    fn back_projection_inverts_projection() {
        let k = Intrinsics::new(640, 480, 525.0, 520.0, 319.5, 239.5).unwrap();
        let p = k.back_project(100.0, 400.0, 2.5);
        let (u, v) = k.project(&p).unwrap();
        assert!((u - 100.0).abs() < 1e-9 && (v - 400.0).abs() < 1e-9);
        assert!(k.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn scaled_intrinsics_keep_pixel_centres() {
        let k = Intrinsics::new(1296, 968, 1170.0, 1170.0, 647.5, 483.5).unwrap();
        let s = k.scaled_to(648, 484);
        assert!((s.fx - 585.0).abs() < 1e-9);
        assert!((s.cx - 323.5).abs() < 1e-9);
    }

    #[test]
    fn depth_treats_zero_nan_and_negative_as_invalid() {
        let d = DepthImage::new(4, 1, vec![0.0, f32::NAN, -1.0, 1.5]).unwrap();
        assert_eq!(d.get(0, 0), None);
        assert_eq!(d.get(1, 0), None);
        assert_eq!(d.get(2, 0), None);
        assert_eq!(d.get(3, 0), Some(1.5));
        assert_eq!(d.valid_count(), 1);
        assert!(DepthImage::new(4, 2, vec![0.0; 7]).is_err());
    }

    #[test]
    fn rigid_f32_matches_the_f64_pose_and_inverts() {
        let pose = Pose::new(Vector3::new(0.5, -1.0, 2.0), Vector3::new(0.1, -0.4, 0.3));
        let rigid = RigidF32::from_pose(&pose);
        let p = [0.3_f32, -0.7, 1.9];
        let q = rigid.apply(p);
        let expected = pose * Point3::new(0.3, -0.7, 1.9);
        for a in 0..3 {
            assert!(
                (f64::from(q[a]) - expected[a]).abs() < 1e-5,
                "{q:?} vs {expected}"
            );
        }
        let back = rigid.inverse_apply(q);
        for a in 0..3 {
            assert!((back[a] - p[a]).abs() < 1e-5, "{back:?}");
        }
    }

    #[test]
    fn frame_rejects_size_mismatch_and_nan_pose() {
        let k = Intrinsics::new(4, 2, 2.0, 2.0, 2.0, 1.0).unwrap();
        let colour = RgbImage::filled(4, 2, [1, 2, 3]);
        let depth = DepthImage::new(3, 2, vec![1.0; 6]).unwrap();
        let err = Frame::new(7, 0.0, colour.clone(), depth, k, None).unwrap_err();
        assert_eq!(err.to_string(), "frame 7: depth image is 3x2, expected 4x2");
        let depth = DepthImage::new(4, 2, vec![1.0; 8]).unwrap();
        let mut pose = Pose::identity();
        pose.translation.vector.x = f64::NAN;
        let err = Frame::new(3, 0.0, colour, depth, k, Some(pose)).unwrap_err();
        assert_eq!(err.to_string(), "frame 3: pose is not finite");
    }

    #[test]
    fn labels_must_cover_the_frame_and_id_zero_has_no_name() {
        let k = Intrinsics::new(4, 2, 2.0, 2.0, 2.0, 1.0).unwrap();
        let frame = Frame::new(
            1,
            0.0,
            RgbImage::filled(4, 2, [1, 2, 3]),
            DepthImage::new(4, 2, vec![1.0; 8]).unwrap(),
            k,
            None,
        )
        .unwrap();
        let names = std::sync::Arc::new(LabelNames::new([
            (0, "void".to_owned()),
            (5, "chair".to_owned()),
        ]));
        assert_eq!(names.len(), 1);
        assert_eq!(names.name(0), None);
        assert_eq!(names.name(5), Some("chair"));
        assert!(LabelImage::new(4, 2, vec![0; 7], names.clone()).is_err());
        let small = LabelImage::new(2, 2, vec![5; 4], names.clone()).unwrap();
        let err = frame.clone().with_labels(small).unwrap_err();
        assert_eq!(err.to_string(), "frame 1: label image is 2x2, expected 4x2");
        let labels = LabelImage::new(4, 2, vec![0, 5, 5, 0, 0, 0, 5, 9], names).unwrap();
        let frame = frame.with_labels(labels).unwrap();
        let labels = frame.labels.as_ref().unwrap();
        assert_eq!(labels.id(1, 0), Some(5));
        assert_eq!(labels.id(3, 1), Some(9));
        assert_eq!(labels.id(4, 0), None);
    }
}

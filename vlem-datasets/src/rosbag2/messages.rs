//! The ROS 2 messages vlem reads, decoded from CDR, and their conversion to vlem's images, camera
//! and poses.
//!
//! Why here: a bag and a live ROS 2 node carry the same messages; decoding them in one module
//! (public, so the fuzz target and a future node share it) keeps the conventions in one place:
//! stamps in integer nanoseconds, depth 0 = no measurement, poses camera-to-world in the camera's
//! optical frame (x right, y down, z forward: ROS's `*_optical_frame`, which is vlem's camera frame).

use nalgebra::{Quaternion, Translation3, UnitQuaternion};
use vlem_core::{DepthImage, Intrinsics, Pose, RgbImage};

use super::cdr::{CdrError, CdrReader};

/// `sensor_msgs/msg/Image`.
pub const IMAGE: &str = "sensor_msgs/msg/Image";
/// `sensor_msgs/msg/CompressedImage`.
pub const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";
/// `sensor_msgs/msg/CameraInfo`.
pub const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";
/// `tf2_msgs/msg/TFMessage` (`/tf`, `/tf_static`).
pub const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";
/// `nav_msgs/msg/Odometry`.
pub const ODOMETRY: &str = "nav_msgs/msg/Odometry";
/// `geometry_msgs/msg/PoseStamped`.
pub const POSE_STAMPED: &str = "geometry_msgs/msg/PoseStamped";

/// The ROS 2 spelling (`pkg/msg/Type`) of a type name; bags converted from ROS 1 write `pkg/Type`.
pub fn normalise_type(type_name: &str) -> String {
    match type_name.split('/').collect::<Vec<_>>().as_slice() {
        [package, name] => format!("{package}/msg/{name}"),
        _ => type_name.to_owned(),
    }
}

/// `std_msgs/msg/Header`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Header {
    /// `stamp` in nanoseconds since the epoch (or the clock's zero).
    pub stamp_ns: i64,
    /// `frame_id`.
    pub frame_id: String,
}

impl Header {
    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        let sec = i64::from(r.i32()?);
        let nanosec = i64::from(r.u32()?);
        let frame_id = r.string()?;
        Ok(Self {
            stamp_ns: sec * 1_000_000_000 + nanosec,
            frame_id,
        })
    }

    /// The stamp in seconds.
    pub fn seconds(&self) -> f64 {
        self.stamp_ns as f64 * 1e-9
    }
}

/// Reads only the header of a message whose first field is one (every stamped message).
///
/// # Errors
/// A malformed or truncated payload.
pub fn header_of(data: &[u8]) -> Result<Header, CdrError> {
    Header::read(&mut CdrReader::new(data)?)
}

/// `sensor_msgs/msg/Image`, its pixels borrowed from the message.
#[derive(Clone, Debug)]
pub struct Image<'a> {
    /// Header.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding (`rgb8`, `16UC1`, …).
    pub encoding: String,
    /// Byte order of multi-byte pixels.
    pub is_bigendian: bool,
    /// Bytes per row (at least `width` × bytes per pixel).
    pub step: u32,
    /// `step` × `height` bytes (or more).
    pub data: &'a [u8],
}

impl<'a> Image<'a> {
    /// Decodes the CDR payload of an `Image`.
    ///
    /// # Errors
    /// A malformed or truncated payload.
    pub fn decode(data: &'a [u8]) -> Result<Self, CdrError> {
        let mut r = CdrReader::new(data)?;
        Ok(Self {
            header: Header::read(&mut r)?,
            height: r.u32()?,
            width: r.u32()?,
            encoding: r.string()?,
            is_bigendian: r.u8()? != 0,
            step: r.u32()?,
            data: r.bytes()?,
        })
    }

    /// The `bytes_per_pixel` × `width` bytes of each row, after checking `step` and the data
    /// length against the size.
    fn rows(&self, bytes_per_pixel: usize) -> Result<impl Iterator<Item = &'a [u8]>, String> {
        let (width, height, step) = (
            self.width as usize,
            self.height as usize,
            self.step as usize,
        );
        if width == 0 || height == 0 {
            return Err(format!("the image is {width}x{height}: empty"));
        }
        let row = width
            .checked_mul(bytes_per_pixel)
            .ok_or("the image width overflows")?;
        if step < row {
            return Err(format!(
                "step {step} is less than width {width} × {bytes_per_pixel} bytes"
            ));
        }
        let needed = step
            .checked_mul(height.saturating_sub(1))
            .and_then(|n| n.checked_add(row))
            .ok_or("the image size overflows")?;
        if self.data.len() < needed {
            return Err(format!(
                "{}x{} {} with step {step} needs {needed} bytes but the message has {}",
                self.width,
                self.height,
                self.encoding,
                self.data.len()
            ));
        }
        let data = self.data;
        Ok((0..height).map(move |y| &data[y * step..y * step + row]))
    }

    /// The colour image: `rgb8`, `bgr8`, `rgba8` or `bgra8` (alpha dropped).
    ///
    /// # Errors
    /// Another encoding, or a size the data does not hold.
    pub fn to_colour(&self) -> Result<RgbImage, String> {
        let (channels, swap) = match self.encoding.as_str() {
            "rgb8" => (3, false),
            "bgr8" => (3, true),
            "rgba8" => (4, false),
            "bgra8" => (4, true),
            other => {
                return Err(format!(
                    "colour encoding `{other}` is not supported (rgb8, bgr8, rgba8, bgra8 are; \
                     a CompressedImage topic of JPEG/PNG also works)"
                ));
            }
        };
        // Rows first: they check the size against the data before anything is allocated.
        let rows = self.rows(channels)?;
        let mut out = Vec::with_capacity(self.width as usize * self.height as usize * 3);
        for row in rows {
            for pixel in row.chunks_exact(channels) {
                if swap {
                    out.extend([pixel[2], pixel[1], pixel[0]]);
                } else {
                    out.extend(&pixel[..3]);
                }
            }
        }
        RgbImage::new(self.width, self.height, out).map_err(|e| e.to_string())
    }

    /// The depth image in metres: `16UC1` (or `mono16`) in raw units, `scale` per metre, 0 = no
    /// measurement; `32FC1` in metres, where NaN, infinite and non-positive values become 0.
    ///
    /// # Errors
    /// Another encoding, or a size the data does not hold.
    pub fn to_depth(&self, scale: f32) -> Result<DepthImage, String> {
        let mut out = Vec::new();
        match self.encoding.as_str() {
            "16UC1" | "mono16" => {
                let rows = self.rows(2)?;
                out.reserve_exact(self.width as usize * self.height as usize);
                for row in rows {
                    out.extend(row.chunks_exact(2).map(|b| {
                        let raw = if self.is_bigendian {
                            u16::from_be_bytes([b[0], b[1]])
                        } else {
                            u16::from_le_bytes([b[0], b[1]])
                        };
                        if raw == 0 {
                            0.0
                        } else {
                            f32::from(raw) / scale
                        }
                    }));
                }
            }
            "32FC1" => {
                let rows = self.rows(4)?;
                out.reserve_exact(self.width as usize * self.height as usize);
                for row in rows {
                    out.extend(row.chunks_exact(4).map(|b| {
                        let bytes = [b[0], b[1], b[2], b[3]];
                        let metres = if self.is_bigendian {
                            f32::from_be_bytes(bytes)
                        } else {
                            f32::from_le_bytes(bytes)
                        };
                        valid_metres(metres)
                    }));
                }
            }
            other => {
                return Err(format!(
                    "depth encoding `{other}` is not supported (16UC1 and 32FC1 are)"
                ));
            }
        }
        DepthImage::new(self.width, self.height, out).map_err(|e| e.to_string())
    }
}

/// A depth in metres, or 0 for "no measurement" (NaN, ±inf, ≤ 0: ROS's conventions for it).
fn valid_metres(metres: f32) -> f32 {
    if metres.is_finite() && metres > 0.0 {
        metres
    } else {
        0.0
    }
}

/// `sensor_msgs/msg/CompressedImage`, its bytes borrowed from the message.
#[derive(Clone, Debug)]
pub struct CompressedImage<'a> {
    /// Header.
    pub header: Header,
    /// `format`: `jpeg`, `png`, or image_transport's `ENCODING; FORMAT compressed …` /
    /// `ENCODING; compressedDepth FORMAT`.
    pub format: String,
    /// The compressed image.
    pub data: &'a [u8],
}

/// What a depth `CompressedImage` holds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CompressedDepth<'a> {
    /// A 16-bit PNG of raw depth units (`16UC1; png compressed`, or `16UC1; compressedDepth png`
    /// after its header).
    Raw16(&'a [u8]),
    /// image_transport's `32FC1; compressedDepth png`: a 16-bit PNG of quantised inverse depth,
    /// metres = `quant_a / (value − quant_b)` for value ≠ 0.
    InverseDepth {
        /// The PNG.
        png: &'a [u8],
        /// `depthParam[0]` of the header.
        quant_a: f32,
        /// `depthParam[1]` of the header.
        quant_b: f32,
    },
}

/// Bytes of compressed_depth_image_transport's `ConfigHeader` (`int32 format; float
/// depthParam[2]`) before the PNG of a `compressedDepth` message.
pub const COMPRESSED_DEPTH_HEADER: usize = 12;

impl<'a> CompressedImage<'a> {
    /// Decodes the CDR payload of a `CompressedImage`.
    ///
    /// # Errors
    /// A malformed or truncated payload.
    pub fn decode(data: &'a [u8]) -> Result<Self, CdrError> {
        let mut r = CdrReader::new(data)?;
        Ok(Self {
            header: Header::read(&mut r)?,
            format: r.string()?,
            data: r.bytes()?,
        })
    }

    /// Whether this is image_transport's `compressedDepth` format.
    pub fn is_compressed_depth(&self) -> bool {
        self.format.contains("compressedDepth")
    }

    /// The depth image this message holds.
    ///
    /// # Errors
    /// `compressedDepth` with RVL (not PNG) or with a header the data lacks, or a plain
    /// compressed `32FC1` (image_transport's `compressed` cannot hold it).
    pub fn depth(&self) -> Result<CompressedDepth<'a>, String> {
        let encoding = self.format.split(';').next().unwrap_or("").trim();
        if !self.is_compressed_depth() {
            if encoding == "32FC1" {
                return Err(format!(
                    "format `{}`: a 32FC1 depth must use the compressedDepth transport",
                    self.format
                ));
            }
            return Ok(CompressedDepth::Raw16(self.data));
        }
        if self.format.contains("rvl") {
            return Err(format!(
                "format `{}`: RVL compressedDepth is not supported; record the `png` variant \
                 (parameter `format: png` of the compressedDepth transport)",
                self.format
            ));
        }
        let Some((header, png)) = self.data.split_first_chunk::<COMPRESSED_DEPTH_HEADER>() else {
            return Err(format!(
                "compressedDepth data of {} bytes is shorter than its {COMPRESSED_DEPTH_HEADER}-byte header",
                self.data.len()
            ));
        };
        if encoding == "32FC1" {
            let float = |i: usize| {
                f32::from_le_bytes([header[i], header[i + 1], header[i + 2], header[i + 3]])
            };
            Ok(CompressedDepth::InverseDepth {
                png,
                quant_a: float(4),
                quant_b: float(8),
            })
        } else {
            Ok(CompressedDepth::Raw16(png))
        }
    }
}

impl CompressedImage<'_> {
    /// The depth image in metres, decoded, and whether it came in raw units (`scale` per metre;
    /// the caller may check that scale) rather than in metres. `origin` is what errors name.
    ///
    /// # Errors
    /// [`crate::DatasetError::UnsupportedImage`] for a format [`CompressedImage::depth`] refuses,
    /// and the errors of [`crate::depth_from_bytes`].
    pub fn depth_image(
        &self,
        scale: f32,
        origin: &std::path::Path,
    ) -> crate::Result<(DepthImage, bool)> {
        let unsupported = |reason| crate::DatasetError::UnsupportedImage {
            path: origin.to_path_buf(),
            reason,
        };
        match self.depth().map_err(unsupported)? {
            CompressedDepth::Raw16(png) => Ok((crate::depth_from_bytes(png, scale, origin)?, true)),
            CompressedDepth::InverseDepth {
                png,
                quant_a,
                quant_b,
            } => {
                // Scale 1: the raw 16-bit values, exactly (they fit an f32).
                let raw = crate::depth_from_bytes(png, 1.0, origin)?;
                let metres = raw
                    .as_raw()
                    .iter()
                    .map(|&v| inverse_depth_to_metres(v as u16, quant_a, quant_b))
                    .collect();
                let depth =
                    DepthImage::new(raw.width(), raw.height(), metres).map_err(|source| {
                        crate::DatasetError::Core {
                            path: origin.to_path_buf(),
                            source,
                        }
                    })?;
                Ok((depth, false))
            }
        }
    }
}

/// Metres from one value of a `32FC1; compressedDepth` PNG (0 = no measurement).
pub fn inverse_depth_to_metres(value: u16, quant_a: f32, quant_b: f32) -> f32 {
    if value == 0 {
        0.0
    } else {
        valid_metres(quant_a / (f32::from(value) - quant_b))
    }
}

/// `sensor_msgs/msg/CameraInfo`: the fields vlem uses.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraInfo {
    /// Header.
    pub header: Header,
    /// Image rows.
    pub height: u32,
    /// Image columns.
    pub width: u32,
    /// `plumb_bob`, `rational_polynomial`, `equidistant`, …
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// Intrinsic matrix, row-major.
    pub k: [f64; 9],
}

impl CameraInfo {
    /// Decodes the CDR payload of a `CameraInfo` (the fields after `k` are not read).
    ///
    /// # Errors
    /// A malformed or truncated payload.
    pub fn decode(data: &[u8]) -> Result<Self, CdrError> {
        let mut r = CdrReader::new(data)?;
        Ok(Self {
            header: Header::read(&mut r)?,
            height: r.u32()?,
            width: r.u32()?,
            distortion_model: r.string()?,
            d: r.f64_sequence()?,
            k: r.f64_array::<9>()?,
        })
    }

    /// The pinhole intrinsics of `k` at `width` × `height`.
    ///
    /// # Errors
    /// Intrinsics vlem cannot use (zero focal length, a size of 0, non-finite values).
    pub fn intrinsics(&self) -> Result<Intrinsics, String> {
        let k = &self.k;
        Intrinsics::new(self.width, self.height, k[0], k[4], k[2], k[5]).map_err(|e| {
            format!(
                "K = [{}] at {}x{}: {e}",
                k.map(|v| v.to_string()).join(", "),
                self.width,
                self.height
            )
        })
    }

    /// Whether any distortion coefficient is non-zero (vlem does not undistort).
    pub fn is_distorted(&self) -> bool {
        self.d.iter().any(|&c| c != 0.0)
    }
}

/// A rigid transform as ROS writes one (translation, then quaternion x, y, z, w), made a pose.
///
/// # Errors
/// A non-finite value or a quaternion whose norm is far from 1 (a zero quaternion is the usual
/// sign of an unset field).
fn read_pose(r: &mut CdrReader<'_>) -> Result<Result<Pose, String>, CdrError> {
    let [x, y, z] = r.f64_array::<3>()?;
    let [qx, qy, qz, qw] = r.f64_array::<4>()?;
    Ok(pose_from_parts([x, y, z], [qx, qy, qz, qw]))
}

/// A pose from a translation and a quaternion `[x, y, z, w]`, normalised when its norm is within
/// 1 % of 1.
///
/// # Errors
/// A non-finite value, or a quaternion norm further from 1.
pub fn pose_from_parts(t: [f64; 3], q: [f64; 4]) -> Result<Pose, String> {
    if t.iter().chain(&q).any(|v| !v.is_finite()) {
        return Err("the pose is not finite".to_owned());
    }
    if let Some(why) = vlem_core::types::implausible_position(t) {
        return Err(why);
    }
    let quaternion = Quaternion::new(q[3], q[0], q[1], q[2]);
    let norm = quaternion.norm();
    if (norm - 1.0).abs() > 0.01 {
        return Err(format!(
            "the rotation quaternion [{}, {}, {}, {}] has norm {norm:.4}, not 1",
            q[0], q[1], q[2], q[3]
        ));
    }
    Ok(Pose::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_quaternion(quaternion),
    ))
}

/// A pose message: `Odometry` or `PoseStamped`, with the frame it is in and the frame it places.
#[derive(Clone, Debug)]
pub struct StampedPose {
    /// Header; `frame_id` is the parent (world) frame.
    pub header: Header,
    /// The frame whose pose this is: `child_frame_id` of an `Odometry`, empty for a
    /// `PoseStamped` (which does not say).
    pub child_frame_id: String,
    /// The pose, or why it cannot be used.
    pub pose: Result<Pose, String>,
}

impl StampedPose {
    /// Decodes an `Odometry` (`header`, `child_frame_id`, `pose.pose`; covariance and twist are
    /// not read).
    ///
    /// # Errors
    /// A malformed or truncated payload.
    pub fn decode_odometry(data: &[u8]) -> Result<Self, CdrError> {
        let mut r = CdrReader::new(data)?;
        let header = Header::read(&mut r)?;
        let child_frame_id = r.string()?;
        Ok(Self {
            header,
            child_frame_id,
            pose: read_pose(&mut r)?,
        })
    }

    /// Decodes a `PoseStamped`.
    ///
    /// # Errors
    /// A malformed or truncated payload.
    pub fn decode_pose_stamped(data: &[u8]) -> Result<Self, CdrError> {
        let mut r = CdrReader::new(data)?;
        Ok(Self {
            header: Header::read(&mut r)?,
            child_frame_id: String::new(),
            pose: read_pose(&mut r)?,
        })
    }
}

/// One `geometry_msgs/msg/TransformStamped` of a `TFMessage`.
#[derive(Clone, Debug)]
pub struct Transform {
    /// Header; `frame_id` is the parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// The child's pose in the parent frame, or why it cannot be used.
    pub transform: Result<Pose, String>,
}

/// Decodes a `tf2_msgs/msg/TFMessage`.
///
/// # Errors
/// A malformed or truncated payload.
pub fn decode_tf_message(data: &[u8]) -> Result<Vec<Transform>, CdrError> {
    let mut r = CdrReader::new(data)?;
    // A TransformStamped takes at least 8 (stamp) + 4 + 4 (two empty strings) + 56 bytes.
    let count = r.sequence_length(72)?;
    let mut out = Vec::with_capacity(count);
    for _ in 0..count {
        let header = Header::read(&mut r)?;
        let child_frame_id = r.string()?;
        let transform = read_pose(&mut r)?;
        out.push(Transform {
            header,
            child_frame_id,
            transform,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A little-endian CDR writer for the tests: the same layout rules, written the other way.
    struct Writer(Vec<u8>);

    impl Writer {
        fn new() -> Self {
            Self(vec![0, 1, 0, 0])
        }
        fn align(&mut self, n: usize) {
            while !(self.0.len() - 4).is_multiple_of(n) {
                self.0.push(0);
            }
        }
        fn u32(&mut self, v: u32) -> &mut Self {
            self.align(4);
            self.0.extend(v.to_le_bytes());
            self
        }
        fn f64(&mut self, v: f64) -> &mut Self {
            self.align(8);
            self.0.extend(v.to_le_bytes());
            self
        }
        fn string(&mut self, s: &str) -> &mut Self {
            self.u32(s.len() as u32 + 1);
            self.0.extend(s.as_bytes());
            self.0.push(0);
            self
        }
        fn bytes(&mut self, b: &[u8]) -> &mut Self {
            self.u32(b.len() as u32);
            self.0.extend(b);
            self
        }
        fn header(&mut self, sec: u32, nanosec: u32, frame: &str) -> &mut Self {
            self.u32(sec).u32(nanosec).string(frame)
        }
    }

    fn image(encoding: &str, width: u32, height: u32, step: u32, data: &[u8]) -> Vec<u8> {
        let mut w = Writer::new();
        w.header(1, 500, "cam")
            .u32(height)
            .u32(width)
            .string(encoding);
        w.0.push(0);
        w.u32(step).bytes(data);
        w.0
    }

    #[test]
    fn colour_encodings_and_padded_rows_give_rgb() {
        // 2x1 pixels, red then blue, with two bytes of row padding.
        let bgr = image("bgr8", 2, 1, 8, &[0, 0, 255, 255, 0, 0, 9, 9]);
        let img = Image::decode(&bgr).unwrap();
        assert_eq!(img.header.stamp_ns, 1_000_000_500);
        assert_eq!(img.to_colour().unwrap().as_raw(), &[255, 0, 0, 0, 0, 255]);
        let rgba = image("rgba8", 2, 1, 8, &[255, 0, 0, 1, 0, 0, 255, 1]);
        let img = Image::decode(&rgba).unwrap();
        assert_eq!(img.to_colour().unwrap().as_raw(), &[255, 0, 0, 0, 0, 255]);
        let mono = image("mono8", 2, 1, 2, &[1, 2]);
        let err = Image::decode(&mono).unwrap().to_colour().unwrap_err();
        assert!(err.contains("`mono8` is not supported"), "{err}");
        let short = image("rgb8", 2, 2, 6, &[0; 6]);
        let err = Image::decode(&short).unwrap().to_colour().unwrap_err();
        assert!(err.contains("needs 12 bytes"), "{err}");
    }

    #[test]
    fn depth_encodings_give_metres_with_zero_for_no_measurement() {
        let raw: Vec<u8> = [0u16, 1500].iter().flat_map(|v| v.to_le_bytes()).collect();
        let message = image("16UC1", 2, 1, 4, &raw);
        let img = Image::decode(&message).unwrap();
        assert_eq!(img.to_depth(1000.0).unwrap().as_raw(), &[0.0, 1.5]);
        let floats: Vec<u8> = [f32::NAN, 2.25, -1.0, f32::INFINITY]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let message = image("32FC1", 4, 1, 16, &floats);
        let img = Image::decode(&message).unwrap();
        assert_eq!(
            img.to_depth(1000.0).unwrap().as_raw(),
            &[0.0, 2.25, 0.0, 0.0]
        );
        let message = image("16UC1", 1, 1, 2, &1500u16.to_be_bytes());
        let mut big = Image::decode(&message).unwrap();
        big.is_bigendian = true;
        assert_eq!(big.to_depth(1000.0).unwrap().as_raw(), &[1.5]);
    }

    #[test]
    fn camera_info_and_poses_decode() {
        let mut w = Writer::new();
        w.header(3, 0, "cam").u32(480).u32(640).string("plumb_bob");
        w.u32(5);
        for d in [0.1, 0.0, 0.0, 0.0, 0.0] {
            w.f64(d);
        }
        for k in [525.0, 0.0, 319.5, 0.0, 526.0, 239.5, 0.0, 0.0, 1.0] {
            w.f64(k);
        }
        let info = CameraInfo::decode(&w.0).unwrap();
        assert!(info.is_distorted());
        let k = info.intrinsics().unwrap();
        assert_eq!((k.fx, k.fy, k.cx, k.cy), (525.0, 526.0, 319.5, 239.5));

        let mut w = Writer::new();
        w.u32(1).header(4, 0, "map").string("cam");
        for v in [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0] {
            w.f64(v);
        }
        let tf = decode_tf_message(&w.0).unwrap();
        assert_eq!(tf[0].child_frame_id, "cam");
        let pose = tf[0].transform.as_ref().unwrap();
        assert_eq!(pose.translation.vector.as_slice(), &[1.0, 2.0, 3.0]);
        assert!(
            pose_from_parts([0.0; 3], [0.0; 4])
                .unwrap_err()
                .contains("norm")
        );
        // A tf of 1e300 m is finite in f64, but no camera pose.
        assert!(
            pose_from_parts([1e300, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
                .unwrap_err()
                .contains("from the map's origin")
        );
    }

    #[test]
    fn compressed_depth_headers_are_read() {
        let mut data = vec![0u8; 4];
        data.extend(10100f32.to_le_bytes());
        data.extend((-1009f32).to_le_bytes());
        data.extend(b"PNG");
        let mut w = Writer::new();
        w.header(0, 0, "cam")
            .string("32FC1; compressedDepth png")
            .bytes(&data);
        let message = CompressedImage::decode(&w.0).unwrap();
        assert_eq!(
            message.depth().unwrap(),
            CompressedDepth::InverseDepth {
                png: b"PNG",
                quant_a: 10100.0,
                quant_b: -1009.0
            }
        );
        // 2 m quantised as the transport does: a / d + b.
        let value = (10100.0f32 / 2.0 - 1009.0) as u16;
        assert!((inverse_depth_to_metres(value, 10100.0, -1009.0) - 2.0).abs() < 1e-3);
        assert_eq!(inverse_depth_to_metres(0, 10100.0, -1009.0), 0.0);
    }
}

//! The ROS 2 messages the node sends and receives, as serde structs in `.msg` field order (what
//! ros2-client serialises to CDR), with their type names.
//!
//! Why hand-written: ros2-client needs no code generation, only serde types whose fields follow
//! the `.msg` definitions. Decoding an image into vlem's types goes through the same conversions
//! as the bag reader ([`vlem_datasets::rosbag2::messages`]), so a topic and a bag of it give the
//! same frames.

use serde::{Deserialize, Serialize};

/// `builtin_interfaces/msg/Time`.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl Time {
    /// The time of `seconds` since the epoch (rounded to the nanosecond).
    pub fn from_seconds(seconds: f64) -> Self {
        let whole = seconds.floor();
        let mut nanosec = ((seconds - whole) * 1e9).round() as u32;
        let mut sec = whole as i32;
        if nanosec >= 1_000_000_000 {
            sec += 1;
            nanosec -= 1_000_000_000;
        }
        Self { sec, nanosec }
    }

    /// Nanoseconds since the epoch.
    pub fn nanoseconds(&self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }

    /// Seconds since the epoch.
    pub fn seconds(&self) -> f64 {
        self.nanoseconds() as f64 * 1e-9
    }
}

/// `std_msgs/msg/Header`.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
pub struct Header {
    /// Stamp.
    pub stamp: Time,
    /// Frame id.
    pub frame_id: String,
}

impl Header {
    /// The view the shared conversions take.
    pub fn to_shared(&self) -> vlem_datasets::rosbag2::messages::Header {
        vlem_datasets::rosbag2::messages::Header {
            stamp_ns: self.stamp.nanoseconds(),
            frame_id: self.frame_id.clone(),
        }
    }
}

/// `std_msgs/msg/String`.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
pub struct StringMessage {
    /// The text.
    pub data: String,
}

/// `sensor_msgs/msg/Image`.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
pub struct Image {
    /// Header.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding.
    pub encoding: String,
    /// Byte order of multi-byte pixels.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// Pixels.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

impl Image {
    /// The view the shared conversions (`to_colour`, `to_depth`) take.
    pub fn view(&self) -> vlem_datasets::rosbag2::messages::Image<'_> {
        vlem_datasets::rosbag2::messages::Image {
            header: self.header.to_shared(),
            height: self.height,
            width: self.width,
            encoding: self.encoding.clone(),
            is_bigendian: self.is_bigendian != 0,
            step: self.step,
            data: &self.data,
        }
    }
}

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
pub struct CompressedImage {
    /// Header.
    pub header: Header,
    /// `jpeg`, `png`, or image_transport's `ENCODING; …` forms.
    pub format: String,
    /// The compressed image.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

impl CompressedImage {
    /// The view the shared conversions take.
    pub fn view(&self) -> vlem_datasets::rosbag2::messages::CompressedImage<'_> {
        vlem_datasets::rosbag2::messages::CompressedImage {
            header: self.header.to_shared(),
            format: self.format.clone(),
            data: &self.data,
        }
    }
}

/// `sensor_msgs/msg/RegionOfInterest`.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq)]
pub struct RegionOfInterest {
    /// Left edge.
    pub x_offset: u32,
    /// Top edge.
    pub y_offset: u32,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Whether the region is to be rectified.
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
pub struct CameraInfo {
    /// Header.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Distortion model.
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// Intrinsic matrix, row-major.
    pub k: [f64; 9],
    /// Rectification rotation.
    pub r: [f64; 9],
    /// Projection matrix.
    pub p: [f64; 12],
    /// Horizontal binning.
    pub binning_x: u32,
    /// Vertical binning.
    pub binning_y: u32,
    /// Region of interest.
    pub roi: RegionOfInterest,
}

impl CameraInfo {
    /// The view the shared conversions take.
    pub fn to_shared(&self) -> vlem_datasets::rosbag2::messages::CameraInfo {
        vlem_datasets::rosbag2::messages::CameraInfo {
            header: self.header.to_shared(),
            height: self.height,
            width: self.width,
            distortion_model: self.distortion_model.clone(),
            d: self.d.clone(),
            k: self.k,
        }
    }
}

/// `geometry_msgs/msg/Point` (also `Vector3`: the same fields).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq)]
pub struct Point {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

/// `geometry_msgs/msg/Pose` (also `Transform`: translation and rotation, the same layout).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub struct PoseMessage {
    /// Position (or translation).
    pub position: Point,
    /// Orientation (or rotation).
    pub orientation: Quaternion,
}

impl PoseMessage {
    /// The ROS form of a vlem pose.
    pub fn from_pose(pose: &vlem_core::Pose) -> Self {
        let t = pose.translation.vector;
        let q = pose.rotation.quaternion();
        Self {
            position: Point {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            orientation: Quaternion {
                x: q.i,
                y: q.j,
                z: q.k,
                w: q.w,
            },
        }
    }

    /// The vlem pose, or why it cannot be one (non-finite, not a unit quaternion).
    ///
    /// # Errors
    /// As [`vlem_datasets::rosbag2::messages::pose_from_parts`].
    pub fn to_pose(&self) -> Result<vlem_core::Pose, String> {
        let (p, q) = (&self.position, &self.orientation);
        vlem_datasets::rosbag2::messages::pose_from_parts([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
    }
}

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct PoseStamped {
    /// Header; `frame_id` is the parent frame.
    pub header: Header,
    /// The pose.
    pub pose: PoseMessage,
}

/// A `float64[36]` covariance: serde derives stop at 32 elements, and two fixed arrays in a row
/// serialise to the same 36 consecutive float64 in CDR (fixed arrays have no length prefix).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub struct Covariance(pub [f64; 18], pub [f64; 18]);

impl Default for Covariance {
    fn default() -> Self {
        Self([0.0; 18], [0.0; 18])
    }
}

/// `geometry_msgs/msg/PoseWithCovariance`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: PoseMessage,
    /// Row-major 6×6 covariance.
    pub covariance: Covariance,
}

/// `geometry_msgs/msg/Twist` (two `Vector3`).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq)]
pub struct Twist {
    /// Linear velocity.
    pub linear: Point,
    /// Angular velocity.
    pub angular: Point,
}

/// `geometry_msgs/msg/TwistWithCovariance`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct TwistWithCovariance {
    /// The twist.
    pub twist: Twist,
    /// Row-major 6×6 covariance.
    pub covariance: Covariance,
}

/// `nav_msgs/msg/Odometry`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Odometry {
    /// Header; `frame_id` is the parent frame.
    pub header: Header,
    /// The frame whose pose this is.
    pub child_frame_id: String,
    /// Pose in the header's frame.
    pub pose: PoseWithCovariance,
    /// Velocity in the child frame.
    pub twist: TwistWithCovariance,
}

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct TransformStamped {
    /// Header; `frame_id` is the parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// The child's pose in the parent (`Transform` has the layout of `Pose`).
    pub transform: PoseMessage,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
pub struct TfMessage {
    /// Transforms.
    pub transforms: Vec<TransformStamped>,
}

/// `sensor_msgs/msg/PointField`.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
pub struct PointField {
    /// Field name (`x`, `rgb`, `similarity` …).
    pub name: String,
    /// Byte offset in a point.
    pub offset: u32,
    /// [`PointField::FLOAT32`] and friends.
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

impl PointField {
    /// `FLOAT32` of `sensor_msgs/msg/PointField`.
    pub const FLOAT32: u8 = 7;
}

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
pub struct PointCloud2 {
    /// Header.
    pub header: Header,
    /// 1 for an unorganised cloud.
    pub height: u32,
    /// Points.
    pub width: u32,
    /// The fields of a point.
    pub fields: Vec<PointField>,
    /// Byte order.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// Points.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    /// No invalid (NaN) points.
    pub is_dense: bool,
}

impl PointCloud2 {
    /// An unorganised little-endian cloud of float32 `x`, `y`, `z`, `rgb` (packed `0x00RRGGBB` in
    /// a float32, as PCL and RViz read it) and, when `values` is given, one more float32 field
    /// named `value_name`.
    pub fn xyz_rgb(
        header: Header,
        points: &[[f32; 3]],
        colours: &[[u8; 3]],
        values: Option<(&str, &[f32])>,
    ) -> Self {
        let field = |name: &str, offset: u32| PointField {
            name: name.to_owned(),
            offset,
            datatype: PointField::FLOAT32,
            count: 1,
        };
        let mut fields = vec![
            field("x", 0),
            field("y", 4),
            field("z", 8),
            field("rgb", 12),
        ];
        if let Some((name, _)) = values {
            fields.push(field(name, 16));
        }
        let point_step = 4 * fields.len() as u32;
        let mut data = Vec::with_capacity(points.len() * point_step as usize);
        for (i, (p, c)) in points.iter().zip(colours).enumerate() {
            for v in p {
                data.extend(v.to_le_bytes());
            }
            let rgb = (u32::from(c[0]) << 16) | (u32::from(c[1]) << 8) | u32::from(c[2]);
            data.extend(rgb.to_le_bytes());
            if let Some((_, values)) = values {
                data.extend(values.get(i).copied().unwrap_or(0.0).to_le_bytes());
            }
        }
        let count = points.len().min(colours.len()) as u32;
        Self {
            header,
            height: 1,
            width: count,
            fields,
            is_bigendian: false,
            point_step,
            row_step: point_step * count,
            data,
            is_dense: true,
        }
    }
}

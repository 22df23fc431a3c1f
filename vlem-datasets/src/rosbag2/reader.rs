//! The bag reader: opens a bag, pairs and poses its frames, decodes one on demand (see the
//! module docs of [`crate::rosbag2`]).

use std::path::{Path, PathBuf};

use vlem_core::config::DatasetConfig;
use vlem_core::{Frame, FrameSource, Intrinsics, Pose};

use crate::colour_from_bytes;
use crate::depth_check::check_depth_scale;
use crate::error::{DatasetError, Result};
use crate::sequence::{Selection, depth_scale, reader_settings};
use crate::tum::{associate, pose_at};

use super::messages::{
    CAMERA_INFO, COMPRESSED_IMAGE, CameraInfo, CompressedImage, IMAGE, Image, ODOMETRY,
    POSE_STAMPED, StampedPose, TF_MESSAGE, decode_tf_message, header_of, normalise_type,
};
use super::poses::TfTree;
use super::storage::{Bag, MessageKey, TopicInfo};
use super::{ROSBAG2, Rosbag2Config, Rosbag2Settings};

/// Raw depth units per metre of a `16UC1` depth image unless `[dataset] depth_scale` says
/// otherwise: millimetres, as RealSense, Orbbec, Azure Kinect and OpenNI drivers publish.
pub const ROS_DEPTH_SCALE: f64 = 1000.0;

/// The tf topics.
const TF: &str = "/tf";
const TF_STATIC: &str = "/tf_static";

/// Whether an image topic holds raw `Image`s or `CompressedImage`s.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ImageType {
    Raw,
    Compressed,
}

/// An image message seen by the scan.
#[derive(Clone, Copy, Debug)]
struct Stamped {
    time: f64,
    key: MessageKey,
}

/// One frame: its two images and its pose.
#[derive(Clone, Debug)]
struct BagFrame {
    time: f64,
    colour: MessageKey,
    depth: MessageKey,
    /// Position of each image among its topic's messages in stamp order, for error messages.
    colour_number: usize,
    depth_number: usize,
    pose: Option<Pose>,
}

/// Reader of a ROS 2 bag (see the module docs).
pub struct Rosbag2Reader {
    bag: Bag,
    settings: Rosbag2Config,
    colour_type: ImageType,
    depth_type: ImageType,
    frames: Vec<BagFrame>,
    intrinsics: Intrinsics,
    intrinsics_origin: String,
    depth_scale: f32,
    has_poses: bool,
    warnings: Vec<String>,
}

/// An image topic the scan reads for a role: the configured one, or one of its image_transport
/// names.
struct ImageTopic {
    /// `"colour"` or `"depth"`.
    role: &'static str,
    name: String,
    /// Whether this is the configured topic (else an image_transport name of it).
    configured: bool,
    image_type: Option<ImageType>,
    stamps: Vec<Stamped>,
    /// An image_transport name's first malformed message: an error only if the topic is read.
    malformed: Option<DatasetError>,
}

/// The topics an image may be on when the configured `topic` is not in a bag: image_transport
/// publishes a camera's images under `TOPIC/compressed` (JPEG or PNG) and depth also under
/// `TOPIC/compressedDepth`, and `ros2 bag record` of a camera often keeps only those. The
/// configured topic comes first, then depth's own transport.
fn image_topics(role: &'static str, topic: &str) -> Vec<ImageTopic> {
    let transports: &[&str] = if role == "depth" {
        &["", "/compressedDepth", "/compressed"]
    } else {
        &["", "/compressed"]
    };
    transports
        .iter()
        .map(|suffix| ImageTopic {
            role,
            name: format!("{topic}{suffix}"),
            configured: suffix.is_empty(),
            image_type: None,
            stamps: Vec::new(),
            malformed: None,
        })
        .collect()
}

/// What the scan collects.
#[derive(Default)]
struct Scan {
    colour: Vec<Stamped>,
    depth: Vec<Stamped>,
    /// The topics the images were read from (the configured ones, or their image_transport names).
    colour_topic: String,
    depth_topic: String,
    /// Which image_transport topics were read instead of configured ones, for the warnings.
    notes: Vec<String>,
    camera_info: Option<CameraInfo>,
    poses: Vec<(f64, Pose)>,
    pose_child_frame: Option<String>,
    tf: TfTree,
    /// Topics found with a type the reader cannot use for their role.
    mistyped: Vec<(String, String, &'static str)>,
    colour_type: Option<ImageType>,
    depth_type: Option<ImageType>,
}

impl Rosbag2Reader {
    /// Opens the bag at `path` (a rosbag2 folder or one storage file) with the topics of
    /// `[dataset.rosbag2]`, and pairs, stamps and poses its frames.
    ///
    /// # Errors
    /// [`DatasetError::Bag`] for unreadable storage, a missing or mistyped topic (listing the
    /// bag's topics with their types and counts), a malformed message, or a pose source without
    /// a pose for any frame; [`DatasetError::BadConfig`] for impossible settings;
    /// [`DatasetError::Empty`] when no colour and depth image pair up.
    pub fn open(path: &Path, config: &DatasetConfig) -> Result<Self> {
        let Rosbag2Settings {
            intrinsics,
            trajectory,
            rosbag2: mut settings,
        } = reader_settings(ROSBAG2, config)?;
        let bad_config = |message: String| DatasetError::BadConfig {
            path: path.to_path_buf(),
            message,
        };
        let tolerance = settings.max_time_difference;
        if !(tolerance.is_finite() && tolerance > 0.0) {
            return Err(bad_config(format!(
                "rosbag2.max_time_difference must be a positive number of seconds, got {tolerance}"
            )));
        }
        vlem_core::ranges::number(
            tolerance,
            0.0,
            vlem_core::config::MAX_TIME_DIFFERENCE_S,
            "s",
        )
        .map_err(|range| bad_config(format!("rosbag2.max_time_difference {range}")))?;
        if settings.pose_topic.is_some() && settings.tf.is_some() {
            return Err(bad_config(
                "rosbag2: set pose_topic or tf, not both (they are two sources of the same poses)"
                    .to_owned(),
            ));
        }
        if trajectory.is_some() {
            return Err(bad_config(
                "trajectory does not apply to a bag; poses come from rosbag2.pose_topic or \
                 rosbag2.tf"
                    .to_owned(),
            ));
        }
        let selection = Selection::from_config(config, path)?;
        let scale = depth_scale(config, ROS_DEPTH_SCALE, path)?;
        let mut bag = Bag::open(path)?;
        let use_camera_info = intrinsics.is_none();
        let mut scan = scan(&mut bag, &settings, use_camera_info)?;
        // From here on the topics are where the images were found.
        settings.colour_topic = std::mem::take(&mut scan.colour_topic);
        settings.depth_topic = std::mem::take(&mut scan.depth_topic);
        let mut warnings = std::mem::take(&mut scan.notes);

        let (colour_type, depth_type) = match (scan.colour_type, scan.depth_type) {
            (Some(c), Some(d)) => (c, d),
            _ => {
                return Err(DatasetError::Bag {
                    path: path.to_path_buf(),
                    message: "no colour or no depth image in the bag".to_owned(),
                });
            }
        };
        let (intrinsics, intrinsics_origin) = match &intrinsics {
            Some(file) => {
                let dir = if path.is_dir() {
                    path
                } else {
                    path.parent().unwrap_or(Path::new("."))
                };
                let file = dir.join(file);
                (
                    crate::read_open3d_intrinsics(&file)?,
                    file.display().to_string(),
                )
            }
            None => {
                let Some(info) = &scan.camera_info else {
                    return Err(DatasetError::Bag {
                        path: path.to_path_buf(),
                        message: format!(
                            "no message on {}; set [dataset] intrinsics to an Open3D intrinsics \
                             JSON file instead",
                            settings.camera_info_topic
                        ),
                    });
                };
                if info.is_distorted() {
                    warnings.push(format!(
                        "{} has {} distortion {:?}, which vlem does not undo: rectify the images \
                         (image_proc) or expect errors that grow towards the image borders",
                        settings.camera_info_topic, info.distortion_model, info.d
                    ));
                }
                let intrinsics = info.intrinsics().map_err(|message| DatasetError::Bag {
                    path: path.to_path_buf(),
                    message: format!("{}: {message}", settings.camera_info_topic),
                })?;
                (
                    intrinsics,
                    format!("camera info {}", settings.camera_info_topic),
                )
            }
        };

        let Scan {
            mut colour,
            mut depth,
            mut poses,
            mut tf,
            pose_child_frame,
            ..
        } = scan;
        colour.sort_by(|a, b| a.time.total_cmp(&b.time));
        depth.sort_by(|a, b| a.time.total_cmp(&b.time));
        let times = |list: &[Stamped]| list.iter().map(|s| s.time).collect::<Vec<f64>>();
        let pairs = associate(&times(&depth), &times(&colour), tolerance);
        let (unpaired_colour, unpaired_depth) =
            (colour.len() - pairs.len(), depth.len() - pairs.len());
        if unpaired_colour + unpaired_depth > 0 {
            warnings.push(format!(
                "{unpaired_colour} colour and {unpaired_depth} depth images have no partner \
                 within {tolerance} s and were left out"
            ));
        }
        let mut frames: Vec<BagFrame> = pairs
            .into_iter()
            .map(|(d, c)| BagFrame {
                time: depth[d].time,
                colour: colour[c].key,
                depth: depth[d].key,
                colour_number: c,
                depth_number: d,
                pose: None,
            })
            .collect();

        let has_poses = settings.pose_topic.is_some() || settings.tf.is_some();
        if has_poses {
            let chain = match &settings.tf {
                Some([parent, child]) => {
                    tf.finish();
                    if tf.reparented > 0 {
                        warnings.push(format!(
                            "{} tf transforms gave a frame a second parent and were ignored",
                            tf.reparented
                        ));
                    }
                    let chain = tf
                        .chain(parent, child)
                        .map_err(|message| DatasetError::Bag {
                            path: path.to_path_buf(),
                            message: format!("tf {parent} -> {child}: {message}"),
                        })?;
                    warn_unless_optical(child, "tf", &mut warnings);
                    Some(chain)
                }
                None => {
                    poses.sort_by(|a, b| a.0.total_cmp(&b.0));
                    if let Some(child) = &pose_child_frame {
                        warn_unless_optical(child, "pose_topic", &mut warnings);
                    }
                    None
                }
            };
            for frame in &mut frames {
                frame.pose = match &chain {
                    Some(chain) => tf.lookup(chain, frame.time, tolerance),
                    None => pose_at(&poses, frame.time, tolerance),
                };
            }
            let before = frames.len();
            frames.retain(|f| f.pose.is_some());
            let dropped = before - frames.len();
            if frames.is_empty() && before > 0 {
                return Err(DatasetError::Bag {
                    path: path.to_path_buf(),
                    message: format!(
                        "none of the {before} frames has a pose from {} within {tolerance} s \
                         (do the pose stamps overlap the image stamps?)",
                        pose_source(&settings)
                    ),
                });
            }
            if dropped > 0 {
                warnings.push(format!(
                    "{dropped} frames have no pose from {} within {tolerance} s (before the first \
                     or after the last pose) and were left out",
                    pose_source(&settings)
                ));
            }
        }
        let frames: Vec<BagFrame> = selection
            .apply(frames)
            .into_iter()
            .map(|(_, f)| f)
            .collect();
        if frames.is_empty() {
            return Err(DatasetError::Empty {
                path: path.to_path_buf(),
            });
        }
        Ok(Self {
            bag,
            settings,
            colour_type,
            depth_type,
            frames,
            intrinsics,
            intrinsics_origin,
            depth_scale: scale,
            has_poses,
            warnings,
        })
    }

    /// The "file" an image of a frame came from, as errors name it: `bag:topic#n`.
    fn origin(&self, topic: &str, number: usize) -> PathBuf {
        PathBuf::from(format!("{}:{topic}#{number}", self.bag.path().display()))
    }

    fn decode_frame(&mut self, index: usize) -> Result<Frame> {
        let len = self.frames.len();
        let frame =
            self.frames
                .get(index)
                .cloned()
                .ok_or_else(|| DatasetError::FrameOutOfRange {
                    path: self.bag.path().to_path_buf(),
                    index,
                    len,
                })?;
        let data = self.bag.fetch(&[frame.colour, frame.depth])?;
        let colour_origin = self.origin(&self.settings.colour_topic, frame.colour_number);
        let depth_origin = self.origin(&self.settings.depth_topic, frame.depth_number);
        let cdr_error = |origin: &Path, e: super::cdr::CdrError| DatasetError::Bag {
            path: origin.to_path_buf(),
            message: e.to_string(),
        };
        let unsupported = |origin: &Path, reason: String| DatasetError::UnsupportedImage {
            path: origin.to_path_buf(),
            reason,
        };
        let colour = match self.colour_type {
            ImageType::Raw => Image::decode(&data[0])
                .map_err(|e| cdr_error(&colour_origin, e))?
                .to_colour()
                .map_err(|r| unsupported(&colour_origin, r))?,
            ImageType::Compressed => {
                let message =
                    CompressedImage::decode(&data[0]).map_err(|e| cdr_error(&colour_origin, e))?;
                colour_from_bytes(message.data, &colour_origin)?
            }
        };
        // Depth in raw units (16-bit) goes through the scale, and is checked for a plausible one
        // as every dataset's is; 32FC1 depth is in metres already.
        let (depth, scaled) = match self.depth_type {
            ImageType::Raw => {
                let image = Image::decode(&data[1]).map_err(|e| cdr_error(&depth_origin, e))?;
                let depth = image
                    .to_depth(self.depth_scale)
                    .map_err(|r| unsupported(&depth_origin, r))?;
                (depth, image.encoding != "32FC1")
            }
            ImageType::Compressed => {
                let message =
                    CompressedImage::decode(&data[1]).map_err(|e| cdr_error(&depth_origin, e))?;
                message.depth_image(self.depth_scale, &depth_origin)?
            }
        };
        if scaled {
            check_depth_scale(&depth, self.depth_scale, &depth_origin)?;
        }
        let colour_size = (colour.width(), colour.height());
        let depth_size = (depth.width(), depth.height());
        if colour_size != depth_size {
            return Err(DatasetError::SizeMismatch {
                colour: colour_origin,
                colour_size,
                depth: depth_origin,
                depth_size,
            });
        }
        let k = &self.intrinsics;
        if colour_size != (k.width, k.height) {
            return Err(DatasetError::IntrinsicsMismatch {
                image: colour_origin,
                image_size: colour_size,
                origin: self.intrinsics_origin.clone(),
                intrinsics_size: (k.width, k.height),
            });
        }
        Frame::new(index, frame.time, colour, depth, *k, frame.pose).map_err(|source| {
            DatasetError::Core {
                path: depth_origin,
                source,
            }
        })
    }
}

/// Reads the bag once, keeping what [`Rosbag2Reader::open`] needs.
fn scan(bag: &mut Bag, settings: &Rosbag2Config, use_camera_info: bool) -> Result<Scan> {
    let path = bag.path().to_path_buf();
    let mut found = Scan::default();
    let mut images = image_topics("colour", &settings.colour_topic);
    images.extend(image_topics("depth", &settings.depth_topic));
    let image_names: Vec<String> = images.iter().map(|t| t.name.clone()).collect();
    let use_tf = settings.tf.is_some();
    let wanted = |topic: &str| {
        image_names.iter().any(|name| name == topic)
            || (use_camera_info && topic == settings.camera_info_topic)
            || settings.pose_topic.as_deref() == Some(topic)
            || (use_tf && (topic == TF || topic == TF_STATIC))
    };
    let mut visit = |topic: &TopicInfo, key: MessageKey, data: &[u8]| -> Result<()> {
        let type_name = normalise_type(&topic.type_name);
        let message_error = |message: String| DatasetError::Bag {
            path: path.clone(),
            message: format!("{} message {}: {message}", topic.name, topic.count - 1),
        };
        let mut mistyped = |role: &'static str| {
            let entry = (topic.name.clone(), type_name.clone(), role);
            if !found.mistyped.contains(&entry) {
                found.mistyped.push(entry);
            }
        };
        // A topic may fill two roles (e.g. one pose topic also given as colour): check each.
        for image in images.iter_mut().filter(|t| t.name == topic.name) {
            let image_type = match type_name.as_str() {
                IMAGE => ImageType::Raw,
                COMPRESSED_IMAGE => ImageType::Compressed,
                // An image_transport name holding something else is just not an alternative.
                _ if !image.configured => continue,
                _ => {
                    mistyped(if image.role == "colour" {
                        "colour_topic (sensor_msgs/msg/Image or CompressedImage)"
                    } else {
                        "depth_topic (sensor_msgs/msg/Image or CompressedImage)"
                    });
                    continue;
                }
            };
            image.image_type = Some(image_type);
            let header = match header_of(data) {
                Ok(header) => header,
                Err(e) if image.configured => return Err(message_error(e.to_string())),
                // A bag whose configured topic is there does not fail on an alternative it
                // does not read.
                Err(e) => {
                    image.malformed.get_or_insert(message_error(e.to_string()));
                    continue;
                }
            };
            image.stamps.push(Stamped {
                time: header.seconds(),
                key,
            });
        }
        if use_camera_info && topic.name == settings.camera_info_topic {
            if type_name != CAMERA_INFO {
                mistyped("camera_info_topic (sensor_msgs/msg/CameraInfo)");
            } else if found.camera_info.is_none() {
                let info = CameraInfo::decode(data).map_err(|e| message_error(e.to_string()))?;
                found.camera_info = Some(info);
            }
        }
        if settings.pose_topic.as_deref() == Some(topic.name.as_str()) {
            let decoded = match type_name.as_str() {
                ODOMETRY => Some(StampedPose::decode_odometry(data)),
                POSE_STAMPED => Some(StampedPose::decode_pose_stamped(data)),
                _ => None,
            };
            match decoded {
                None => {
                    mistyped("pose_topic (nav_msgs/msg/Odometry or geometry_msgs/msg/PoseStamped)")
                }
                Some(decoded) => {
                    let message = decoded.map_err(|e| message_error(e.to_string()))?;
                    let pose = message.pose.map_err(message_error)?;
                    found.poses.push((message.header.seconds(), pose));
                    if !message.child_frame_id.is_empty() {
                        found.pose_child_frame = Some(message.child_frame_id);
                    }
                }
            }
        }
        if use_tf && (topic.name == TF || topic.name == TF_STATIC) {
            if type_name != TF_MESSAGE {
                mistyped("/tf and /tf_static (tf2_msgs/msg/TFMessage)");
                return Ok(());
            }
            let transforms = decode_tf_message(data).map_err(|e| message_error(e.to_string()))?;
            for t in transforms {
                let pose = t.transform.map_err(|m| {
                    message_error(format!(
                        "{} -> {}: {m}",
                        t.header.frame_id, t.child_frame_id
                    ))
                })?;
                found.tf.insert(
                    &t.header.frame_id,
                    &t.child_frame_id,
                    t.header.seconds(),
                    pose,
                    topic.name == TF_STATIC,
                );
            }
        }
        Ok(())
    };
    let topics = bag.scan(&wanted, &mut visit)?;

    let listing = || {
        let list: Vec<String> = topics
            .iter()
            .map(|t| format!("{} ({}, {} messages)", t.name, t.type_name, t.count))
            .collect();
        if list.is_empty() {
            "none".to_owned()
        } else {
            list.join(", ")
        }
    };
    if let Some((topic, type_name, role)) = found.mistyped.first() {
        return Err(DatasetError::Bag {
            path,
            message: format!(
                "topic {topic} has type {type_name}, but as {role} it needs another; the bag's \
                 topics: {}",
                listing()
            ),
        });
    }
    for (role, key) in [("colour", "colour_topic"), ("depth", "depth_topic")] {
        let mut candidates = images.iter_mut().filter(|t| t.role == role);
        let Some(chosen) = candidates.find(|t| {
            t.image_type.is_some() || (t.configured && topics.iter().any(|b| b.name == t.name))
        }) else {
            let names: Vec<String> = images
                .iter()
                .filter(|t| t.role == role)
                .map(|t| t.name.clone())
                .collect();
            return Err(DatasetError::Bag {
                path,
                message: format!(
                    "no topic {} ([dataset.rosbag2] {key}), nor its image_transport names {}; \
                     the bag's topics: {}",
                    names[0],
                    names[1..].join(", "),
                    listing()
                ),
            });
        };
        if !chosen.configured {
            found.notes.push(format!(
                "[dataset.rosbag2] {key} {} is not in the bag: reading its image_transport topic \
                 {} instead (name it as {key} to silence this)",
                if role == "colour" {
                    &settings.colour_topic
                } else {
                    &settings.depth_topic
                },
                chosen.name
            ));
        }
        if let Some(malformed) = chosen.malformed.take() {
            return Err(malformed);
        }
        let stamps = std::mem::take(&mut chosen.stamps);
        let (list, topic, slot) = if role == "colour" {
            (
                &mut found.colour,
                &mut found.colour_topic,
                &mut found.colour_type,
            )
        } else {
            (
                &mut found.depth,
                &mut found.depth_topic,
                &mut found.depth_type,
            )
        };
        *list = stamps;
        *topic = chosen.name.clone();
        *slot = chosen.image_type;
    }
    let mut needed = Vec::new();
    if use_camera_info {
        needed.push(("camera_info_topic", settings.camera_info_topic.clone()));
    }
    if let Some(topic) = &settings.pose_topic {
        needed.push(("pose_topic", topic.clone()));
    }
    for (key, topic) in needed {
        if !topics.iter().any(|t| t.name == topic) {
            return Err(DatasetError::Bag {
                path,
                message: format!(
                    "no topic {topic} ([dataset.rosbag2] {key}); the bag's topics: {}",
                    listing()
                ),
            });
        }
    }
    if use_tf && !topics.iter().any(|t| t.name == TF || t.name == TF_STATIC) {
        return Err(DatasetError::Bag {
            path,
            message: format!(
                "no /tf or /tf_static topic for [dataset.rosbag2] tf; the bag's topics: {}",
                listing()
            ),
        });
    }
    Ok(found)
}

/// A warning when the frame whose poses are used is not an optical frame by its name.
fn warn_unless_optical(frame: &str, source: &str, warnings: &mut Vec<String>) {
    if !frame.ends_with("optical_frame") {
        warnings.push(format!(
            "{source} gives poses of frame `{frame}`, whose name does not end in `optical_frame`: \
             vlem's camera frame is the optical convention (x right, y down, z forward); poses of \
             a ROS body frame (x forward, z up) put the map on its side"
        ));
    }
}

fn pose_source(settings: &Rosbag2Config) -> String {
    match (&settings.pose_topic, &settings.tf) {
        (Some(topic), _) => topic.clone(),
        (None, Some([parent, child])) => format!("tf {parent} -> {child}"),
        (None, None) => "no pose source".to_owned(),
    }
}

impl FrameSource for Rosbag2Reader {
    fn describe(&self) -> String {
        format!(
            "ROS 2 bag {} ({} + {})",
            self.bag.path().display(),
            self.settings.colour_topic,
            self.settings.depth_topic
        )
    }

    fn len(&self) -> usize {
        self.frames.len()
    }

    fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }

    fn has_poses(&self) -> bool {
        self.has_poses
    }

    fn frame(&mut self, index: usize) -> vlem_core::Result<Frame> {
        Ok(self.decode_frame(index)?)
    }

    fn warnings(&self) -> Vec<String> {
        self.warnings.clone()
    }
}

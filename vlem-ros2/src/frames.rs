//! Frames from topics: colour and depth paired by stamp, the camera from camera info, poses from
//! an optional pose topic, each malformed or unusable message counted and skipped.
//!
//! Why apart from the node: this is the part with the decisions (what pairs, what waits, what is
//! dropped and why), and it needs no DDS to test. Conversions are the bag reader's
//! ([`vlem_datasets::rosbag2::messages`]), so a live topic and a bag of it give the same frames.

use std::collections::VecDeque;

use vlem_core::{DepthImage, Frame, Intrinsics, Pose, RgbImage};
use vlem_datasets::rosbag2::poses::TfTree;

use crate::msgs::{CameraInfo, CompressedImage, Image};
use crate::status::{Counter, Status};

/// An image as it arrived: raw or compressed.
#[derive(Clone, Debug)]
pub enum ImageMessage {
    /// `sensor_msgs/msg/Image`.
    Raw(Image),
    /// `sensor_msgs/msg/CompressedImage`.
    Compressed(CompressedImage),
}

impl ImageMessage {
    /// Header stamp in seconds.
    pub fn stamp(&self) -> f64 {
        match self {
            Self::Raw(m) => m.header.stamp.seconds(),
            Self::Compressed(m) => m.header.stamp.seconds(),
        }
    }

    fn colour(&self) -> Result<RgbImage, String> {
        match self {
            Self::Raw(m) => m.view().to_colour(),
            Self::Compressed(m) => {
                vlem_datasets::colour_from_bytes(&m.data, std::path::Path::new("colour"))
                    .map_err(|e| e.to_string())
            }
        }
    }

    fn depth(&self, scale: f32) -> Result<DepthImage, String> {
        let origin = std::path::Path::new("depth");
        match self {
            Self::Raw(m) => m.view().to_depth(scale),
            Self::Compressed(m) => m
                .view()
                .depth_image(scale, origin)
                .map(|(depth, _)| depth)
                .map_err(|e| e.to_string()),
        }
    }
}

/// Stamp span (s) an unpaired image or a frame waiting for its pose is kept, measured against
/// the newest stamp seen: long enough for a late partner, short enough to bound memory.
const KEEP_SECONDS: f64 = 0.5;

/// At most this many images of one kind wait for a partner.
const MAX_WAITING: usize = 16;

/// Where frames get their poses.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PoseSource {
    /// Nowhere: the tracker estimates them.
    None,
    /// A pose topic ([`Assembler::pose`]).
    Topic,
    /// The tf tree ([`Assembler::transform`]) along `[parent, child]`.
    Tf([String; 2]),
}

/// The poses received so far.
enum Poses {
    None,
    Topic(VecDeque<(f64, Pose)>),
    Tf { tree: TfTree, frames: [String; 2] },
}

/// Assembles frames from the messages of the node's topics.
pub struct Assembler {
    tolerance: f64,
    depth_scale: f32,
    camera: Option<Intrinsics>,
    colour: VecDeque<ImageMessage>,
    depth: VecDeque<ImageMessage>,
    /// Paired images waiting for a pose at their stamp.
    paired: VecDeque<(ImageMessage, ImageMessage)>,
    poses: Poses,
    newest: f64,
}

impl Assembler {
    /// An assembler pairing within `tolerance` seconds, with poses from `source` (frames then
    /// carry the pose at their stamp).
    pub fn new(tolerance: f64, depth_scale: f32, source: PoseSource) -> Self {
        Self {
            tolerance,
            depth_scale,
            camera: None,
            colour: VecDeque::new(),
            depth: VecDeque::new(),
            paired: VecDeque::new(),
            poses: match source {
                PoseSource::None => Poses::None,
                PoseSource::Topic => Poses::Topic(VecDeque::new()),
                PoseSource::Tf(frames) => Poses::Tf {
                    tree: TfTree::default(),
                    frames,
                },
            },
            newest: f64::NEG_INFINITY,
        }
    }

    /// The camera, once camera info arrived.
    pub fn camera(&self) -> Option<Intrinsics> {
        self.camera
    }

    /// Takes camera info: the first sets the camera; a later one that differs is counted and
    /// replaces it (frames of the new size are then refused by the stream, and counted).
    pub fn camera_info(&mut self, info: &CameraInfo, status: &Status) {
        let shared = info.to_shared();
        match shared.intrinsics() {
            Ok(k) => {
                if self.camera.is_none() && shared.is_distorted() {
                    status.warn(
                        Counter::Distorted,
                        &format!(
                            "camera info has {} distortion {:?}, which vlem does not undo",
                            shared.distortion_model, shared.d
                        ),
                    );
                }
                if self.camera.is_some_and(|c| c != k) {
                    status.warn(
                        Counter::CameraChanged,
                        &format!(
                            "camera info changed to {}x{} fx {} fy {}",
                            k.width, k.height, k.fx, k.fy
                        ),
                    );
                }
                self.camera = Some(k);
            }
            Err(e) => status.warn(Counter::BadMessage, &format!("camera info: {e}")),
        }
    }

    /// Takes a colour image.
    pub fn colour(&mut self, message: ImageMessage) {
        self.newest = self.newest.max(message.stamp());
        self.colour.push_back(message);
    }

    /// Takes a depth image.
    pub fn depth(&mut self, message: ImageMessage) {
        self.newest = self.newest.max(message.stamp());
        self.depth.push_back(message);
    }

    /// Takes a pose of the camera's optical frame at `stamp` (pose topic).
    pub fn pose(&mut self, stamp: f64, pose: Pose) {
        if let Poses::Topic(poses) = &mut self.poses {
            poses.push_back((stamp, pose));
            // Poses come at odometry rates: keep a few seconds.
            while poses.len() > 1000 {
                poses.pop_front();
            }
        }
    }

    /// Takes one transform of `/tf` (`fixed = false`) or `/tf_static`.
    pub fn transform(&mut self, parent: &str, child: &str, stamp: f64, pose: Pose, fixed: bool) {
        if let Poses::Tf { tree, .. } = &mut self.poses {
            tree.insert(parent, child, stamp, pose, fixed);
        }
    }

    /// The frames that can be made now, oldest first; images that will never pair and frames
    /// that will never get a pose are counted and dropped.
    pub fn frames(&mut self, status: &Status) -> Vec<Frame> {
        self.pair();
        self.drop_stale(status);
        let mut out = Vec::new();
        if let Poses::Tf { tree, .. } = &mut self.poses {
            tree.finish();
        }
        while let Some((colour, depth)) = self.paired.front() {
            let time = depth.stamp();
            let pose = match self.pose_at(time) {
                PoseLookup::NotWanted => None,
                PoseLookup::Found(pose) => Some(pose),
                PoseLookup::Wait(_) if self.newest - time < KEEP_SECONDS => break,
                PoseLookup::Wait(why) | PoseLookup::None(why) => {
                    status.warn(Counter::NoPose, &format!("a frame without a pose: {why}"));
                    self.paired.pop_front();
                    continue;
                }
            };
            let (colour, depth) = (colour.clone(), depth.clone());
            self.paired.pop_front();
            self.forget_poses_before(time);
            match self.make_frame(&colour, &depth, time, pose) {
                Ok(frame) => out.push(frame),
                Err((counter, message)) => status.warn(counter, &message),
            }
        }
        out
    }

    /// Pairs each waiting depth image (oldest first) with the nearest colour image within the
    /// tolerance.
    fn pair(&mut self) {
        let mut d = 0;
        while d < self.depth.len() {
            let t = self.depth[d].stamp();
            let nearest = self
                .colour
                .iter()
                .enumerate()
                .map(|(i, c)| (i, (c.stamp() - t).abs()))
                .filter(|(_, dt)| *dt <= self.tolerance)
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(i, _)| i);
            match (nearest, self.depth.remove(d)) {
                (Some(c), Some(depth)) => {
                    if let Some(colour) = self.colour.remove(c) {
                        self.paired.push_back((colour, depth));
                    }
                }
                (None, Some(depth)) => {
                    self.depth.insert(d, depth);
                    d += 1;
                }
                (_, None) => break,
            }
        }
    }

    /// Drops images too old to find a partner (or too many waiting), counting them.
    fn drop_stale(&mut self, status: &Status) {
        for queue in [&mut self.colour, &mut self.depth] {
            while queue
                .front()
                .is_some_and(|m| self.newest - m.stamp() > KEEP_SECONDS)
                || queue.len() > MAX_WAITING
            {
                queue.pop_front();
                status.count(Counter::Unpaired);
            }
        }
    }

    fn pose_at(&self, time: f64) -> PoseLookup {
        let tolerance = self.tolerance;
        match &self.poses {
            Poses::None => PoseLookup::NotWanted,
            Poses::Topic(poses) => {
                let nearest = poses
                    .iter()
                    .min_by(|a, b| (a.0 - time).abs().total_cmp(&(b.0 - time).abs()));
                match nearest {
                    Some((t, pose)) if (t - time).abs() <= tolerance => PoseLookup::Found(*pose),
                    _ if poses.back().is_none_or(|(t, _)| *t < time) => {
                        PoseLookup::Wait("no pose at or after its stamp".to_owned())
                    }
                    _ => PoseLookup::None(format!("no pose within {tolerance} s of its stamp")),
                }
            }
            Poses::Tf {
                tree,
                frames: [parent, child],
            } => {
                let chain = match tree.chain(parent, child) {
                    Ok(chain) => chain,
                    Err(why) => return PoseLookup::Wait(format!("tf {parent} -> {child}: {why}")),
                };
                match tree.covered_until(&chain) {
                    Some(until) if until >= time - tolerance => {
                        match tree.lookup(&chain, time, tolerance) {
                            Some(pose) => PoseLookup::Found(pose),
                            None => PoseLookup::None(format!(
                                "tf {parent} -> {child} has no transform near its stamp"
                            )),
                        }
                    }
                    _ => PoseLookup::Wait(format!(
                        "tf {parent} -> {child} has no transform at or after its stamp"
                    )),
                }
            }
        }
    }

    /// Forgets poses the next frames cannot need (their stamps only grow).
    fn forget_poses_before(&mut self, time: f64) {
        if let Poses::Tf { tree, .. } = &mut self.poses {
            tree.forget_before(time - KEEP_SECONDS);
        }
    }

    fn make_frame(
        &self,
        colour: &ImageMessage,
        depth: &ImageMessage,
        time: f64,
        pose: Option<Pose>,
    ) -> Result<Frame, (Counter, String)> {
        let Some(camera) = self.camera else {
            return Err((
                Counter::NoCameraInfo,
                "no camera info yet: frames are skipped until it arrives".to_owned(),
            ));
        };
        let bad = |what: &str, e: String| (Counter::BadMessage, format!("{what} image: {e}"));
        let colour = colour.colour().map_err(|e| bad("colour", e))?;
        let depth = depth.depth(self.depth_scale).map_err(|e| bad("depth", e))?;
        let (cw, ch, dw, dh) = (
            colour.width(),
            colour.height(),
            depth.width(),
            depth.height(),
        );
        if (cw, ch) != (dw, dh) {
            return Err((
                Counter::SizeMismatch,
                format!(
                    "colour is {cw}x{ch} but depth {dw}x{dh}: vlem needs depth registered to \
                     colour (e.g. the aligned_depth_to_color topic)"
                ),
            ));
        }
        if (cw, ch) != (camera.width, camera.height) {
            return Err((
                Counter::SizeMismatch,
                format!(
                    "images are {cw}x{ch} but the camera info is for {}x{}",
                    camera.width, camera.height
                ),
            ));
        }
        Frame::new(0, time, colour, depth, camera, pose)
            .map_err(|e| (Counter::BadMessage, e.to_string()))
    }
}

enum PoseLookup {
    /// Frames carry no pose.
    NotWanted,
    Found(Pose),
    /// No pose yet at or after this stamp: it may still come (why, if it never does).
    Wait(String),
    /// None will come (why).
    None(String),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Header, Time};

    fn image(stamp: f64, encoding: &str, data: Vec<u8>, step: u32) -> ImageMessage {
        ImageMessage::Raw(Image {
            header: Header {
                stamp: Time::from_seconds(stamp),
                frame_id: "camera_color_optical_frame".into(),
            },
            height: 1,
            width: 2,
            encoding: encoding.into(),
            is_bigendian: 0,
            step,
            data,
        })
    }

    fn colour(stamp: f64) -> ImageMessage {
        image(stamp, "rgb8", vec![255, 0, 0, 0, 255, 0], 6)
    }

    fn depth(stamp: f64) -> ImageMessage {
        image(stamp, "16UC1", vec![0xE8, 0x03, 0, 0], 4)
    }

    fn info(width: u32) -> CameraInfo {
        CameraInfo {
            width,
            height: 1,
            k: [1.0, 0.0, 0.5, 0.0, 1.0, 0.5, 0.0, 0.0, 1.0],
            ..CameraInfo::default()
        }
    }

    #[test]
    fn pairs_by_stamp_and_counts_what_it_drops() {
        let status = Status::default();
        let mut a = Assembler::new(0.02, 1000.0, PoseSource::None);
        // Before camera info: paired frames are counted as skipped.
        a.colour(colour(1.0));
        a.depth(depth(1.004));
        assert!(a.frames(&status).is_empty());
        assert_eq!(status.get(Counter::NoCameraInfo), 1);
        a.camera_info(&info(2), &status);
        a.colour(colour(2.0));
        a.depth(depth(2.1)); // no partner within 0.02 s
        a.colour(colour(2.1));
        let frames = a.frames(&status);
        assert_eq!(frames.len(), 1);
        assert!((frames[0].timestamp - 2.1).abs() < 1e-9);
        assert_eq!(frames[0].depth.as_raw(), &[1.0, 0.0]);
        // The colour image of 2.0 is dropped once it is 0.5 s older than the newest stamp.
        a.colour(colour(2.7));
        assert!(a.frames(&status).is_empty());
        assert_eq!(status.get(Counter::Unpaired), 1);
        // A size change is refused and counted, the node goes on.
        a.camera_info(&info(4), &status);
        assert_eq!(status.get(Counter::CameraChanged), 1);
        a.depth(depth(2.7));
        assert!(a.frames(&status).is_empty());
        assert_eq!(status.get(Counter::SizeMismatch), 1);
        // A malformed image is counted.
        a.camera_info(&info(2), &status);
        a.colour(image(3.0, "mono8", vec![1, 2], 2));
        a.depth(depth(3.0));
        assert!(a.frames(&status).is_empty());
        assert_eq!(status.get(Counter::BadMessage), 1);
    }

    #[test]
    fn frames_wait_for_their_pose() {
        let status = Status::default();
        let mut a = Assembler::new(0.02, 1000.0, PoseSource::Topic);
        a.camera_info(&info(2), &status);
        a.colour(colour(1.0));
        a.depth(depth(1.0));
        // No pose at or after 1.0 yet: the frame waits.
        assert!(a.frames(&status).is_empty());
        a.pose(1.01, Pose::translation(1.0, 0.0, 0.0));
        let frames = a.frames(&status);
        assert_eq!(frames.len(), 1);
        assert_eq!(frames[0].pose.unwrap().translation.vector.x, 1.0);
        // Poses moved on past this frame without one near it: dropped and counted.
        a.pose(2.0, Pose::identity());
        a.colour(colour(1.5));
        a.depth(depth(1.5));
        assert!(a.frames(&status).is_empty());
        assert_eq!(status.get(Counter::NoPose), 1);
    }

    #[test]
    fn frames_take_their_pose_from_the_tf_chain() {
        let status = Status::default();
        let frames = ["map".to_owned(), "camera".to_owned()];
        let mut a = Assembler::new(0.02, 1000.0, PoseSource::Tf(frames));
        a.camera_info(&info(2), &status);
        a.transform(
            "base",
            "camera",
            0.0,
            Pose::translation(0.0, 0.0, 1.0),
            true,
        );
        a.transform("map", "base", 0.9, Pose::translation(1.0, 0.0, 0.0), false);
        a.colour(colour(1.0));
        a.depth(depth(1.0));
        // The moving edge ends before the frame: it waits.
        assert!(a.frames(&status).is_empty());
        a.transform("map", "base", 1.1, Pose::translation(3.0, 0.0, 0.0), false);
        let frames = a.frames(&status);
        assert_eq!(frames.len(), 1);
        let t = frames[0].pose.unwrap().translation.vector;
        assert!((t.x - 2.0).abs() < 1e-9 && (t.z - 1.0).abs() < 1e-9, "{t}");
    }
}

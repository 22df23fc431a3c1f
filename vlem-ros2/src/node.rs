//! The node: subscribes to the camera topics, runs the pipeline on the live stream, and publishes
//! the tracked pose, the map and the answers to queries.
//!
//! Threads: this one takes messages (never blocking on the pipeline: a frame that finds the
//! tracker's queue full is dropped and counted), publishes the pose and the map; the pipeline runs
//! on its own thread over a [`vlem_core::stream`] (real-time mode skips embedding frames while the
//! encoder is busy, as for a dataset); queries are answered on a third thread through the
//! [`LiveMap`], so a slow query never stalls the images.

use std::net::Ipv4Addr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use ros2_client::dds::rustdds::DomainParticipantBuilder;
use ros2_client::qos::{Durability, History, WhenFull};
use ros2_client::{
    Context, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher, QosProfile,
    Subscription,
};
use serde::Serialize;
use serde::de::DeserializeOwned;
use vlem_core::config::{DEPTH_SCALE_RANGE, MAX_TIME_DIFFERENCE_S};
use vlem_core::live::LiveMap;
use vlem_core::pipeline::{Pipeline, RunReport};
use vlem_core::ranges;
use vlem_core::stream::{FrameSender, StreamSpec, frame_stream};
use vlem_core::{CoreError, Segmenter};
use vlem_query::answer::{AnswerOptions, answer_live};
use vlem_query::grasp::GraspParams;
use vlem_query::heatmap::jet;

use crate::config::{Ros2Config, Ros2PoseType};
use crate::error::{Result, Ros2Error};
use crate::frames::{Assembler, ImageMessage, PoseSource};
use crate::msgs::{
    CameraInfo, CompressedImage, Header, Image, Odometry, PointCloud2, PoseMessage, PoseStamped,
    StringMessage, TfMessage, Time, TransformStamped,
};
use crate::status::{Counter, Status, StatusReport};

/// What a node run did.
pub struct NodeReport {
    /// The pipeline's run (`None` when no frame ever reached it, e.g. no camera info arrived,
    /// or when it stopped on an error).
    pub run: Option<RunReport>,
    /// The error the pipeline stopped on, if it did; the map up to it is kept in the pipeline's
    /// live map, so the caller can still save it.
    pub error: Option<CoreError>,
    /// The node's counters.
    pub status: StatusReport,
    /// The pipeline, back from its thread (its live map holds the map).
    pub pipeline: Pipeline,
}

/// How long the loop sleeps when no message is waiting.
const IDLE: Duration = Duration::from_millis(5);

/// Runs the node until `stop` is set, then ends the stream, waits for the pipeline to finish the
/// frames it has, and returns.
///
/// # Errors
/// [`Ros2Error::Config`] for settings that cannot work (including a `ground-truth` tracker
/// without a pose source), [`Ros2Error::Dds`] when the DDS participant or a topic cannot be
/// created. A pipeline that stops on an error ends the node too, with the error in
/// [`NodeReport::error`].
pub fn run_node(
    pipeline: Pipeline,
    segmenter: Box<dyn Segmenter>,
    settings: &Ros2Config,
    stop: &AtomicBool,
) -> Result<NodeReport> {
    validate(settings, &pipeline)?;
    let domain = domain_id(settings)?;
    let live = pipeline.live();
    let status = Arc::new(Status::default());
    let ctx = context(settings, domain)?;
    let mut node = ctx
        .new_node(
            NodeName::new("/", &settings.node_name).map_err(dds("node name"))?,
            NodeOptions::new().enable_rosout(false),
        )
        .map_err(dds("node"))?;
    let io = Io::new(&mut node, settings)?;
    eprintln!(
        "vlem ros2: node /{} on domain {} listening to {} + {} ({}), answering {}",
        settings.node_name,
        domain,
        settings.colour_topic,
        settings.depth_topic,
        settings.camera_info_topic,
        settings.query_topic
    );

    let (queries, query_thread) =
        spawn_query_worker(&mut node, settings, live.clone(), segmenter, status.clone())?;
    let source = match (&settings.pose_topic, &settings.tf) {
        (Some(_), _) => PoseSource::Topic,
        (None, Some(frames)) => PoseSource::Tf(frames.clone()),
        (None, None) => PoseSource::None,
    };
    let mut assembler = Assembler::new(
        settings.max_time_difference,
        settings.depth_scale as f32,
        source,
    );
    let mut pipeline = Some(pipeline);
    let mut running: Option<(FrameSender, JoinHandle<RunOutcome>)> = None;
    let mut published_pose: Option<usize> = None;
    let mut map_published_at: Option<(Instant, usize)> = None;
    let mut last_image = Instant::now();
    let mut images_seen = false;
    let mut stalled = false;

    while !stop.load(Ordering::Relaxed) {
        let got_images = io.take_images(&mut assembler, &status);
        let mut busy = got_images;
        busy |= io.take_camera_info(&mut assembler, &status);
        busy |= io.take_poses(&mut assembler, &status);
        busy |= io.take_transforms(&mut assembler, &status);
        while let Some(text) = io.take_query(&status) {
            busy = true;
            match queries.try_send(text) {
                Ok(()) => {}
                Err(mpsc::TrySendError::Full(text)) => status.warn(
                    Counter::QueriesDropped,
                    &format!(
                        "the query {} was dropped: {QUERY_QUEUE} queries are waiting",
                        for_log(&text)
                    ),
                ),
                Err(mpsc::TrySendError::Disconnected(_)) => {
                    status.warn(Counter::QueryErrors, "the query thread has stopped");
                }
            }
        }
        if got_images {
            last_image = Instant::now();
            images_seen = true;
            stalled = false;
        }
        if !stalled && last_image.elapsed().as_secs_f64() > settings.stall_seconds {
            stalled = true;
            if images_seen {
                status.warn(
                    Counter::Stalls,
                    &format!(
                        "no image for {} s: is the camera still publishing?",
                        settings.stall_seconds
                    ),
                );
            } else {
                eprintln!(
                    "vlem ros2: no image on {} or {} yet; check the topic names, the domain \
                     ({}) and that the camera publishes (`ros2 topic list`, `ros2 topic hz`)",
                    settings.colour_topic, settings.depth_topic, domain
                );
            }
        }
        // The pipeline starts with the first camera info: its stream is for that camera.
        if running.is_none()
            && let Some(camera) = assembler.camera()
            && let Some(p) = pipeline.take()
        {
            running = Some(start_pipeline(p, camera, settings)?);
        }
        for frame in assembler.frames(&status) {
            let Some((sender, _)) = &running else {
                break;
            };
            match sender.try_send(frame) {
                Ok(Some(_)) => status.count(Counter::FramesQueued),
                Ok(None) => status.count(Counter::DroppedBusy),
                Err(CoreError::FrameRefused { reason }) => {
                    status.warn(Counter::Refused, &format!("frame refused: {reason}"));
                }
                Err(_) => {
                    // The pipeline stopped reading: it ended on an error, reported below.
                    stop_reading(&status);
                    break;
                }
            }
        }
        if running.as_ref().is_some_and(|(_, h)| h.is_finished()) {
            break;
        }
        publish_pose(&io, &live, settings, &mut published_pose);
        publish_map(&io, &live, settings, &status, &mut map_published_at);
        if !busy {
            std::thread::sleep(IDLE);
        }
    }

    drop(queries);
    let _ = query_thread.join();
    let (run, error, pipeline) = match running {
        Some((sender, handle)) => {
            sender.finish();
            let outcome = handle
                .join()
                .map_err(|_| Ros2Error::Config("the pipeline thread panicked".into()))?;
            match outcome.report {
                Ok(report) => (Some(report), None, outcome.pipeline),
                Err(e) => (None, Some(e), outcome.pipeline),
            }
        }
        None => match pipeline {
            Some(p) => (None, None, p),
            None => return Err(Ros2Error::Config("the pipeline was lost".into())),
        },
    };
    // One last pose and map, so a late subscriber of a short run sees the final state.
    publish_pose(&io, &live, settings, &mut published_pose);
    map_published_at = None;
    publish_map(&io, &live, settings, &status, &mut map_published_at);
    Ok(NodeReport {
        run,
        error,
        status: status.report(),
        pipeline,
    })
}

fn stop_reading(status: &Status) {
    status.warn(
        Counter::Refused,
        "the pipeline stopped reading frames; the node ends",
    );
}

struct RunOutcome {
    pipeline: Pipeline,
    report: vlem_core::Result<RunReport>,
}

fn start_pipeline(
    mut pipeline: Pipeline,
    camera: vlem_core::Intrinsics,
    settings: &Ros2Config,
) -> Result<(FrameSender, JoinHandle<RunOutcome>)> {
    let spec = StreamSpec {
        description: format!(
            "the ROS 2 topics {} + {}",
            settings.colour_topic, settings.depth_topic
        ),
        intrinsics: camera,
        has_poses: settings.pose_topic.is_some() || settings.tf.is_some(),
        capacity: settings.queue,
        max_stamp_jump: settings.max_stamp_jump,
    };
    let (sender, mut stream) = frame_stream(spec)?;
    let handle = std::thread::Builder::new()
        .name("vlem-ros2-pipeline".into())
        .spawn(move || {
            let report = pipeline.run(&mut stream, None, &|_| {});
            RunOutcome { pipeline, report }
        })
        .map_err(|e| Ros2Error::Config(format!("cannot start the pipeline thread: {e}")))?;
    eprintln!(
        "vlem ros2: camera {}x{} (fx {}, fy {}); mapping",
        camera.width, camera.height, camera.fx, camera.fy
    );
    Ok((sender, handle))
}

fn validate(settings: &Ros2Config, pipeline: &Pipeline) -> Result<()> {
    validate_settings(settings)?;
    if pipeline.tracker().needs_dataset_poses()
        && settings.pose_topic.is_none()
        && settings.tf.is_none()
    {
        return Err(Ros2Error::Config(format!(
            "the tracker `{}` reads poses from the source, but [ros2] has no pose_topic or tf; \
             set one or use [tracker] kind = \"odometry\" or \"frame-to-model\"",
            pipeline.tracker().name()
        )));
    }
    Ok(())
}

/// The checks of `[ros2]` alone: every number in its range (docs/config-ranges.md).
fn validate_settings(settings: &Ros2Config) -> Result<()> {
    let bad = |message: String| Err(Ros2Error::Config(message));
    let in_range = |key: &str, checked: std::result::Result<f64, String>| {
        checked
            .map(|_| ())
            .map_err(|range| Ros2Error::Config(format!("[ros2] {key} {range}")))
    };
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if !positive(settings.max_time_difference) {
        return bad(format!(
            "[ros2] max_time_difference must be a positive number of seconds, got {}",
            settings.max_time_difference
        ));
    }
    in_range(
        "max_time_difference",
        ranges::number(
            settings.max_time_difference,
            0.0,
            MAX_TIME_DIFFERENCE_S,
            "s",
        ),
    )?;
    in_range(
        "depth_scale",
        ranges::number(
            settings.depth_scale,
            DEPTH_SCALE_RANGE.0,
            DEPTH_SCALE_RANGE.1,
            "raw units per metre",
        ),
    )?;
    if !positive(settings.stall_seconds) {
        return bad(format!(
            "[ros2] stall_seconds must be positive, got {}",
            settings.stall_seconds
        ));
    }
    if settings.map_rate != 0.0 {
        in_range(
            "map_rate",
            ranges::number(settings.map_rate, MAP_RATE_HZ.0, MAP_RATE_HZ.1, "Hz").map_err(
                |range| format!("must be 0 (never) or {}", range.trim_start_matches("must ")),
            ),
        )?;
    }
    if let Err(range) = ranges::count(settings.map_max_points, 1, MAX_MAP_MESSAGE_POINTS, "points")
    {
        return bad(format!("[ros2] map_max_points {range}"));
    }
    let domain = domain_id(settings)?;
    if let Err(range) = ranges::count(domain, 0, MAX_DOMAIN_ID, "") {
        return bad(format!(
            "[ros2] domain_id (or $ROS_DOMAIN_ID) {range}: DDS derives its ports from it and has \
             domains 0–{MAX_DOMAIN_ID} only"
        ));
    }
    if settings.queue == 0 {
        return bad("[ros2] queue must be at least 1".into());
    }
    if settings.pose_topic.is_some() && settings.tf.is_some() {
        return bad(
            "[ros2]: set pose_topic or tf, not both (two sources of the same poses)".into(),
        );
    }
    Ok(())
}

/// The largest DDS domain id: the RTPS port formula (7400 + 250 × id + …) leaves the 16-bit port
/// range above it.
const MAX_DOMAIN_ID: u16 = 232;
/// The map publication rates accepted besides 0 (never): a period between 1000 s and 1 ms.
const MAP_RATE_HZ: (f64, f64) = (0.001, 1000.0);
/// The most points one published map message may carry (36 bytes each in the PointCloud2).
const MAX_MAP_MESSAGE_POINTS: usize = 50_000_000;

/// `[ros2] domain_id`, else `$ROS_DOMAIN_ID`, else 0.
///
/// # Errors
/// [`Ros2Error::Config`] for a `$ROS_DOMAIN_ID` that is not a number (it used to fall back to 0
/// silently, joining another domain than the user's other nodes).
fn domain_id(settings: &Ros2Config) -> Result<u16> {
    if let Some(id) = settings.domain_id {
        return Ok(id);
    }
    match std::env::var("ROS_DOMAIN_ID") {
        Ok(text) if !text.trim().is_empty() => text.trim().parse().map_err(|_| {
            Ros2Error::Config(format!(
                "$ROS_DOMAIN_ID is `{text}`, not a domain id (0–{MAX_DOMAIN_ID})"
            ))
        }),
        _ => Ok(0),
    }
}

fn dds<E: std::fmt::Debug>(what: &'static str) -> impl Fn(E) -> Ros2Error {
    move |e| Ros2Error::Dds(format!("{what}: {e:?}"))
}

fn context(settings: &Ros2Config, domain: u16) -> Result<Context> {
    let mut builder = DomainParticipantBuilder::new(domain);
    if settings.localhost_only {
        builder = builder.with_only_networks([Ipv4Addr::LOCALHOST]);
    }
    let participant = builder.build().map_err(dds("DDS participant"))?;
    Context::from_domain_participant(participant).map_err(dds("ROS 2 context"))
}

/// rclcpp's `SensorDataQoS`: best effort (so it matches any camera driver's writer), keep last 5.
fn sensor_qos() -> QosProfile {
    QosProfile::subscription_default()
        .reliability_best_effort()
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 5 })
}

/// rclcpp's default `QoS(10)`: reliable, volatile, keep last 10.
fn reliable_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::Wait(Duration::from_millis(100)))
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 })
}

/// tf2's listener QoS for `/tf`: reliable, keep last 100.
fn tf_qos() -> QosProfile {
    reliable_qos().history(History::KeepLast { depth: 100 })
}

/// tf2's static listener QoS: reliable, transient local (latched), keep last 1.
fn tf_static_qos() -> QosProfile {
    reliable_qos()
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

/// Whether an image topic carries `CompressedImage` (image_transport's topic naming).
fn is_compressed_topic(topic: &str) -> bool {
    topic.ends_with("/compressed") || topic.ends_with("/compressedDepth")
}

fn subscribe<M: DeserializeOwned + 'static>(
    node: &mut Node,
    topic: &str,
    (package, name): (&str, &str),
    qos: QosProfile,
) -> Result<Subscription<M>> {
    let parsed = Name::parse(topic)
        .map_err(|e| Ros2Error::Config(format!("topic name `{topic}`: {e:?}")))?;
    let topic_handle = node
        .create_topic(&parsed, MessageTypeName::new(package, name), &qos)
        .map_err(dds("topic"))?;
    node.create_subscription(&topic_handle, Some(qos))
        .map_err(dds("subscription"))
}

fn advertise<M: Serialize>(
    node: &mut Node,
    topic: &str,
    (package, name): (&str, &str),
) -> Result<Publisher<M>> {
    let qos = reliable_qos();
    let parsed = Name::parse(topic)
        .map_err(|e| Ros2Error::Config(format!("topic name `{topic}`: {e:?}")))?;
    let topic_handle = node
        .create_topic(&parsed, MessageTypeName::new(package, name), &qos)
        .map_err(dds("topic"))?;
    node.create_publisher(&topic_handle, Some(qos))
        .map_err(dds("publisher"))
}

const IMAGE: (&str, &str) = ("sensor_msgs", "Image");
const COMPRESSED_IMAGE: (&str, &str) = ("sensor_msgs", "CompressedImage");
const POINT_CLOUD2: (&str, &str) = ("sensor_msgs", "PointCloud2");
const POSE_STAMPED: (&str, &str) = ("geometry_msgs", "PoseStamped");
const TF_MESSAGE: (&str, &str) = ("tf2_msgs", "TFMessage");

/// A subscription to raw or compressed images.
enum ImageSubscription {
    Raw(Subscription<Image>),
    Compressed(Subscription<CompressedImage>),
}

impl ImageSubscription {
    fn new(node: &mut Node, topic: &str) -> Result<Self> {
        Ok(if is_compressed_topic(topic) {
            Self::Compressed(subscribe(node, topic, COMPRESSED_IMAGE, sensor_qos())?)
        } else {
            Self::Raw(subscribe(node, topic, IMAGE, sensor_qos())?)
        })
    }

    /// The next waiting image, `None` when there is none; a message that fails to deserialise
    /// is counted and skipped.
    fn take(&self, status: &Status) -> Option<ImageMessage> {
        let taken = match self {
            Self::Raw(s) => s
                .take()
                .map(|m| m.map(|(m, _)| ImageMessage::Raw(m)))
                .map_err(|e| format!("{e:?}")),
            Self::Compressed(s) => s
                .take()
                .map(|m| m.map(|(m, _)| ImageMessage::Compressed(m)))
                .map_err(|e| format!("{e:?}")),
        };
        taken.unwrap_or_else(|e| {
            status.warn(Counter::BadMessage, &format!("image message: {e}"));
            None
        })
    }
}

enum PoseSubscription {
    Odometry(Subscription<Odometry>),
    PoseStamped(Subscription<PoseStamped>),
}

/// The node's subscriptions and the publishers of this thread.
struct Io {
    colour: ImageSubscription,
    depth: ImageSubscription,
    camera_info: Subscription<CameraInfo>,
    pose: Option<PoseSubscription>,
    /// `/tf` and `/tf_static`, when poses come from tf.
    tf_in: Option<(Subscription<TfMessage>, Subscription<TfMessage>)>,
    query: Subscription<StringMessage>,
    pose_out: Publisher<PoseStamped>,
    tf: Publisher<TfMessage>,
    map: Publisher<PointCloud2>,
}

impl Io {
    fn new(node: &mut Node, settings: &Ros2Config) -> Result<Self> {
        let pose = match &settings.pose_topic {
            None => None,
            Some(topic) => Some(match settings.pose_type {
                Ros2PoseType::Odometry => PoseSubscription::Odometry(subscribe(
                    node,
                    topic,
                    ("nav_msgs", "Odometry"),
                    reliable_qos(),
                )?),
                Ros2PoseType::PoseStamped => PoseSubscription::PoseStamped(subscribe(
                    node,
                    topic,
                    POSE_STAMPED,
                    reliable_qos(),
                )?),
            }),
        };
        let tf_in = match &settings.tf {
            None => None,
            Some(_) => Some((
                subscribe(node, "/tf", TF_MESSAGE, tf_qos())?,
                subscribe(node, "/tf_static", TF_MESSAGE, tf_static_qos())?,
            )),
        };
        Ok(Self {
            tf_in,
            colour: ImageSubscription::new(node, &settings.colour_topic)?,
            depth: ImageSubscription::new(node, &settings.depth_topic)?,
            camera_info: subscribe(
                node,
                &settings.camera_info_topic,
                ("sensor_msgs", "CameraInfo"),
                sensor_qos(),
            )?,
            pose,
            query: subscribe(
                node,
                &settings.query_topic,
                ("std_msgs", "String"),
                reliable_qos(),
            )?,
            pose_out: advertise(node, &settings.pose_out_topic, POSE_STAMPED)?,
            tf: advertise(node, "/tf", TF_MESSAGE)?,
            map: advertise(node, &settings.map_topic, POINT_CLOUD2)?,
        })
    }

    /// Moves every waiting image into the assembler; whether there was one.
    fn take_images(&self, assembler: &mut Assembler, status: &Status) -> bool {
        let mut any = false;
        while let Some(image) = self.colour.take(status) {
            status.count(Counter::Colour);
            assembler.colour(image);
            any = true;
        }
        while let Some(image) = self.depth.take(status) {
            status.count(Counter::Depth);
            assembler.depth(image);
            any = true;
        }
        any
    }

    fn take_camera_info(&self, assembler: &mut Assembler, status: &Status) -> bool {
        let mut any = false;
        loop {
            match self.camera_info.take() {
                Ok(Some((info, _))) => {
                    assembler.camera_info(&info, status);
                    any = true;
                }
                Ok(None) => return any,
                Err(e) => {
                    status.warn(Counter::BadMessage, &format!("camera info: {e:?}"));
                    return any;
                }
            }
        }
    }

    fn take_poses(&self, assembler: &mut Assembler, status: &Status) -> bool {
        let mut any = false;
        loop {
            let taken = match &self.pose {
                None => return false,
                Some(PoseSubscription::Odometry(s)) => s
                    .take()
                    .map(|m| m.map(|(m, _)| (m.header, m.pose.pose)))
                    .map_err(|e| format!("{e:?}")),
                Some(PoseSubscription::PoseStamped(s)) => s
                    .take()
                    .map(|m| m.map(|(m, _)| (m.header, m.pose)))
                    .map_err(|e| format!("{e:?}")),
            };
            match taken {
                Ok(Some((header, pose))) => {
                    any = true;
                    match pose.to_pose() {
                        Ok(pose) => assembler.pose(header.stamp.seconds(), pose),
                        Err(e) => status.warn(Counter::BadMessage, &format!("pose: {e}")),
                    }
                }
                Ok(None) => return any,
                Err(e) => {
                    status.warn(Counter::BadMessage, &format!("pose message: {e}"));
                    return any;
                }
            }
        }
    }

    fn take_transforms(&self, assembler: &mut Assembler, status: &Status) -> bool {
        let Some((moving, fixed)) = &self.tf_in else {
            return false;
        };
        let mut any = false;
        for (subscription, is_static) in [(moving, false), (fixed, true)] {
            loop {
                match subscription.take() {
                    Ok(Some((message, _))) => {
                        any = true;
                        for t in message.transforms {
                            match t.transform.to_pose() {
                                Ok(pose) => assembler.transform(
                                    &t.header.frame_id,
                                    &t.child_frame_id,
                                    t.header.stamp.seconds(),
                                    pose,
                                    is_static,
                                ),
                                Err(e) => status.warn(
                                    Counter::BadMessage,
                                    &format!(
                                        "tf {} -> {}: {e}",
                                        t.header.frame_id, t.child_frame_id
                                    ),
                                ),
                            }
                        }
                    }
                    Ok(None) => break,
                    Err(e) => {
                        status.warn(Counter::BadMessage, &format!("tf message: {e:?}"));
                        break;
                    }
                }
            }
        }
        any
    }

    fn take_query(&self, status: &Status) -> Option<String> {
        match self.query.take() {
            Ok(message) => message.map(|(m, _)| m.data),
            Err(e) => {
                status.warn(Counter::BadMessage, &format!("query message: {e:?}"));
                None
            }
        }
    }
}

fn header(frame: &str, stamp: Time) -> Header {
    Header {
        stamp,
        frame_id: frame.to_owned(),
    }
}

/// Publishes the tracker's latest pose (PoseStamped and tf) when it is new.
fn publish_pose(io: &Io, live: &LiveMap, settings: &Ros2Config, last: &mut Option<usize>) {
    let Some(latest) = live.latest_pose() else {
        return;
    };
    if *last == Some(latest.index) {
        return;
    }
    *last = Some(latest.index);
    let stamp = Time::from_seconds(latest.timestamp);
    let pose = PoseMessage::from_pose(&latest.pose);
    // Publishing fails only when the writer's queue is full: the next pose replaces this one.
    let _ = io.pose_out.publish(PoseStamped {
        header: header(&settings.map_frame, stamp),
        pose,
    });
    let _ = io.tf.publish(TfMessage {
        transforms: vec![TransformStamped {
            header: header(&settings.map_frame, stamp),
            child_frame_id: settings.camera_frame.clone(),
            transform: pose,
        }],
    });
}

/// Publishes the map at `map_rate` when it changed since the last time.
fn publish_map(
    io: &Io,
    live: &LiveMap,
    settings: &Ros2Config,
    status: &Status,
    last: &mut Option<(Instant, usize)>,
) {
    if settings.map_rate <= 0.0 || !live.has_map() {
        return;
    }
    let period = Duration::from_secs_f64(1.0 / settings.map_rate);
    if last.is_some_and(|(t, _)| t.elapsed() < period) {
        return;
    }
    let frames = live.status().frames_integrated;
    if frames == 0 || last.is_some_and(|(_, f)| f == frames) {
        return;
    }
    let Ok(points) = live.read(|view| view.map.coloured_points()) else {
        return;
    };
    let n = points.vertices.len();
    let step = n.div_ceil(settings.map_max_points.max(1)).max(1);
    let positions: Vec<[f32; 3]> = points.vertices.iter().step_by(step).copied().collect();
    let colours: Vec<[u8; 3]> = points.colours.iter().step_by(step).copied().collect();
    let stamp = live
        .latest_pose()
        .map_or(Time::default(), |p| Time::from_seconds(p.timestamp));
    let cloud = PointCloud2::xyz_rgb(
        header(&settings.map_frame, stamp),
        &positions,
        &colours,
        None,
    );
    if io.map.publish(cloud).is_ok() {
        status.count(Counter::MapsPublished);
    }
    *last = Some((Instant::now(), frames));
}

/// Queries waiting for the query thread at most; more are dropped and counted, so a burst cannot
/// delay later queries (or the end of the node) by more than this many answers.
pub const QUERY_QUEUE: usize = 16;

/// Characters of a query that log lines show.
const LOGGED_QUERY_CHARS: usize = 80;

/// `text` quoted for a log line: at most [`LOGGED_QUERY_CHARS`] characters, then how long it was.
fn for_log(text: &str) -> String {
    match text.char_indices().nth(LOGGED_QUERY_CHARS) {
        Some((cut, _)) => format!("\"{}…\" ({} bytes)", &text[..cut], text.len()),
        None => format!("\"{text}\""),
    }
}

/// A query's text and whether it asks for a grasp: the prefix `grasp:` in any case (`Grasp:`,
/// `GRASP:`), as docs/ros2.md documents, with the spaces around the text removed.
fn parse_query(text: &str) -> (String, bool) {
    let text = text.trim();
    match text.get(..6) {
        Some(prefix) if prefix.eq_ignore_ascii_case("grasp:") => {
            (text[6..].trim().to_owned(), true)
        }
        _ => (text.to_owned(), false),
    }
}

/// The query thread: answers each text on the live map and publishes the heatmap, the best set
/// and, for `grasp: TEXT`, the grasp.
fn spawn_query_worker(
    node: &mut Node,
    settings: &Ros2Config,
    live: LiveMap,
    segmenter: Box<dyn Segmenter>,
    status: Arc<Status>,
) -> Result<(mpsc::SyncSender<String>, JoinHandle<()>)> {
    let heatmap: Publisher<PointCloud2> = advertise(node, &settings.heatmap_topic, POINT_CLOUD2)?;
    let best: Publisher<PointCloud2> = advertise(node, &settings.best_topic, POINT_CLOUD2)?;
    let grasp: Publisher<PoseStamped> = advertise(node, &settings.grasp_topic, POSE_STAMPED)?;
    let frame = settings.map_frame.clone();
    let max_points = settings.map_max_points.max(1);
    let (sender, receiver) = mpsc::sync_channel::<String>(QUERY_QUEUE);
    let handle = std::thread::Builder::new()
        .name("vlem-ros2-query".into())
        .spawn(move || {
            for text in receiver {
                let (text, wants_grasp) = parse_query(&text);
                if text.is_empty() {
                    eprintln!("vlem ros2: an empty query was ignored");
                    continue;
                }
                let options = AnswerOptions {
                    grasp: wants_grasp.then(GraspParams::default),
                    indices: false,
                };
                let answered = match answer_live(
                    &live,
                    segmenter.as_ref(),
                    std::slice::from_ref(&text),
                    &options,
                ) {
                    Ok(answered) => answered,
                    Err(e) => {
                        status.warn(
                            Counter::QueryErrors,
                            &format!("query {} failed: {e}", for_log(&text)),
                        );
                        continue;
                    }
                };
                let (answered, positions) = answered;
                let stamp = live
                    .latest_pose()
                    .map_or(Time::default(), |p| Time::from_seconds(p.timestamp));
                let head = || header(&frame, stamp);
                let scores = answered.scores.scores.first().cloned().unwrap_or_default();
                let sent = |result: std::result::Result<(), String>, what: &str| {
                    if let Err(e) = result {
                        status.warn(Counter::QueryErrors, &format!("publishing the {what}: {e}"));
                    }
                };
                // Published clouds are capped like the map: an even subsample of larger ones.
                let step = positions.len().div_ceil(max_points).max(1);
                let shown: Vec<usize> = (0..positions.len()).step_by(step).collect();
                let pick = |indices: &[usize]| -> (Vec<[f32; 3]>, Vec<[u8; 3]>, Vec<f32>) {
                    let mut out = (Vec::new(), Vec::new(), Vec::new());
                    for &i in indices {
                        if let (Some(p), Some(&s)) = (positions.get(i), scores.get(i)) {
                            out.0.push(*p);
                            out.1.push(jet(s));
                            out.2.push(s);
                        }
                    }
                    out
                };
                let (points, colours, values) = pick(&shown);
                sent(
                    heatmap
                        .publish(PointCloud2::xyz_rgb(
                            head(),
                            &points,
                            &colours,
                            Some(("similarity", &values)),
                        ))
                        .map_err(|e| e.to_string()),
                    "heatmap",
                );
                let best_set = answered
                    .sets
                    .iter()
                    .filter(|s| s.query == 0 && !s.indices.is_empty())
                    .max_by(|a, b| a.mean_score.total_cmp(&b.mean_score));
                let best_indices: Vec<usize> = best_set.map_or_else(Vec::new, |set| {
                    let step = set.indices.len().div_ceil(max_points).max(1);
                    set.indices.iter().step_by(step).copied().collect()
                });
                let (points, colours, _) = pick(&best_indices);
                sent(
                    best.publish(PointCloud2::xyz_rgb(head(), &points, &colours, None))
                        .map_err(|e| e.to_string()),
                    "best set",
                );
                if let Some(Some(g)) = answered.grasps.first() {
                    let pose = vlem_core::Pose::from_parts(
                        nalgebra::Translation3::new(g.position[0], g.position[1], g.position[2]),
                        g.rotation,
                    );
                    sent(
                        grasp
                            .publish(PoseStamped {
                                header: head(),
                                pose: PoseMessage::from_pose(&pose),
                            })
                            .map_err(|e| e.to_string()),
                        "grasp",
                    );
                }
                status.count(Counter::Queries);
                eprintln!(
                    "vlem ros2: answered {} on {} points ({} frames), best set {} points{}",
                    for_log(&text),
                    positions.len(),
                    answered.answer.frames_integrated,
                    points.len(),
                    if wants_grasp { ", grasp published" } else { "" }
                );
            }
        })
        .map_err(|e| Ros2Error::Config(format!("cannot start the query thread: {e}")))?;
    Ok((sender, handle))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_grasp_prefix_is_read_in_any_case() {
        for text in ["grasp: mug", "GRASP: mug", " Grasp:mug ", "gRaSp:   mug"] {
            assert_eq!(parse_query(text), ("mug".to_owned(), true), "{text:?}");
        }
        assert_eq!(parse_query(" red mug "), ("red mug".to_owned(), false));
        assert_eq!(parse_query("grasp"), ("grasp".to_owned(), false));
        // A multi-byte character where the prefix would end is no prefix, and no panic.
        assert_eq!(parse_query("grasé: x"), ("grasé: x".to_owned(), false));
    }

    #[test]
    fn out_of_range_settings_are_refused_naming_key_range_and_value() {
        assert!(validate_settings(&Ros2Config::default()).is_ok());
        /// Puts one setting out of its range.
        type Change = fn(&mut Ros2Config);
        let cases: [(Change, &str); 6] = [
            (
                |c| c.map_rate = 1e-30,
                "[ros2] map_rate must be 0 (never) or lie in 0.001–1000 Hz, got 1e-30",
            ),
            (
                |c| c.domain_id = Some(300),
                "domain_id (or $ROS_DOMAIN_ID) must lie in 0–232",
            ),
            (
                |c| c.depth_scale = 1e300,
                "[ros2] depth_scale must lie in 0.001–1e7",
            ),
            (
                |c| c.max_time_difference = 60.0,
                "[ros2] max_time_difference must lie in 0–1 s",
            ),
            (
                |c| c.map_max_points = 0,
                "[ros2] map_max_points must lie in 1–50000000",
            ),
            (|c| c.queue = 0, "[ros2] queue must be at least 1"),
        ];
        for (change, expected) in cases {
            let mut settings = Ros2Config::default();
            change(&mut settings);
            let error = validate_settings(&settings).unwrap_err().to_string();
            assert!(error.contains(expected), "{error}");
        }
        // Never (0) stays allowed.
        let never = Ros2Config {
            map_rate: 0.0,
            ..Ros2Config::default()
        };
        assert!(validate_settings(&never).is_ok());
    }

    #[test]
    fn long_queries_are_cut_in_log_lines() {
        assert_eq!(for_log("mug"), "\"mug\"");
        let long = "é".repeat(1000);
        let shown = for_log(&long);
        assert!(shown.ends_with("…\" (2000 bytes)"), "{shown}");
        assert_eq!(
            shown.chars().filter(|c| *c == 'é').count(),
            LOGGED_QUERY_CHARS
        );
    }
}

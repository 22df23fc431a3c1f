#!/usr/bin/env python3
"""Write the ROS 2 bags that vlem's rosbag2 reader is tested against.

Why this exists
---------------
vlem reads rosbag2 recordings (MCAP and SQLite3 storage) itself, in Rust. Its tests must not
read bags that vlem wrote, or a shared misunderstanding of the format would pass unnoticed.
These bags are therefore written by an independent implementation, the `rosbags` Python
package (Ternaris), from the real frames committed in ../../../../data/living-room, so that
the tests can compare what vlem decodes with the committed JPEG/PNG files and trajectory.

How to run
----------
    python3 -m venv ../../../../bench/.venv-rosbags     # git-ignored (bench/.venv*)
    ../../../../bench/.venv-rosbags/bin/pip install rosbags==0.11.9 numpy pillow
    ../../../../bench/.venv-rosbags/bin/python make_bags.py

It deletes and rewrites the four bag folders beside this file. The output is deterministic:
no clock, no randomness; the same inputs and package versions give byte-identical files
(the MCAP header names the writer, "rosbags-0.11.9", and PNG bytes depend on zlib).

What the bags hold
------------------
Stamps: frame i has t_i = 1_700_000_000 s + round(i * 1e9 / 30) ns. Every header.stamp is t_i
of its frame and every record (log) time equals its header stamp, unless noted.
All messages are CDR little-endian; types come from the ROS 2 Humble typestore.

living-room-mcap/, living-room-sqlite/ (same messages, MCAP and SQLite3), frames 0..4:
  /camera/color/image_raw/compressed                    sensor_msgs/msg/CompressedImage
      "rgb8; jpeg compressed bgr8", the committed JPEG bytes; plus one extra leading message at
      t_0 - 1/30 s (frame 0's JPEG) that has no depth partner.
  /camera/aligned_depth_to_color/image_raw/compressed   CompressedImage
      "16UC1; png compressed", the committed 16-bit PNG bytes (millimetres, 0 = invalid).
  /camera/aligned_depth_to_color/image_raw/compressedDepth    CompressedImage
      "16UC1; compressedDepth png": 12-byte ConfigHeader + the committed PNG bytes.
  /camera/aligned_depth_to_color/image_raw/compressedDepth32  CompressedImage
      "32FC1; compressedDepth png": 12-byte ConfigHeader + inverse-depth 16-bit PNG, quantised
      exactly as compressed_depth_image_transport does for a 32FC1 image in metres.
  /camera/color/camera_info             sensor_msgs/msg/CameraInfo  640x480, fx=fy=525, plumb_bob 0
  /camera/color/camera_info_distorted   CameraInfo, same but d = [0.1, -0.05, 0.001, 0, 0]
  /tf_static     tf2_msgs/msg/TFMessage, one message at t_0: base_link->camera_link,
                 camera_link->camera_color_optical_frame
  /tf            TFMessage per frame: map->odom, odom->base_link (so that the chain
                 map->...->camera_color_optical_frame is the trajectory pose), odom->wheel_left
  /camera/pose   geometry_msgs/msg/PoseStamped, "map", the trajectory pose
  /odom          nav_msgs/msg/Odometry, "map" -> "camera_color_optical_frame", the trajectory pose
  /chatter       std_msgs/msg/String, one message "hello" at t_0

raw-mcap/, raw-sqlite/ (same messages), frames 0..2, images subsampled by 8 (80x60: pixel (x, y)
is pixel (8x, 8y) of the original), all sensor_msgs/msg/Image, "camera_color_optical_frame":
  /raw/rgb8, /raw/bgr8 (step 244: 4 bytes 0xAB padding per row), /raw/rgba8, /raw/bgra8
  (alpha 255), /raw/mono8 (PIL "L" grey), /raw/depth_16uc1 (mm), /raw/depth_32fc1 (metres as
  float32(mm) / 1000.0f, NaN where invalid); /raw/camera_info (intrinsics / 8); /raw/pose.
"""

from __future__ import annotations

import io
import math
import shutil
import struct
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_typestore

HERE = Path(__file__).resolve().parent
FRAMES = HERE.parents[3] / "data" / "living-room"

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types  # message classes by type name, e.g. T["sensor_msgs/msg/Image"]

T0_NS = 1_700_000_000 * 10**9
OPTICAL = "camera_color_optical_frame"
FX = FY = 525.0
CX, CY = 319.5, 239.5
WIDTH, HEIGHT = 640, 480

# compressed_depth_image_transport (ros-perception/image_transport_plugins, codec.cpp and
# compression_common.h): the payload starts with `struct ConfigHeader { compressionFormat
# format; float depthParam[2]; }`, 12 bytes in host (little-endian) order. The encoder always
# sets format = INV_DEPTH (= 0, after UNDEFINED = -1). For 32FC1 it stores
# depthQuantA = z0 * (z0 + 1) and depthQuantB = 1 - depthQuantA / depth_max (float32), with the
# publisher defaults depth_quantization z0 = 100 and depth_max = 10 m; for 16UC1 it never sets
# depthParam (uninitialised memory upstream; we write zeros).
INV_DEPTH = 0
DEPTH_QUANTIZATION = np.float32(100.0)
DEPTH_MAX = np.float32(10.0)
QUANT_A = DEPTH_QUANTIZATION * (DEPTH_QUANTIZATION + np.float32(1.0))  # 10100
QUANT_B = np.float32(1.0) - QUANT_A / DEPTH_MAX  # -1009


# ---------------------------------------------------------------------------------------------
# Stamps, frames and poses
# ---------------------------------------------------------------------------------------------


def stamp_ns(i: int) -> int:
    """t_i in ns: T0 + round(i * 1e9 / 30), in exact integers (i * 1e9 / 30 is never a tie)."""
    return T0_NS + (2 * i * 10**9 + 30) // 60


def header(ns: int, frame_id: str) -> object:
    # Floor division keeps nanosec in [0, 1e9) for stamps before T0 too.
    stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def read_trajectory() -> list[np.ndarray]:
    """Camera-to-world 4x4 matrices from the Redwood .log (a metadata line, then 4 rows)."""
    lines = [ln for ln in (FRAMES / "trajectory.log").read_text().splitlines() if ln.strip()]
    return [
        np.array([[float(v) for v in row.split()] for row in lines[k + 1 : k + 5]])
        for k in range(0, len(lines), 5)
    ]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(x, y, z, w) with w >= 0 of the rotation nearest to r.

    The .log rows are rounded to 8 decimals, so r is only orthonormal to ~1e-8; projecting it
    onto SO(3) first (SVD) makes the quaternion a well-defined function of the file.
    """
    u, _, vt = np.linalg.svd(r)
    r = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    # Shepperd: take the square root of the largest of 4w^2, 4x^2, 4y^2, 4z^2 for stability.
    tr = np.trace(r)
    k = int(np.argmax([tr, r[0, 0], r[1, 1], r[2, 2]]))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    q = np.array(q) / np.linalg.norm(q)
    return -q if q[3] < 0 else q


def yaw_quat(degrees: float) -> np.ndarray:
    half = math.radians(degrees) / 2
    return np.array([0.0, 0.0, math.sin(half), math.cos(half)])


def rigid(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(q)
    m[:3, 3] = t
    return m


def invert(m: np.ndarray) -> np.ndarray:
    inv = np.eye(4)
    inv[:3, :3] = m[:3, :3].T
    inv[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return inv


# The fixed transforms of the tf tree map -> odom -> base_link -> camera_link -> optical.
MAP_ODOM = (np.array([1.0, -2.0, 0.0]), yaw_quat(30.0))
BASE_CAMERA = (np.array([0.10, 0.02, 0.50]), yaw_quat(10.0))
# REP 103: optical z forward, x right, y down, seen from camera_link's x forward, z up.
CAMERA_OPTICAL = (np.zeros(3), np.array([-0.5, 0.5, -0.5, 0.5]))
WHEEL_LEFT = (np.array([0.0, 0.2, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))  # a distractor


def pose_tq(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation and quaternion of a camera-to-world matrix: what the pose topics carry."""
    return m[:3, 3].copy(), matrix_to_quat(m[:3, :3])


def odom_base(pose: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """odom -> base_link such that map->odom->base_link->camera_link->optical is `pose`."""
    base_optical = rigid(*BASE_CAMERA) @ rigid(*CAMERA_OPTICAL)
    m = invert(rigid(*MAP_ODOM)) @ rigid(*pose) @ invert(base_optical)
    t, q = m[:3, 3].copy(), matrix_to_quat(m[:3, :3])
    chain = rigid(*MAP_ODOM) @ rigid(t, q) @ base_optical
    assert np.abs(chain - rigid(*pose)).max() < 1e-12, "tf chain does not reproduce the pose"
    return t, q


# ---------------------------------------------------------------------------------------------
# Message builders
# ---------------------------------------------------------------------------------------------


def pose_msg(t: np.ndarray, q: np.ndarray) -> object:
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def transform_msg(ns: int, parent: str, child: str, tq: tuple[np.ndarray, np.ndarray]) -> object:
    t, q = tq
    return T["geometry_msgs/msg/TransformStamped"](
        header=header(ns, parent),
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )


def tf_msg(transforms: list[object]) -> object:
    return T["tf2_msgs/msg/TFMessage"](transforms=transforms)


def compressed_msg(ns: int, fmt: str, data: bytes) -> object:
    return T["sensor_msgs/msg/CompressedImage"](
        header=header(ns, OPTICAL), format=fmt, data=np.frombuffer(data, dtype=np.uint8)
    )


def image_msg(ns: int, encoding: str, pixels: np.ndarray, pad: int = 0) -> object:
    """A raw Image of (height, width[, channels]) pixels in wire order; each row is followed by
    `pad` bytes of 0xAB, so step = width * bytes per pixel + pad."""
    height, width = pixels.shape[:2]
    rows = np.ascontiguousarray(pixels).view(np.uint8).reshape(height, -1)
    rows = np.concatenate([rows, np.full((height, pad), 0xAB, dtype=np.uint8)], axis=1)
    return T["sensor_msgs/msg/Image"](
        header=header(ns, OPTICAL),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=rows.shape[1],
        data=rows.reshape(-1),
    )


def camera_info_msg(ns: int, scale: float, d: list[float]) -> object:
    fx, fy, cx, cy = FX / scale, FY / scale, CX / scale, CY / scale
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(ns, OPTICAL),
        height=round(HEIGHT / scale),
        width=round(WIDTH / scale),
        distortion_model="plumb_bob",
        d=np.array(d, dtype=np.float64),
        k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64),
        r=np.eye(3).reshape(-1),
        p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64),
        binning_x=0,
        binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


def pose_stamped_msg(ns: int, tq: tuple[np.ndarray, np.ndarray]) -> object:
    return T["geometry_msgs/msg/PoseStamped"](header=header(ns, "map"), pose=pose_msg(*tq))


def odometry_msg(ns: int, tq: tuple[np.ndarray, np.ndarray]) -> object:
    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T["nav_msgs/msg/Odometry"](
        header=header(ns, "map"),
        child_frame_id=OPTICAL,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(*tq), covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
            covariance=np.zeros(36),
        ),
    )


# ---------------------------------------------------------------------------------------------
# compressedDepth
# ---------------------------------------------------------------------------------------------


def config_header(quant_a: float, quant_b: float) -> bytes:
    return struct.pack("<iff", INV_DEPTH, quant_a, quant_b)


def png16(a: np.ndarray) -> bytes:
    """A 16-bit greyscale PNG of a uint16 array (level 9, as Humble's png_level default)."""
    out = io.BytesIO()
    Image.fromarray(a.astype(np.uint16)).save(out, format="PNG", compress_level=9)
    return out.getvalue()


def metres(mm: np.ndarray) -> np.ndarray:
    """Depth in metres as a 32FC1 driver would publish it: float32(mm) / 1000.0f, NaN = invalid."""
    m = mm.astype(np.float32) / np.float32(1000.0)
    m[mm == 0] = np.nan
    return m


def inverse_depth(depth_m: np.ndarray) -> np.ndarray:
    """The codec's 32FC1 quantisation, in its float32 arithmetic.

    `if (d < depthMax) q = depthQuantA / d + depthQuantB; else q = 0;` with the float result
    converted to unsigned short by truncation. NaN fails the comparison, so invalid pixels are 0.
    """
    q = np.zeros(depth_m.shape, dtype=np.uint16)
    with np.errstate(invalid="ignore"):
        valid = depth_m < DEPTH_MAX
    v = QUANT_A / depth_m[valid] + QUANT_B  # float32 throughout, like the C++
    assert v.max() < 65536, "depth too small for the 16-bit inverse-depth range"
    q[valid] = np.trunc(v).astype(np.uint16)
    return q


def compressed_depth_16(png: bytes, mm: np.ndarray) -> bytes:
    # The codec's 16UC1 path only zeroes values above depth_max (10 m) and PNG-encodes the
    # rest; the committed PNG already is that, so its bytes go in unchanged.
    assert mm.max() <= int(DEPTH_MAX * 1000)
    return config_header(0.0, 0.0) + png


def compressed_depth_32(mm: np.ndarray) -> bytes:
    return config_header(QUANT_A, QUANT_B) + png16(inverse_depth(metres(mm)))


# ---------------------------------------------------------------------------------------------
# Bags
# ---------------------------------------------------------------------------------------------


def load_frame(i: int) -> tuple[bytes, bytes, np.ndarray]:
    """The committed JPEG and PNG bytes of frame i, and the depth in millimetres."""
    jpeg = (FRAMES / "color" / f"{i:05d}.jpg").read_bytes()
    png = (FRAMES / "depth" / f"{i:05d}.png").read_bytes()
    mm = np.array(Image.open(io.BytesIO(png)))
    assert mm.dtype == np.uint16 and mm.shape == (HEIGHT, WIDTH)
    return jpeg, png, mm


# (topic, type) in connection order; on equal stamps messages are written in this order.
LIVING_ROOM_TOPICS = [
    ("/tf_static", "tf2_msgs/msg/TFMessage"),
    ("/tf", "tf2_msgs/msg/TFMessage"),
    ("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo"),
    ("/camera/color/camera_info_distorted", "sensor_msgs/msg/CameraInfo"),
    ("/camera/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage"),
    ("/camera/aligned_depth_to_color/image_raw/compressed", "sensor_msgs/msg/CompressedImage"),
    (
        "/camera/aligned_depth_to_color/image_raw/compressedDepth",
        "sensor_msgs/msg/CompressedImage",
    ),
    (
        "/camera/aligned_depth_to_color/image_raw/compressedDepth32",
        "sensor_msgs/msg/CompressedImage",
    ),
    ("/camera/pose", "geometry_msgs/msg/PoseStamped"),
    ("/odom", "nav_msgs/msg/Odometry"),
    ("/chatter", "std_msgs/msg/String"),
]

RAW_TOPICS = [
    ("/raw/camera_info", "sensor_msgs/msg/CameraInfo"),
    ("/raw/rgb8", "sensor_msgs/msg/Image"),
    ("/raw/bgr8", "sensor_msgs/msg/Image"),
    ("/raw/rgba8", "sensor_msgs/msg/Image"),
    ("/raw/bgra8", "sensor_msgs/msg/Image"),
    ("/raw/mono8", "sensor_msgs/msg/Image"),
    ("/raw/depth_16uc1", "sensor_msgs/msg/Image"),
    ("/raw/depth_32fc1", "sensor_msgs/msg/Image"),
    ("/raw/pose", "geometry_msgs/msg/PoseStamped"),
]


def living_room_messages(poses: list[np.ndarray]) -> list[tuple[int, str, object]]:
    """(record time ns, topic, message) of the living-room bags, frames 0..4."""
    msgs: list[tuple[int, str, object]] = []
    t0 = stamp_ns(0)
    msgs.append(
        (
            t0,
            "/tf_static",
            tf_msg(
                [
                    transform_msg(t0, "base_link", "camera_link", BASE_CAMERA),
                    transform_msg(t0, "camera_link", OPTICAL, CAMERA_OPTICAL),
                ]
            ),
        )
    )
    msgs.append((t0, "/chatter", T["std_msgs/msg/String"](data="hello")))

    # One colour image a frame period before the first depth image: it has no depth partner.
    early = stamp_ns(-1)
    jpeg0 = load_frame(0)[0]
    msgs.append(
        (
            early,
            "/camera/color/image_raw/compressed",
            compressed_msg(early, "rgb8; jpeg compressed bgr8", jpeg0),
        )
    )

    depth = "/camera/aligned_depth_to_color/image_raw"
    for i in range(5):
        ns = stamp_ns(i)
        jpeg, png, mm = load_frame(i)
        pose = pose_tq(poses[i])
        transforms = [
            transform_msg(ns, "map", "odom", MAP_ODOM),
            transform_msg(ns, "odom", "base_link", odom_base(pose)),
            transform_msg(ns, "odom", "wheel_left", WHEEL_LEFT),
        ]
        distorted = [0.1, -0.05, 0.001, 0.0, 0.0]
        msgs += [
            (ns, "/tf", tf_msg(transforms)),
            (ns, "/camera/color/camera_info", camera_info_msg(ns, 1, [0.0] * 5)),
            (ns, "/camera/color/camera_info_distorted", camera_info_msg(ns, 1, distorted)),
            (
                ns,
                "/camera/color/image_raw/compressed",
                compressed_msg(ns, "rgb8; jpeg compressed bgr8", jpeg),
            ),
            (ns, f"{depth}/compressed", compressed_msg(ns, "16UC1; png compressed", png)),
            (
                ns,
                f"{depth}/compressedDepth",
                compressed_msg(ns, "16UC1; compressedDepth png", compressed_depth_16(png, mm)),
            ),
            (
                ns,
                f"{depth}/compressedDepth32",
                compressed_msg(ns, "32FC1; compressedDepth png", compressed_depth_32(mm)),
            ),
            (ns, "/camera/pose", pose_stamped_msg(ns, pose)),
            (ns, "/odom", odometry_msg(ns, pose)),
        ]
    return msgs


def raw_messages(
    poses: list[np.ndarray], frames: int = 3, factor: int = 8
) -> list[tuple[int, str, object]]:
    """(record time ns, topic, message) of the raw bags, frames 0..frames-1 subsampled by
    `factor` (8 for the test bags, 80 for the fuzz seeds)."""
    msgs: list[tuple[int, str, object]] = []
    for i in range(frames):
        ns = stamp_ns(i)
        jpeg, _, mm = load_frame(i)
        rgb = np.array(Image.open(io.BytesIO(jpeg)).convert("RGB"))[::factor, ::factor]
        mm = np.ascontiguousarray(mm[::factor, ::factor])
        bgr = rgb[..., ::-1]
        alpha = np.full(rgb.shape[:2] + (1,), 255, dtype=np.uint8)
        grey = np.array(Image.fromarray(np.ascontiguousarray(rgb)).convert("L"))
        msgs += [
            (ns, "/raw/camera_info", camera_info_msg(ns, factor, [0.0] * 5)),
            (ns, "/raw/rgb8", image_msg(ns, "rgb8", rgb)),
            # bgr8 rows carry 4 padding bytes so that step != width * 3.
            (ns, "/raw/bgr8", image_msg(ns, "bgr8", bgr, pad=4)),
            (ns, "/raw/rgba8", image_msg(ns, "rgba8", np.concatenate([rgb, alpha], axis=2))),
            (ns, "/raw/bgra8", image_msg(ns, "bgra8", np.concatenate([bgr, alpha], axis=2))),
            (ns, "/raw/mono8", image_msg(ns, "mono8", grey)),
            (ns, "/raw/depth_16uc1", image_msg(ns, "16UC1", mm.astype("<u2"))),
            (ns, "/raw/depth_32fc1", image_msg(ns, "32FC1", metres(mm).astype("<f4"))),
            (ns, "/raw/pose", pose_stamped_msg(ns, pose_tq(poses[i]))),
        ]
    return msgs


def write_bag(
    path: Path,
    storage: StoragePlugin,
    topics: list[tuple[str, str]],
    msgs: list[tuple[int, str, object]],
    zstd: bool = True,
) -> None:
    if path.exists():
        shutil.rmtree(path)
    order = {topic: k for k, (topic, _) in enumerate(topics)}
    types = dict(topics)
    # Record order = time order (ties in topic order), as a recorder would write them.
    msgs = sorted(msgs, key=lambda m: (m[0], order[m[1]]))
    writer = Writer(path, version=8, storage_plugin=storage)
    if storage == StoragePlugin.MCAP and zstd:
        # zstd-compressed chunks, as `ros2 bag record -s mcap` writes by default (libmcap's
        # default); the reader must decompress them, and the bags get smaller.
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        conns = {topic: writer.add_connection(topic, typ, typestore=TS) for topic, typ in topics}
        for ns, topic, msg in msgs:
            writer.write(conns[topic], ns, TS.serialize_cdr(msg, types[topic], little_endian=True))


def write_fuzz_seeds(corpus: Path, poses: list[np.ndarray]) -> None:
    """Seeds of the fuzz targets rosbag2_bag (tiny whole storage files: 2 frames of 8x6) and
    rosbag2_messages (one CDR payload per message type, after the byte that picks the type)."""
    raw = raw_messages(poses, frames=2, factor=80)
    keep = {"/raw/camera_info", "/raw/rgb8", "/raw/depth_16uc1", "/raw/pose"}
    topics = [t for t in RAW_TOPICS if t[0] in keep]
    tiny = [m for m in raw if m[1] in keep]
    bags = corpus / "rosbag2_bag"
    bags.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name, storage, zstd in (
            ("tiny_zstd.mcap", StoragePlugin.MCAP, True),
            ("tiny_plain.mcap", StoragePlugin.MCAP, False),
            ("tiny.db3", StoragePlugin.SQLITE3, False),
        ):
            folder = Path(tmp) / name.split(".")[0]
            write_bag(folder, storage, topics, tiny, zstd=zstd)
            storage_file = next(f for f in folder.iterdir() if f.suffix in (".mcap", ".db3"))
            shutil.copy(storage_file, bags / name)
    messages = corpus / "rosbag2_messages"
    messages.mkdir(parents=True, exist_ok=True)
    types = dict(RAW_TOPICS + LIVING_ROOM_TOPICS)
    # The selector byte of each type (fuzz_targets/rosbag2_messages.rs).
    living_room = living_room_messages(poses)
    first = {topic: msg for _, topic, msg in reversed(raw + living_room)}
    picks = [
        (0, "/raw/rgb8"), (0, "/raw/bgr8"), (0, "/raw/depth_16uc1"), (0, "/raw/depth_32fc1"),
        (0, "/raw/mono8"), (1, "/camera/aligned_depth_to_color/image_raw/compressedDepth32"),
        (2, "/raw/camera_info"), (2, "/camera/color/camera_info_distorted"), (3, "/tf"),
        (3, "/tf_static"), (4, "/odom"), (5, "/raw/pose"),
    ]
    for selector, topic in picks:
        payload = TS.serialize_cdr(first[topic], types[topic], little_endian=True)
        if selector == 1:
            # Keep the seed small: the transport header and the PNG's first bytes.
            payload = payload[:400]
        name = topic.strip("/").replace("/", "_")
        (messages / f"{name}.cdr").write_bytes(bytes([selector]) + payload)


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--fuzz-seeds":
        write_fuzz_seeds(Path(sys.argv[2]), read_trajectory())
        return
    poses = read_trajectory()
    living_room = living_room_messages(poses)
    raw = raw_messages(poses)
    for suffix, storage in (("mcap", StoragePlugin.MCAP), ("sqlite", StoragePlugin.SQLITE3)):
        write_bag(HERE / f"living-room-{suffix}", storage, LIVING_ROOM_TOPICS, living_room)
        write_bag(HERE / f"raw-{suffix}", storage, RAW_TOPICS, raw)
        print(f"wrote living-room-{suffix}/ and raw-{suffix}/")


if __name__ == "__main__":
    main()

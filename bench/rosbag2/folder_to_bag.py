#!/usr/bin/env python3
"""Write an ICL-layout RGB-D folder (color/*.jpg|png, depth/*.png, intrinsics.json, a Redwood .log
trajectory) as a ROS 2 bag, with the `rosbags` package (an implementation independent of vlem's).

Why: to measure vlem's bag reader on a real-length sequence against the same frames as a folder
(BENCHMARKS.md, "ROS 2 bags"), and to let users try `kind = "rosbag2"` on data they already have.

    python3 -m venv bench/.venv-rosbags && bench/.venv-rosbags/bin/pip install rosbags==0.11.9 numpy pillow
    bench/.venv-rosbags/bin/python bench/rosbag2/folder_to_bag.py FOLDER OUT_BAG [--raw] [--sqlite]

Topics: /camera/color/image_raw (raw rgb8, with --raw) or /camera/color/image_raw/compressed (the
JPEG/PNG bytes as they are), /camera/aligned_depth_to_color/image_raw (raw 16UC1, with --raw) or
.../compressed (the 16-bit PNG bytes), /camera/color/camera_info, /camera/pose (PoseStamped of the
optical frame). Frames are stamped at 30 Hz from 1_700_000_000 s. MCAP (zstd chunks) by default.
"""
import argparse
import io
import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
FRAME = "camera_color_optical_frame"


def stamp(i):
    ns = 1_700_000_000 * 10**9 + round(i * 1e9 / 30)
    return ns, T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def header(i):
    return T["std_msgs/msg/Header"](stamp=stamp(i)[1], frame_id=FRAME)


def quaternion(r):
    t = np.trace(r)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
    q = [0.0, 0.0, 0.0]
    q[i] = 0.25 * s
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    return (q[0], q[1], q[2], (r[k, j] - r[j, k]) / s)


def trajectory(folder):
    logs = sorted(folder.glob("*.log"))
    if not logs:
        return []
    rows = [line.split() for line in open(logs[0]) if line.strip()]
    return [np.array([[float(x) for x in r] for r in rows[i + 1:i + 5]]) for i in range(0, len(rows), 5)]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--raw", action="store_true", help="raw Image messages instead of CompressedImage")
    parser.add_argument("--sqlite", action="store_true", help="SQLite3 storage instead of MCAP")
    a = parser.parse_args()
    colour_files = sorted((a.folder / "color").glob("*")) or sorted((a.folder / "image").glob("*"))
    depth_files = sorted((a.folder / "depth").glob("*.png"))
    intrinsics = json.load(open(a.folder / "intrinsics.json"))
    k = intrinsics["intrinsic_matrix"]  # column-major
    fx, fy, cx, cy = k[0], k[4], k[6], k[7]
    width, height = intrinsics["width"], intrinsics["height"]
    poses = trajectory(a.folder)
    if a.out.exists():
        shutil.rmtree(a.out)
    writer = Writer(a.out, version=8, storage_plugin=StoragePlugin.SQLITE3 if a.sqlite else StoragePlugin.MCAP)
    if not a.sqlite:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    suffix = "" if a.raw else "/compressed"
    kind = "sensor_msgs/msg/Image" if a.raw else "sensor_msgs/msg/CompressedImage"
    with writer:
        add = lambda topic, typ: writer.add_connection(topic, typ, typestore=TS)  # noqa: E731
        colour_c = add("/camera/color/image_raw" + suffix, kind)
        depth_c = add("/camera/aligned_depth_to_color/image_raw" + suffix, kind)
        info_c = add("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo")
        pose_c = add("/camera/pose", "geometry_msgs/msg/PoseStamped")
        write = lambda c, ns, msg, typ: writer.write(c, ns, TS.serialize_cdr(msg, typ))  # noqa: E731
        for i, (cf, df) in enumerate(zip(colour_files, depth_files)):
            ns, _ = stamp(i)
            if a.raw:
                rgb = np.asarray(Image.open(cf).convert("RGB"))
                mm = np.asarray(Image.open(df)).astype("<u2")
                colour = T[kind](header=header(i), height=rgb.shape[0], width=rgb.shape[1], encoding="rgb8",
                                 is_bigendian=0, step=rgb.shape[1] * 3, data=rgb.reshape(-1).view(np.uint8))
                depth = T[kind](header=header(i), height=mm.shape[0], width=mm.shape[1], encoding="16UC1",
                                is_bigendian=0, step=mm.shape[1] * 2, data=mm.reshape(-1).view(np.uint8))
            else:
                colour = T[kind](header=header(i), format="rgb8; jpeg compressed bgr8",
                                 data=np.frombuffer(cf.read_bytes(), dtype=np.uint8))
                depth = T[kind](header=header(i), format="16UC1; png compressed",
                                data=np.frombuffer(df.read_bytes(), dtype=np.uint8))
            info = T["sensor_msgs/msg/CameraInfo"](
                header=header(i), height=height, width=width, distortion_model="plumb_bob",
                d=np.zeros(5), k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0]), r=np.eye(3).reshape(-1),
                p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                           do_rectify=False))
            write(info_c, ns, info, "sensor_msgs/msg/CameraInfo")
            write(colour_c, ns, colour, kind)
            write(depth_c, ns, depth, kind)
            if i < len(poses):
                t = poses[i]
                q = quaternion(t[:3, :3])
                pose = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=t[0, 3], y=t[1, 3], z=t[2, 3]),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
                write(pose_c, ns, T["geometry_msgs/msg/PoseStamped"](
                    header=T["std_msgs/msg/Header"](stamp=stamp(i)[1], frame_id="map"), pose=pose),
                    "geometry_msgs/msg/PoseStamped")
    print(f"wrote {len(depth_files)} frames to {a.out}")


if __name__ == "__main__":
    main()

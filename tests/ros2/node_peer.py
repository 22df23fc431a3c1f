"""End-to-end test of `vlem ros2` against a DDS peer vlem did not write: Eclipse Cyclone DDS
(`cyclonedds` from PyPI), on loopback, speaking ROS 2 topic names and message types.

The peer plays a RealSense camera (colour `rgb8`, aligned depth `16UC1`, camera info) and a
localisation node (`PoseStamped` of the optical frame, or with `--tf` the tf tree: a latched
`/tf_static` base_link -> camera_color_optical_frame and `/tf` map -> base_link per frame) with
the committed living-room frames,
sends malformed and out-of-order messages the node must survive, asks a query, and checks what
the node publishes: the tracked pose (PoseStamped and /tf), the map (PointCloud2 xyz + rgb), the
heatmap (with a `similarity` field), the best point set and a grasp. Then it stops the node with
SIGINT and checks the saved map and the counters.

    python3 -m venv bench/.venv-ros2 && bench/.venv-ros2/bin/pip install cyclonedds==11.0.1 numpy pillow
    cargo build --release --features ros2
    VLEM_BIN=target/release/vlem bench/.venv-ros2/bin/python tests/ros2/node_peer.py [--tf]

Exits 0 when every check passes; prints what failed otherwise.
"""
import io
import json
import os
import random
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image as PilImage

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
FRAMES = REPO / "data" / "living-room"
N_FRAMES = 8

# Cyclone on loopback: lo has no multicast, so discovery is unicast to 127.0.0.1.
os.environ["CYCLONEDDS_URI"] = (
    "<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface address='127.0.0.1'/>"
    "</Interfaces><AllowMulticast>false</AllowMulticast></General>"
    "<Internal><SocketReceiveBufferSize min='4MB'/></Internal>"
    "<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>32"
    "</MaxAutoParticipantIndex><Peers><Peer address='127.0.0.1'/></Peers></Discovery>"
    "</Domain></CycloneDDS>"
)

from cyclonedds.core import Policy, Qos  # noqa: E402 (after CYCLONEDDS_URI)
from cyclonedds.domain import DomainParticipant  # noqa: E402
from cyclonedds.internal import InvalidSample  # noqa: E402
from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402
from cyclonedds.util import duration  # noqa: E402

sys.path.insert(0, str(HERE))
import ros2_msgs as m  # noqa: E402

LATCHED = Qos(
    Policy.Reliability.Reliable(duration(milliseconds=100)),
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(1),
)
# The camera mount of the --tf mode: base_link -> optical frame (a yaw of 10 degrees, then ROS's
# optical rotation), as a robot's URDF would give it.
MOUNT = np.array([
    [0.0, -0.17364818, 0.98480775, 0.10],
    [-1.0, 0.0, 0.0, 0.02],
    [0.0, -0.98480775, -0.17364818, 0.50],
    [0.0, 0.0, 0.0, 1.0],
])
USE_TF = "--tf" in sys.argv
SENSOR = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5))
RELIABLE = Qos(
    Policy.Reliability.Reliable(duration(milliseconds=100)),
    Policy.Durability.Volatile,
    Policy.History.KeepLast(10),
)
T0 = 1_700_000_000


def stamp(i):
    ns = round(i * 1e9 / 10)  # 10 Hz
    return m.Time(sec=T0 + ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def seconds(t):
    return t.sec + t.nanosec * 1e-9


def trajectory():
    rows = [line.split() for line in open(FRAMES / "trajectory.log") if line.strip()]
    return [np.array([[float(x) for x in r] for r in rows[i + 1:i + 5]]) for i in range(0, len(rows), 5)]


def quaternion(r):
    """x, y, z, w of a rotation matrix (Shepperd)."""
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


def transform(parent, child, i, t):
    p = pose_message(t)
    return m.TransformStamped(
        header=m.Header(stamp=stamp(i), frame_id=parent), child_frame_id=child,
        transform=m.Transform(
            translation=m.Vector3(x=p.position.x, y=p.position.y, z=p.position.z),
            rotation=p.orientation,
        ),
    )


def pose_message(t):
    q = quaternion(t[:3, :3])
    return m.Pose(
        position=m.Point(x=t[0, 3], y=t[1, 3], z=t[2, 3]),
        orientation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def take_all(reader):
    return [s for s in reader.take(N=64) if not isinstance(s, InvalidSample)]


def wait_for(what, predicate, timeout):
    start = time.monotonic()
    while not predicate():
        if time.monotonic() - start > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)


def cloud_fields(cloud):
    return [(f.name, f.offset, f.datatype) for f in cloud.fields]


def cloud_points(cloud):
    step = cloud.point_step
    return [struct.unpack_from("<4f", cloud.data, i * step) for i in range(cloud.width)]


def main():
    vlem = os.environ.get("VLEM_BIN", str(REPO / "target" / "release" / "vlem"))
    m.enable_fast_u8_sequences()
    domain = random.randrange(100, 200)
    work = Path(tempfile.mkdtemp(prefix="vlem-ros2-test-"))
    config = work / "node.toml"
    config.write_text(
        f"""
[pipeline]
mode = "offline"

[tracker]
kind = "ground-truth"

[encoder]
kind = "colour-names"

[map]
kind = "point-cloud"

[query.segmenter]
kind = "threshold"
threshold = 0.75

[ros2]
domain_id = {domain}
localhost_only = true
{'tf = ["map", "camera_color_optical_frame"]' if USE_TF else 'pose_topic = "/camera/pose"'}
pose_type = "pose-stamped"
map_rate = 5.0
map_max_points = 60000
queue = {N_FRAMES}
"""
    )
    node = subprocess.Popen(
        [vlem, "ros2", "--config", str(config), "--save-map", str(work / "map.vlem"),
         "--status-json", str(work / "status.json")],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        check(domain)
    except BaseException:
        node.send_signal(signal.SIGINT)
        try:
            _, stderr = node.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            node.kill()
            _, stderr = node.communicate()
        print(stderr, file=sys.stderr)
        status = work / "status.json"
        if status.exists():
            print("node status:", status.read_text(), file=sys.stderr)
        raise
    node.send_signal(signal.SIGINT)
    _, stderr = node.communicate(timeout=60)
    print(stderr, file=sys.stderr)
    assert node.returncode == 0, f"vlem ros2 exited with {node.returncode}"
    status = json.loads((work / "status.json").read_text())
    counts = status["status"]
    print("node status:", json.dumps(status))
    assert counts["frames_queued"] == N_FRAMES, counts
    assert counts["bad_messages"] >= 1, counts  # the mono8 image
    assert counts["refused"] >= 1, counts  # the frame stamped before the previous one
    assert counts["queries"] == 1, counts
    assert status["run"]["frames_processed"] == N_FRAMES, status["run"]
    saved = (work / "map.vlem").read_bytes()
    assert saved.startswith(b"VLEMMAP\0"), saved[:8]
    print(f"PASS: vlem ros2 against cyclonedds, poses from {'tf' if USE_TF else 'a PoseStamped topic'}")


def check(domain):
    dp = DomainParticipant(domain)
    topic = lambda name, kind: Topic(dp, "rt" + name, kind)  # noqa: E731
    colour_w = DataWriter(dp, topic("/camera/color/image_raw", m.Image), qos=SENSOR)
    depth_w = DataWriter(dp, topic("/camera/aligned_depth_to_color/image_raw", m.Image), qos=SENSOR)
    info_w = DataWriter(dp, topic("/camera/color/camera_info", m.CameraInfo), qos=SENSOR)
    pose_w = DataWriter(dp, topic("/camera/pose", m.PoseStamped), qos=RELIABLE)
    tf_w = DataWriter(dp, topic("/tf", m.TFMessage), qos=RELIABLE)
    tf_static_w = DataWriter(dp, Topic(dp, "rt/tf_static", m.TFMessage, qos=LATCHED), qos=LATCHED)
    query_w = DataWriter(dp, topic("/vlem/query", m.String), qos=RELIABLE)
    pose_r = DataReader(dp, topic("/vlem/pose", m.PoseStamped), qos=RELIABLE)
    tf_r = DataReader(dp, topic("/tf", m.TFMessage), qos=RELIABLE)
    map_r = DataReader(dp, topic("/vlem/map", m.PointCloud2), qos=RELIABLE)
    heat_r = DataReader(dp, topic("/vlem/heatmap", m.PointCloud2), qos=RELIABLE)
    best_r = DataReader(dp, topic("/vlem/best", m.PointCloud2), qos=RELIABLE)
    grasp_r = DataReader(dp, topic("/vlem/grasp", m.PoseStamped), qos=RELIABLE)

    writers = [colour_w, depth_w, info_w, tf_w if USE_TF else pose_w, query_w]
    wait_for("the node's subscriptions", lambda: all(w.get_matched_subscriptions() for w in writers), 60)
    readers = [pose_r, tf_r, map_r, heat_r, best_r, grasp_r]
    wait_for("the node's publishers", lambda: all(r.get_matched_publications() for r in readers), 30)
    time.sleep(0.3)

    poses = trajectory()
    if USE_TF:
        # Latched, written once before any frame (a late-joining reader still gets it).
        tf_static_w.write(m.TFMessage(transforms=[transform("base_link", "camera_color_optical_frame", 0, MOUNT)]))
    k = [525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1]
    p = [525.0, 0, 319.5, 0, 0, 525.0, 239.5, 0, 0, 0, 1, 0]
    frame_id = "camera_color_optical_frame"

    def image(i, encoding, pixels):
        return m.Image(
            header=m.Header(stamp=stamp(i), frame_id=frame_id),
            height=pixels.shape[0], width=pixels.shape[1], encoding=encoding, is_bigendian=0,
            step=pixels.strides[0], data=pixels.tobytes(),
        )

    received_poses = []
    for i in range(N_FRAMES):
        rgb = np.asarray(PilImage.open(FRAMES / "color" / f"{i:05}.jpg").convert("RGB"))
        depth = np.asarray(PilImage.open(FRAMES / "depth" / f"{i:05}.png")).astype("<u2")
        info_w.write(m.CameraInfo(
            header=m.Header(stamp=stamp(i), frame_id=frame_id), height=480, width=640,
            distortion_model="plumb_bob", d=[0.0] * 5, k=k, r=[1.0, 0, 0, 0, 1, 0, 0, 0, 1], p=p,
        ))
        if USE_TF:
            base = poses[i] @ np.linalg.inv(MOUNT)
            tf_w.write(m.TFMessage(transforms=[transform("map", "base_link", i, base)]))
        else:
            pose_w.write(m.PoseStamped(header=m.Header(stamp=stamp(i), frame_id="map"), pose=pose_message(poses[i])))
        if i == 3:
            # Malformed: an encoding vlem cannot use (counted, skipped, the node goes on).
            grey = np.asarray(PilImage.open(FRAMES / "color" / f"{i:05}.jpg").convert("L"))
            colour_w.write(image(i, "mono8", grey))
            depth_w.write(image(i, "16UC1", depth))
            time.sleep(0.1)
        colour_w.write(image(i, "rgb8", rgb))
        depth_w.write(image(i, "16UC1", depth))
        # Wait for the node to have mapped this frame (the queue never fills: nothing dropped).
        wait_for(f"the pose of frame {i}", lambda: bool(received_poses.extend(take_all(pose_r)) or
                 any(abs(seconds(r.header.stamp) - seconds(stamp(i))) < 1e-6 for r in received_poses)),
                 float(os.environ.get("VLEM_TEST_TIMEOUT", "60")))
    # Out of order: a frame stamped before the last one (refused and counted).
    colour_w.write(image(2, "rgb8", rgb))
    depth_w.write(image(2, "16UC1", depth))
    time.sleep(0.5)

    last = [r for r in received_poses if abs(seconds(r.header.stamp) - seconds(stamp(N_FRAMES - 1))) < 1e-6][0]
    t = poses[N_FRAMES - 1]
    got = (last.pose.position.x, last.pose.position.y, last.pose.position.z)
    assert last.header.frame_id == "map", last.header.frame_id
    assert np.allclose(got, t[:3, 3], atol=1e-9), (got, t[:3, 3])
    q = quaternion(t[:3, :3])
    got_q = (last.pose.orientation.x, last.pose.orientation.y, last.pose.orientation.z, last.pose.orientation.w)
    assert np.allclose(got_q, q, atol=1e-9) or np.allclose(got_q, -np.array(q), atol=1e-9), (got_q, q)
    # The node's transforms (in --tf mode the peer reads its own /tf messages too).
    tfs = [x for x in take_all(tf_r) if x.transforms[0].child_frame_id == "vlem_camera_optical_frame"]
    assert tfs and tfs[-1].transforms[0].header.frame_id == "map", tfs[-1:]
    print(f"peer: {len(received_poses)} poses and {len(tfs)} tf messages; the last pose is the one sent")

    maps = []
    # 8 frames make ~430k points; clouds are published as an even subsample of at most 60000.
    wait_for("a map with every frame", lambda: bool(maps.extend(take_all(map_r)) or
             (maps and maps[-1].width > 50_000)), 30)
    cloud = maps[-1]
    assert cloud_fields(cloud) == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("rgb", 12, 7)], cloud_fields(cloud)
    assert cloud.header.frame_id == "map" and cloud.height == 1 and cloud.point_step == 16
    assert len(cloud.data) == cloud.row_step == 16 * cloud.width
    xyz = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 4)[:, :3]
    assert np.isfinite(xyz).all() and np.abs(xyz).max() < 20, np.abs(xyz).max()
    print(f"peer: map of {cloud.width} points")

    query_w.write(m.String(data="grasp: brown"))
    heat, best, grasp = [], [], []
    wait_for("the query's answers", lambda: bool(heat.extend(take_all(heat_r)) or best.extend(take_all(best_r))
             or grasp.extend(take_all(grasp_r))) or (heat and best and grasp), 60)
    h = heat[-1]
    assert [f[0] for f in cloud_fields(h)] == ["x", "y", "z", "rgb", "similarity"], cloud_fields(h)
    similarity = np.frombuffer(h.data, dtype="<f4").reshape(-1, 5)[:, 4]
    assert 50_000 < h.width <= 60_000 and 0.0 <= similarity.min() and similarity.max() <= 1.0
    b = best[-1]
    assert 0 < b.width < h.width, (b.width, h.width)
    g = grasp[-1].pose.position
    centre = np.frombuffer(b.data, dtype="<f4").reshape(-1, 4)[:, :3].mean(axis=0)
    assert np.linalg.norm(np.array([g.x, g.y, g.z]) - centre) < 1.0, ((g.x, g.y, g.z), centre)
    print(f"peer: heatmap of {h.width} points, best set of {b.width}, grasp at ({g.x:.2f}, {g.y:.2f}, {g.z:.2f})")


if __name__ == "__main__":
    main()

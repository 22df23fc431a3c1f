#!/usr/bin/env bash
# Regenerates the seed corpus fuzz/corpus/<target>/ from the real data in ../shared/data (see its
# README.md) plus a few hand-made edge cases. Images are cropped or sampled down to tiny sizes so
# that each seed is a few KB. Needs cargo and python3; CI never runs this, it runs on the committed
# corpus.
#
#   fuzz/make-seeds.sh [DATA_DIR]     (default: ../shared/data beside the repository)
set -euo pipefail
cd "$(dirname "$0")"
data="${1:-../../shared/data}"
samples="$data/rgbd-samples"
icl="$data/icl-livingroom1"
for d in "$samples" "$icl"; do
    [[ -d $d ]] || { echo "make-seeds: $d not found (pass the shared data folder)" >&2; exit 1; }
done

c=corpus
rm -rf "$c"
mkdir -p "$c"/{depth_image,colour_image,open3d_intrinsics,redwood_log,tum_trajectory,association_lists,scannet_text,config_toml,map_file,rosbag2_bag,rosbag2_messages,http_request_head}

# Images are cut down by seedgen/ (a small Rust tool on the `image` crate, the decoder vlem uses):
# `sample:WxH` is nearest-neighbour, so depth values stay real depths.
cargo build --quiet --release --manifest-path seedgen/Cargo.toml
seedgen() { seedgen/target/release/vlem-fuzz-seedgen "$@"; }
seedgen "$samples/depth/00000.png" "$c/depth_image/redwood_sample_32x24.png" png-gray16 sample:32x24
seedgen "$samples/depth/00001.png" "$c/depth_image/redwood_crop_24x16.png" png-gray16 crop:24x16+300+200
seedgen "$icl/depth/00000.png" "$c/depth_image/icl_sample_20x15.png" png-gray16 sample:20x15
seedgen "$samples/other_formats/TUM_depth.png" "$c/depth_image/tum_sample_32x24.png" png-gray16 sample:32x24
seedgen "$samples/other_formats/TUM_depth.png" "$c/depth_image/tum_crop_16x16.png" png-gray16 crop:16x16+320+240
seedgen "$samples/depth/00000.png" "$c/depth_image/one_pixel.png" png-gray16 crop:1x1+320+240
seedgen "$samples/other_formats/NYU_depth.pgm" "$c/depth_image/nyu_16x12.pgm" pgm16 sample:16x12
# Refused inputs: 8-bit depth (a visualisation) and colour.
seedgen "$samples/depth/00000.png" "$c/depth_image/eight_bit_refused.png" png-gray8 sample:16x12
seedgen "$samples/color/00000.jpg" "$c/depth_image/colour_refused.png" png-rgb8 sample:8x6

seedgen "$samples/color/00000.jpg" "$c/colour_image/redwood_32x24.jpg" jpeg-rgb sample:32x24
seedgen "$icl/color/00000.jpg" "$c/colour_image/icl_crop_24x16.jpg" jpeg-rgb crop:24x16+300+200
seedgen "$icl/color/00001.jpg" "$c/colour_image/gray_16x12.jpg" jpeg-gray sample:16x12
seedgen "$samples/other_formats/TUM_color.png" "$c/colour_image/tum_24x18.png" png-rgb8 sample:24x18
seedgen "$samples/other_formats/TUM_color.png" "$c/colour_image/tum_rgba16_8x6.png" png-rgba16 sample:8x6
seedgen "$samples/other_formats/TUM_color.png" "$c/colour_image/tum_gray_8x6.png" png-gray8 sample:8x6
seedgen "$samples/other_formats/NYU_color.ppm" "$c/colour_image/nyu_16x12.ppm" ppm sample:16x12

cp "$icl/intrinsics.json" "$c/open3d_intrinsics/icl_livingroom1.json"
cp "$samples/other_formats/intrinsics.json" "$c/open3d_intrinsics/other_formats.json" 2>/dev/null || true
printf '{"width": 320, "height": 240, "intrinsic_matrix": [300, 0, 0, 0, 310, 0, 160.5, 120.5, 1]}' \
    >"$c/open3d_intrinsics/one_line.json"
printf '{"width": 640, "height": 480, "intrinsic_matrix": [525, 0, 0, 0, 525, 0, 319.5, 239.5]}' \
    >"$c/open3d_intrinsics/eight_numbers.json"
printf '{"width": 640, "height": 480, "intrinsic_matrix": [1e309, 0, 0, 0, -525, 0, NaN, 239.5, 1]}' \
    >"$c/open3d_intrinsics/bad_numbers.json"

cp "$samples/trajectory.log" "$c/redwood_log/rgbd_samples_trajectory.log"
cp "$samples/odometry.log" "$c/redwood_log/rgbd_samples_odometry.log"
head -n 10 "$icl/trajectory_open3d_estimate.log" >"$c/redwood_log/icl_first_two.log"
printf '0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n' >"$c/redwood_log/truncated_record.log"
printf '0 0 1\nnan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n' >"$c/redwood_log/nan.log"
printf '0 0 1\n-1 0 0 0\n0 -1 0 0\n0 0 1 0\n0 0 0 1\n' >"$c/redwood_log/half_turn.log"

# The rest is text derived from the real files by python: TUM trajectory lines (the .log poses as
# `t tx ty tz qx qy qz qw`), ScanNet pose files (one .log record's matrix) and intrinsic_depth.txt
# (K of intrinsics.json as a 4x4 matrix), TUM rgb.txt/depth.txt lists, map files.
python3 - "$samples" "$icl" "$c" <<'PY'
import json, math, struct, sys, zlib
samples, icl, c = sys.argv[1:]

def log_records(path):
    rows = [l.split() for l in open(path) if l.strip()]
    return [[[float(x) for x in r] for r in rows[i + 1:i + 5]] for i in range(0, len(rows), 5)]

def quat(m):
    # Shepperd's method: scalar part last, as TUM writes it.
    t = m[0][0] + m[1][1] + m[2][2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        return ((m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, 0.25 * s)
    i = max(range(3), key=lambda k: m[k][k])
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + m[i][i] - m[j][j] - m[k][k]) * 2
    q = [0.0] * 3
    q[i] = 0.25 * s
    q[j] = (m[j][i] + m[i][j]) / s
    q[k] = (m[k][i] + m[i][k]) / s
    return (q[0], q[1], q[2], (m[k][j] - m[j][k]) / s)

records = log_records(f"{samples}/trajectory.log")
t0 = 1305031102.175304
lines = ["# timestamp tx ty tz qx qy qz qw"]
for n, m in enumerate(records):
    q = quat(m)
    lines.append(f"{t0 + n / 30:.6f} {m[0][3]:.4f} {m[1][3]:.4f} {m[2][3]:.4f} "
                 + " ".join(f"{x:.4f}" for x in q))
open(f"{c}/tum_trajectory/rgbd_samples_groundtruth.txt", "w").write("\n".join(lines) + "\n")
open(f"{c}/tum_trajectory/one_pose.txt", "w").write(lines[1] + "\n")
open(f"{c}/tum_trajectory/zero_quaternion.txt", "w").write("1.0 0 0 0 0 0 0 0\n")
open(f"{c}/tum_trajectory/seven_fields.txt", "w").write("1.0 0 0 0 0 0 1\n")
open(f"{c}/tum_trajectory/inf.txt", "w").write("1.0 inf 0 0 0 0 0 1\n")

for n, m in enumerate(records[:2]):
    open(f"{c}/scannet_text/pose_{n}.txt", "w").write(
        "\n".join(" ".join(repr(x) for x in r) for r in m) + "\n")
open(f"{c}/scannet_text/pose_lost_frame.txt", "w").write(
    "\n".join(" ".join(["-inf"] * 4) for _ in range(4)) + "\n")
k = json.load(open(f"{icl}/intrinsics.json"))["intrinsic_matrix"]
fx, fy, cx, cy = k[0], k[4], k[6], k[7]
open(f"{c}/scannet_text/intrinsic_depth.txt", "w").write(
    f"{fx} 0 {cx} 0\n0 {fy} {cy} 0\n0 0 1 0\n0 0 0 1\n")
open(f"{c}/scannet_text/three_rows.txt", "w").write("1 0 0 0\n0 1 0 0\n0 0 1 0\n")

depth = [f"{t0 + n / 30:.6f} depth/{t0 + n / 30:.6f}.png" for n in range(5)]
rgb = [f"{t0 + n / 30 + 0.011:.6f} rgb/{t0 + n / 30 + 0.011:.6f}.png" for n in range(4)]
head = "# depth maps\n# file: 'rgbd_dataset_freiburg1_xyz.bag'\n# timestamp filename\n"
open(f"{c}/association_lists/tum_depth_nul_rgb.txt", "w").write(
    head + "\n".join(depth) + "\n\0" + head.replace("depth maps", "color images") + "\n".join(rgb) + "\n")
open(f"{c}/association_lists/tum_one_list.txt", "w").write(head + "\n".join(depth) + "\n")
open(f"{c}/association_lists/rgbd.match", "w").write(open(f"{samples}/rgbd.match").read())
open(f"{c}/association_lists/bad_fields.txt", "w").write("1.0\n\0nan rgb/1.png\n")

def map_file(kind, points, dim, encoder, path):
    header = {"map_kind": kind, "points": len(points), "dim": dim, "embedding_type": "f32",
              "metadata": {"encoder": encoder, "config_dir": None, "frames_integrated": 3,
                           "vlem_version": "0.1.0"}}
    h = json.dumps(header, separators=(",", ":")).encode()
    body = b"VLEMMAP\0" + struct.pack("<II", 1, len(h)) + h
    for p, _, _ in points:
        body += struct.pack("<3f", *p)
    for _, rgb, _ in points:
        body += bytes(rgb)
    for _, _, e in points:
        body += struct.pack(f"<{dim}f", *e[:dim])
    open(path, "wb").write(body + struct.pack("<I", zlib.crc32(body)))

# Points back-projected from the first depth pixels of the sample trajectory's camera centres.
pts = [((m[0][3], m[1][3], m[2][3]), (200 - 30 * n, 120, 40 + 20 * n), (0.6, 0.8, 0.0, 0.0))
       for n, m in enumerate(records[:3])]
map_file("point-cloud", pts, 0, None, f"{c}/map_file/geometry_only.vlem")
map_file("voxel", pts, 4, {"kind": "colour-names"}, f"{c}/map_file/dim4.vlem")
map_file("point-cloud", [], 512, {"kind": "colour-names", "device": "cpu"}, f"{c}/map_file/empty.vlem")
PY
printf 'VLEMMAP\0\1\0\0\0\377\377\377\377' >"$c/map_file/huge_header_length.vlem"

cp ../configs/*.toml "$c/config_toml/"
printf '[pipeline]\nmode = "real-time"\nframe_rate = 1e-300\nqueue_capacity = 0\n' >"$c/config_toml/extreme_pipeline.toml"
printf '[dataset]\nkind = "synthetic"\n[dataset.synthetic]\nwidth = 0\nroom = [nan, inf, -1]\n' >"$c/config_toml/synthetic_bad_values.toml"
printf '[map]\nkind = "point-cloud"\nnested = { a = [[1, 2], [3.5]], b = { c = "d" } }\n' >"$c/config_toml/nested_params.toml"

# Request heads as curl, a browser and a hostile client send them to the query server.
h=$c/http_request_head
printf 'GET /status HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUser-Agent: curl/8.5.0\r\nAccept: */*\r\n\r\n' >"$h/curl_status"
printf 'POST /query HTTP/1.1\r\nHost: localhost:8765\r\nContent-Type: application/json\r\nContent-Length: 18\r\nExpect: 100-continue\r\n\r\n{"texts": ["red"]}' >"$h/post_query"
printf 'GET /heatmap.ply?text=coffee+machine&grasp=1 HTTP/1.1\r\nHost: [::1]:8765\r\nOrigin: http://localhost:8765\r\nConnection: close\r\n\r\n' >"$h/heatmap_origin"
printf 'GET / HTTP/2.0\r\n\r\n' >"$h/http2"
printf 'PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n' >"$h/h2_preface"
printf 'GET /status HTTP/1.0\r\nX: a\r\n folded\r\n\r\n' >"$h/http10_folded"
printf 'POST /snapshot HTTP/1.1\r\nTransfer-Encoding: chunked\r\nContent-Length: 3\r\n\r\n0\r\n\r\n' >"$h/chunked_and_length"

du -sh "$c"/*

# ROS 2 bags (tiny whole storage files) and messages (CDR payloads), written by the `rosbags`
# package, an implementation independent of vlem's: set up its virtualenv as
# vlem-datasets/tests/data/rosbag2/make_bags.py says, or point ROSBAGS_PYTHON at a python with it.
"${ROSBAGS_PYTHON:-../bench/.venv-rosbags/bin/python}" ../vlem-datasets/tests/data/rosbag2/make_bags.py --fuzz-seeds "$c"

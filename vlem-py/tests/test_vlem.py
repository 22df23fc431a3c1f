"""The vlem Python package: numpy in and out, the same answers as the `vlem` command, frames fed
while another thread queries, Python encoders through the pipeline, and the errors.

Run from the repository root after installing the package (see docs/python.md):
    python -m pytest vlem-py/tests
`VLEM_BIN` names the `vlem` binary for the comparison with `vlem query` (that test is skipped
without it). Reading the committed JPEG/PNG frames needs Pillow.
"""

import json
import os
import pathlib
import subprocess
import sys
import threading

import numpy as np
import pytest

import vlem

REPO = pathlib.Path(__file__).resolve().parents[2]
FRAMES = REPO / "data" / "living-room"
DEMO = REPO / "configs" / "demo.toml"
NUMPY_ENCODER = REPO / "examples" / "python" / "colour_names.py"


def config(encoder=None, **map_params):
    return {
        "dataset": {"path": str(FRAMES)},
        "tracker": {"kind": "ground-truth"},
        "encoder": encoder or {"kind": "colour-names"},
        "map": {"kind": "point-cloud", "max_points": 200000, **map_params},
    }


def test_a_run_writes_its_folder_as_vlem_run_does(tmp_path):
    # The same outputs as `vlem run --out`, stats.json last and equal to what run() returns;
    # a missing folder is created, an earlier run's heatmaps go.
    out = tmp_path / "runs" / "demo"
    out.mkdir(parents=True)
    (out / "query-old.ply").write_bytes(b"earlier run")
    stats = vlem.Pipeline(DEMO).run(max_frames=3, out=out)
    assert sorted(p.name for p in out.iterdir()) == ["map.vlem", "stats.json", "trajectory.tum"]
    written = json.loads((out / "stats.json").read_text())
    assert written["frames"] == stats["frames"] and written["map"]["file_bytes"] == (out / "map.vlem").stat().st_size
    assert len((out / "trajectory.tum").read_text().splitlines()) == 1 + 3
    assert vlem.Map.load(out / "map.vlem").frames_integrated == 3


def test_plugins_list_what_the_build_contains():
    names = {(p["stage"], p["name"]) for p in vlem.plugins()}
    assert ("encoder", "colour-names") in names
    assert ("encoder", "python") in names
    assert ("map", "point-cloud") in names
    assert ("dataset", "icl") in names and ("dataset", "synthetic") in names
    assert all(p["description"] for p in vlem.plugins())
    features = {p["name"]: p["feature"] for p in vlem.plugins()}
    assert features["point-cloud"] == "point-cloud" and features["icl"] is None


def test_a_run_gives_numpy_arrays_of_the_documented_dtypes():
    pipeline = vlem.Pipeline(DEMO)
    events = []
    stats = pipeline.run(max_frames=4, progress=events.append)
    assert stats["frames"]["processed"] == 4
    assert [e["index"] for e in events if e["event"] == "tracked"] == [0, 1, 2, 3]
    m = pipeline.map
    n = len(m)
    assert n > 1000 and m.frames_integrated == 4 and m.dim == 11 and m.kind == "point-cloud"
    assert m.points.dtype == np.float32 and m.points.shape == (n, 3)
    assert m.colours.dtype == np.uint8 and m.colours.shape == (n, 3)
    e = m.embeddings()
    assert e.dtype == np.float32 and e.shape == (n, 11)
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-4)
    assert m.embeddings("float16").dtype == np.float16
    snap = m.snapshot()
    assert snap["frames_integrated"] == 4 and snap["points"].shape == (n, 3)
    scores = m.scores(["white wall", "brown"])
    assert scores.shape == (n, 2) and scores.dtype == np.float32
    assert (scores >= 0).all() and (scores <= 1).all() and (scores.max(axis=0) > 0.99).all()
    # A table over 4 GiB is refused before anything is scored (not an abort of the interpreter).
    with pytest.raises(MemoryError, match="fewer texts per call"):
        m.scores(["red"] * ((4 << 30) // (4 * n) + 1))
    t = pipeline.trajectory
    assert t.shape == (4, 8) and t.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(t[:, 4:], axis=1), 1.0)
    assert pipeline.status["state"] == "finished"


def test_a_saved_map_answers_as_the_vlem_command_does(tmp_path):
    pipeline = vlem.Pipeline(DEMO)
    pipeline.run(max_frames=6)
    # A folder that does not exist yet is created, as `vlem run --out` creates its own.
    path = tmp_path / "out" / "run" / "map.vlem"
    assert pipeline.map.save(path) == len(pipeline.map)
    loaded = vlem.Map.load(path)
    assert len(loaded) == len(pipeline.map) and loaded.frames_integrated == 6
    np.testing.assert_array_equal(loaded.points, pipeline.map.points)
    answer = loaded.query(["white wall", "brown"], grasp=True)
    assert answer["lines"] == pipeline.map.query(["white wall", "brown"], grasp=True)["lines"]
    best = answer["queries"][0]
    assert best["selected"] == sum(len(i) for i in best["indices"])
    assert best["indices"][0].dtype == np.int64
    # The best point set's points, as the README shows it.
    points = loaded.points[best["indices"][0]]
    assert points.shape[1] == 3 and len(points) == best["sets"][0]["points"]
    binary = os.environ.get("VLEM_BIN")
    if not binary:
        pytest.skip("VLEM_BIN is not set: no vlem binary to compare with")
    out = subprocess.run(
        [binary, "query", "--map", str(path), "--grasp", "white wall", "brown"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.splitlines()
    assert out[1:] == answer["lines"], out


def read_frames(count):
    """The committed frames as numpy arrays, with their poses from trajectory.log."""
    image = pytest.importorskip("PIL.Image")
    rows = [line.split() for line in (FRAMES / "trajectory.log").read_text().splitlines() if line.strip()]
    poses = [np.array(rows[i * 5 + 1 : i * 5 + 5], dtype=np.float64) for i in range(count)]
    for i in range(count):
        colour = np.asarray(image.open(FRAMES / "color" / f"{i:05d}.jpg").convert("RGB"))
        depth = np.asarray(image.open(FRAMES / "depth" / f"{i:05d}.png")).astype(np.uint16)
        yield colour, depth, poses[i]


def test_camera_sizes_out_of_range_name_their_argument():
    for width, height, name in [(-1, 480, "width"), (640, 0, "height"), (2**40, 480, "width")]:
        with pytest.raises(ValueError, match=f"{name} must be a positive number of pixels"):
            vlem.Intrinsics(width, height, 525.0, 525.0, 319.5, 239.5)


def test_frames_fed_from_numpy_map_like_the_folder_and_are_queried_while_feeding():
    camera = vlem.Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
    assert vlem.Intrinsics.from_matrix([[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]], 640, 480) == camera
    fed = vlem.Pipeline(config())
    seen = []
    done = threading.Event()

    def query_while_feeding():
        while not done.is_set():
            answer = fed.map.query("white wall")
            seen.append((answer["frames_integrated"], answer["points"]))

    reader = threading.Thread(target=query_while_feeding)
    with fed.start(camera) as feed:
        reader.start()
        for i, (colour, depth, pose) in enumerate(read_frames(10)):
            assert feed.push(colour, depth, timestamp=float(i), pose=pose) == i
    stats = feed.finish()
    done.set()
    reader.join()
    assert stats["frames"]["processed"] == 10
    counts = [f for f, _ in seen]
    assert counts == sorted(counts), "a query saw the map go back in time"
    assert len(seen) >= 2
    # The same frames read by vlem from the folder give the same map, up to the JPEG decoders
    # (Pillow's and vlem's round a few pixels differently, and colour takes part in fusion).
    folder = vlem.Pipeline(config())
    folder.run(max_frames=10)
    assert abs(len(fed.map) - len(folder.map)) <= len(folder.map) * 1e-3
    for a, b in [(fed.map.points.min(axis=0), folder.map.points.min(axis=0)), (fed.map.points.max(axis=0), folder.map.points.max(axis=0))]:
        np.testing.assert_allclose(a, b, atol=1e-3)


def test_feeding_refuses_bad_arrays_naming_the_argument():
    camera = vlem.Intrinsics(8, 6, 10.0, 10.0, 3.5, 2.5)
    pipeline = vlem.Pipeline(config())
    colour = np.zeros((6, 8, 3), np.uint8)
    depth = np.ones((6, 8), np.float32)
    with pipeline.start(camera, poses=True) as feed:
        with pytest.raises(TypeError, match="colour must be uint8"):
            feed.push(colour.astype(np.float32), depth, timestamp=0.0, pose=np.eye(4))
        with pytest.raises(ValueError, match="depth must be"):
            feed.push(colour, depth[:5], timestamp=0.0, pose=np.eye(4))
        with pytest.raises(ValueError, match="C-contiguous"):
            feed.push(np.asfortranarray(colour), depth, timestamp=0.0, pose=np.eye(4))
        with pytest.raises(TypeError, match="must be a numpy array"):
            feed.push(colour.tolist(), depth, timestamp=0.0, pose=np.eye(4))
        with pytest.raises(ValueError, match="rigid"):
            feed.push(colour, depth, timestamp=0.0, pose=np.ones((4, 4)))
        far = np.eye(4)
        far[0, 3] = 1e30
        with pytest.raises(ValueError, match="from the map's origin"):
            feed.push(colour, depth, timestamp=0.0, pose=far)
        assert feed.push(colour, depth, timestamp=1.0, pose=np.eye(4)) == 0
        with pytest.raises(vlem.DatasetError, match="not after the previous"):
            feed.push(colour, depth, timestamp=0.5, pose=np.eye(4))
        with pytest.raises(vlem.DatasetError, match="no pose"):
            feed.push(colour, depth, timestamp=2.0)
        assert feed.push(colour, (depth * 1000).astype(np.uint16), timestamp=3.0, pose=np.eye(4)) == 1
    assert pipeline.status["frames_integrated"] == 2
    # The pipeline is back: it can run again.
    pipeline.run(max_frames=1)


def test_a_python_encoder_maps_like_the_rust_encoder_it_copies():
    python = vlem.Pipeline(config({"kind": "python", "path": str(NUMPY_ENCODER), "class": "ColourNames"}))
    rust = vlem.Pipeline(config())
    python.run(max_frames=3)
    rust.run(max_frames=3)
    assert len(python.map) == len(rust.map)
    np.testing.assert_allclose(python.map.embeddings(), rust.map.embeddings(), atol=1e-4)
    np.testing.assert_allclose(python.map.scores(["white"]), rust.map.scores(["white"]), atol=1e-4)


BOOM = """
import numpy as np

class Boom(Exception):
    pass

class Encoder:
    dim = 2

    def __init__(self, fail_at):
        self.calls = 0
        self.fail_at = fail_at

    def encode_image(self, rgb, regions):
        self.calls += 1
        if self.calls == self.fail_at:
            raise Boom(f"call {self.calls}")
        return {"grid": np.ones((2, 2, 2), np.float32)}

    def encode_text(self, text):
        return np.ones(2, np.float32)
"""


def test_an_exception_in_a_python_encoder_stops_the_run_and_the_map_stays(tmp_path):
    (tmp_path / "boom.py").write_text(BOOM)
    encoder = {"kind": "python", "path": "boom.py", "class": "Encoder", "params": {"fail_at": 3}}
    pipeline = vlem.Pipeline(config(encoder), config_dir=tmp_path)
    with pytest.raises(Exception) as raised:
        pipeline.run(max_frames=6)
    assert type(raised.value).__name__ == "Boom" and str(raised.value) == "call 3"
    assert any("encode_image" in str(frame) for frame in raised.traceback)
    m = pipeline.map
    assert m.frames_integrated == 2 and len(m) > 0
    assert m.save(tmp_path / "kept.vlem") == len(m)
    assert "call 3" in pipeline.status["state"]["failed"]


def test_errors_are_typed_and_carry_the_command_line_message(tmp_path):
    with pytest.raises(vlem.ConfigError, match="unknown encoder `clipp`.*known:.*colour-names"):
        vlem.Pipeline(config({"kind": "clipp"}))
    with pytest.raises(vlem.ConfigError, match="unknown field `bogus`"):
        vlem.Pipeline(config(bogus=1))
    # A typo inside a stage's table names the file (or text) and the line, as `vlem run` does.
    typo = '[encoder]\nkind = "colour-names"\n\n[map]\nkind = "point-cloud"\nmax_point = 5\n'
    (tmp_path / "typo.toml").write_text(typo)
    with pytest.raises(vlem.ConfigError, match=r"unknown field `max_point`.*\(config .*typo\.toml, line 6\)"):
        vlem.Pipeline(str(tmp_path / "typo.toml"))
    with pytest.raises(vlem.ConfigError, match=r"max_point.*\(config text, line 6\)"):
        vlem.Pipeline(typo)
    assert issubclass(vlem.ConfigError, vlem.VlemError) and issubclass(vlem.EncoderError, vlem.StageError)
    with pytest.raises(vlem.DatasetError):
        vlem.Pipeline(config()).run(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError):
        vlem.Map.load(tmp_path / "missing.vlem")
    (tmp_path / "junk.vlem").write_bytes(b"not a map")
    with pytest.raises(vlem.MapFileError):
        vlem.Map.load(tmp_path / "junk.vlem")
    pipeline = vlem.Pipeline(DEMO)
    pipeline.run(max_frames=1)
    with pytest.raises(vlem.QueryError):
        pipeline.map.query([])
    with pytest.raises(vlem.StageError, match="colour words"):
        pipeline.map.query(["a chair"])
    with pytest.raises(TypeError):
        vlem.Pipeline(42)
    with pytest.raises(vlem.ConfigError, match="python"):
        vlem.Pipeline(config({"kind": "python", "class": "X"}))


@pytest.mark.parametrize("set_before, expected", [(None, "cpus"), ("1", "1"), ("all", "cpus")])
def test_the_import_gives_candle_its_thread_count(set_before, expected):
    # candle re-reads /proc/cpuinfo on every CPU op unless RAYON_NUM_THREADS holds a count: the
    # import sets it to the CPUs this process may use, and keeps a count set before it.
    env = {k: v for k, v in os.environ.items() if k != "RAYON_NUM_THREADS"}
    if set_before is not None:
        env["RAYON_NUM_THREADS"] = set_before
    out = subprocess.run(
        [sys.executable, "-c", "import os, vlem; print(os.environ['RAYON_NUM_THREADS'])"],
        env=env, capture_output=True, text=True, check=True,
    )
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert out.stdout.strip() == (str(cpus) if expected == "cpus" else expected)

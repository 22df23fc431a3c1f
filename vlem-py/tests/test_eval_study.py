"""Evaluations and studies from Python: the same reports as `vlem eval ... --json` and the same
table as `vlem study`, Ctrl-C during a blocking run, and the comparison-study example as written.

`VLEM_BIN` names the `vlem` binary for the comparisons with the command (skipped without it).
"""

import _thread
import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import vlem

REPO = pathlib.Path(__file__).resolve().parents[2]
FRAMES = REPO / "data" / "living-room"

# A small labelled synthetic scene, mapped with the weight-free colour-names encoder.
SYNTHETIC = {
    "dataset": {"kind": "synthetic", "synthetic": {"seed": 2, "frames": 8, "width": 96, "height": 72}},
    "tracker": {"kind": "ground-truth"},
    "encoder": {"kind": "colour-names"},
    "map": {"kind": "point-cloud", "max_distance": 0.05},
}
# The colour-names encoder knows only colour words: each class is queried by a colour.
COLOURS = ["white", "brown", "grey", "red", "blue", "green"]
PROMPTS = {name: COLOURS[i % len(COLOURS)] for i, name in enumerate(vlem.class_names())}


def binary():
    path = os.environ.get("VLEM_BIN")
    if not path:
        pytest.skip("VLEM_BIN is not set: no vlem binary to compare with")
    return path


def toml_text(config):
    """The SYNTHETIC-shaped dict as TOML (tables of scalars and one nested table)."""
    lines = []
    for section, table in config.items():
        lines.append(f"[{section}]")
        nested = {k: v for k, v in table.items() if isinstance(v, dict)}
        for key, value in table.items():
            if not isinstance(value, dict):
                lines.append(f"{key} = {json.dumps(value)}")
        for name, inner in nested.items():
            lines.append(f"[{section}.{name}]")
            lines.extend(f"{k} = {json.dumps(v)}" for k, v in inner.items())
    return "\n".join(lines) + "\n"


def write_tum(path, poses):
    with open(path, "w") as f:
        for t, (x, y, z) in poses:
            f.write(f"{t:.6f} {x} {y} {z} 0 0 0 1\n")


def test_a_trajectory_report_is_the_commands_json(tmp_path):
    reference = [(0.1 * i, (0.1 * i, 0.02 * i * i, 0.0)) for i in range(20)]
    # A rigidly moved copy: no error after the alignment, and the shift is recovered.
    estimate = [(t, (x + 1.0, y - 2.0, z + 0.5)) for t, (x, y, z) in reference]
    write_tum(tmp_path / "ref.tum", reference)
    write_tum(tmp_path / "est.tum", estimate)
    report = vlem.eval_trajectory(tmp_path / "est.tum", tmp_path / "ref.tum", delta=2)
    assert report["associated"] == 20
    assert report["ate"]["position_m"]["rmse"] < 1e-6
    assert report["rpe"]["delta"] == 2 and report["rpe"]["translation_m"]["count"] == 18
    np.testing.assert_allclose(report["ate"]["alignment"]["translation"], [-1.0, 2.0, -0.5], atol=1e-6)
    with pytest.raises(FileNotFoundError, match="no-such.tum"):
        vlem.eval_trajectory(tmp_path / "no-such.tum", tmp_path / "ref.tum")

    json_path = tmp_path / "trajectory.json"
    subprocess.run(
        [binary(), "eval", "trajectory", "--estimate", str(tmp_path / "est.tum"),
         "--reference", str(tmp_path / "ref.tum"), "--delta", "2", "--json", str(json_path)],
        check=True, capture_output=True,
    )
    assert json.loads(json_path.read_text()) == report


def test_semseg_reports_are_the_commands_json(tmp_path):
    pipeline = vlem.Pipeline(SYNTHETIC)
    pipeline.run()
    pipeline.map.save(tmp_path / "map.vlem")
    report = vlem.eval_semseg3d(SYNTHETIC, tmp_path / "map.vlem", prompts=PROMPTS)
    assert 0.0 < report["miou"] <= 1.0
    assert report["protocol"] == "vlem" and report["map_points"] == len(pipeline.map)
    assert set(report["per_class"]) == {c["name"] for c in report["class_details"]}
    flat = vlem.eval_semseg2d(SYNTHETIC, prompts=PROMPTS, stride=4)
    assert flat["frames"] == 2 and 0.0 < flat["miou"] <= 1.0
    with pytest.raises(vlem.EvalError, match="cannot embed the class"):
        vlem.eval_semseg3d(SYNTHETIC, tmp_path / "map.vlem")  # "wall" is no colour word
    with pytest.raises(ValueError, match="rayfronts"):
        vlem.eval_semseg3d(SYNTHETIC, tmp_path / "map.vlem", protocol="paper")
    unlabelled = {**SYNTHETIC, "dataset": {"path": str(FRAMES)}}
    with pytest.raises(vlem.DatasetError, match="no ground-truth labels"):
        vlem.eval_semseg2d(unlabelled, prompts=PROMPTS)

    (tmp_path / "config.toml").write_text(toml_text(SYNTHETIC))
    (tmp_path / "prompts.json").write_text(json.dumps(PROMPTS))
    for dims, extra in [("semseg3d", ["--map", str(tmp_path / "map.vlem")]), ("semseg2d", ["--stride", "4"])]:
        json_path = tmp_path / f"{dims}.json"
        subprocess.run(
            [binary(), "eval", dims, "--config", str(tmp_path / "config.toml"),
             "--prompts", str(tmp_path / "prompts.json"), "--json", str(json_path), *extra],
            check=True, capture_output=True,
        )
        command = json.loads(json_path.read_text())
        ours = report if dims == "semseg3d" else flat
        for key in ["miou", "per_class", "class_details", "evaluated_classes", "encoder"]:
            assert command[key] == ours[key], key


def write_study(tmp_path, axes):
    (tmp_path / "base.toml").write_text(toml_text(SYNTHETIC))
    (tmp_path / "prompts.json").write_text(json.dumps(PROMPTS))
    study = tmp_path / "study.toml"
    study.write_text('[study]\nbase = "base.toml"\nprompts = "prompts.json"\n' + textwrap.dedent(axes))
    return study


def test_a_study_returns_its_table_and_resumes(tmp_path):
    study = write_study(tmp_path, """
        [[maps]]
        name = "point-cloud 5 cm"
        kind = "point-cloud"
        max_distance = 0.05

        [[maps]]
        name = "point-cloud 10 cm"
        kind = "point-cloud"
        max_distance = 0.1

        [[sequences]]
        name = "missing folder"
        path = "no-such-dataset"

        [[sequences]]
        name = "synthetic"
        kind = "synthetic"
        [sequences.synthetic]
        seed = 3
        frames = 6
        width = 64
        height = 48
    """)
    assert [c["map"] for c in vlem.study_cells(study)] == ["point-cloud 5 cm", "point-cloud 10 cm"] * 2
    events = []
    with pytest.warns(UserWarning, match="2 study cell"):
        table = vlem.study(study, tmp_path / "out", progress=events.append)
    assert isinstance(table, vlem.StudyTable) and len(table) == 4
    assert [r["status"] for r in table] == ["failed", "failed", "ok", "ok"]
    assert "no-such-dataset" in table.failed()[0]["error"]
    for row in table[2:]:
        assert 0.0 < row["miou"] <= 1.0 and row["peak_resident_bytes"] > 0 and row["map_points"] > 0
    assert events[0] == {"event": "planned", "total": 4}
    assert [e["event"] for e in events[1:]] == ["started", "finished"] * 4
    assert (tmp_path / "out" / "study.csv").read_text().startswith("cell,sequence,tracker")
    # Finished cells are not run again: only the two failed ones are.
    with pytest.warns(UserWarning):
        again = vlem.study(study, tmp_path / "out", progress=events.append)
    assert events[-5] == {"event": "planned", "total": 2} and again == table
    try:
        import pandas  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="pip install pandas"):
            table.to_dataframe()
    else:
        frame = table.to_dataframe()
        assert list(frame["status"]) == ["failed", "failed", "ok", "ok"]

    # The command gathers the same table from the same folder.
    subprocess.run([binary(), "study", str(study), "--out", str(tmp_path / "out"), "--report"],
                   check=True, capture_output=True)
    assert (tmp_path / "out" / "study.csv").read_text().count("\n") == 5


def test_ctrl_c_stops_a_blocking_run_and_the_map_stays():
    pipeline = vlem.Pipeline({
        "dataset": {"path": str(FRAMES)},
        "tracker": {"kind": "ground-truth"},
        "encoder": {"kind": "colour-names"},
        "map": {"kind": "point-cloud"},
    })

    def on_event(event):
        # What a Ctrl-C does: SIGINT for the main thread, here from the pipeline's own thread.
        if event["event"] == "tracked" and event["index"] == 2:
            _thread.interrupt_main()
        # The run looks at Python's signals ten times a second and now maps the 30 frames in a
        # few tenths of a second, so the interrupt could land after its last look (the run then
        # ends unstopped); each tracked frame takes a while here, as a camera's frames do.
        if event["event"] == "tracked":
            time.sleep(0.02)

    # interrupt_main() does nothing where SIGINT is ignored, as it is for a job started in the
    # background by a shell without job control (`bash .ci/run &`): handle it as Python does by
    # default, for this test.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            pipeline.run(progress=on_event)
    finally:
        signal.signal(signal.SIGINT, previous)
    status = pipeline.status
    assert 3 <= status["frames_tracked"] < len(os.listdir(FRAMES / "color")), status
    assert pipeline.map.frames_integrated >= 1
    assert pipeline.map.query(["white"])["queries"][0]["text"] == "white"
    assert vlem.class_names("scannet20")[:2] == ["wall", "floor"] and len(vlem.class_names()) == 40
    # The pipeline runs again afterwards, to the end.
    stats = pipeline.run(max_frames=3)
    assert stats["stopped"] is False and stats["frames"]["tracked"] == 3


def test_the_comparison_study_example_runs(tmp_path):
    script = REPO / "examples" / "python" / "compare_maps.py"
    done = subprocess.run(
        [sys.executable, str(script), "--frames", "4", "--out", str(tmp_path / "out")],
        capture_output=True, text=True,
    )
    assert done.returncode == 0, done.stderr
    assert re.search(r"point-cloud 5 cm\s+mIoU\s+\d", done.stdout), done.stdout
    assert (tmp_path / "out" / "study.csv").exists()

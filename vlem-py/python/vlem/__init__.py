"""vlem: real-time 3D vision-language embedding mapping, from Python.

A raw RGB-D stream becomes a metric 3D map whose points carry vision-language embeddings; the map
answers text queries with per-point scores, point sets and grasp poses, while it is being built.
This package is a thin front-end over the same Rust library as the ``vlem`` command:

>>> import vlem
>>> pipeline = vlem.Pipeline("configs/demo.toml")      # a TOML file, TOML text or a dict
>>> report = pipeline.run("data/living-room")          # blocking; releases the GIL
>>> answer = pipeline.map.query(["white wall"])
>>> best = answer["queries"][0]["indices"][0]          # int64 indices of the best point set
>>> points = pipeline.map.points[best]                 # float32[n, 3]

Evaluations (``vlem.eval_trajectory``, ``vlem.eval_semseg3d``, ``vlem.eval_semseg2d``) return
the ``vlem eval ... --json`` reports as dicts; ``vlem.study`` runs a comparison study and returns
its table (``.to_dataframe()`` with pandas installed).

See ``help(vlem.Pipeline)``, ``help(vlem.Map)``, ``help(vlem.Feed)`` and ``help(vlem.study)``.
"""

import os
import sys
import warnings
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Union

# Before the native module loads: candle, the models' CPU backend, looks up its thread count on
# every operation and, with RAYON_NUM_THREADS unset, counts the cores anew from /proc/cpuinfo each
# time (vlem-backends/src/threads.rs). As the ``vlem`` command does, give it the CPUs this process
# may use; a value set before the import is kept.
_threads = os.environ.get("RAYON_NUM_THREADS", "")
if not (_threads.isascii() and _threads.isdigit() and int(_threads) > 0):
    os.environ["RAYON_NUM_THREADS"] = str(
        len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    )
del _threads

from ._vlem import (  # noqa: F401  (re-exported)
    ConfigError,
    DatasetError,
    EncoderError,
    EvalError,
    Feed,
    Intrinsics,
    Map,
    MapFileError,
    Pipeline,
    QueryError,
    StageError,
    VlemError,
    __version__,
    class_names,
    eval_semseg2d,
    eval_semseg3d,
    eval_trajectory,
    plugins,
    study_cells,
)
from . import _vlem

__all__ = [
    "ConfigError",
    "DatasetError",
    "EncoderError",
    "EvalError",
    "Feed",
    "Intrinsics",
    "Map",
    "MapFileError",
    "PatchGrid",
    "Pipeline",
    "QueryError",
    "Regions",
    "StageError",
    "StudyTable",
    "VlemError",
    "__version__",
    "class_names",
    "eval_semseg2d",
    "eval_semseg3d",
    "eval_trajectory",
    "plugins",
    "study",
    "study_cells",
]


@dataclass
class Regions:
    """What a Python encoder's ``encode_image`` returns for region embeddings.

    ``index``: integer ``[h, w]`` array, the region of each pixel (``-1``: no embedding);
    ``table``: ``float32[regions, dim]``, one embedding per region (vlem normalises the rows).
    """

    index: Any
    table: Any


@dataclass
class PatchGrid:
    """What a Python encoder's ``encode_image`` returns for patch embeddings.

    ``grid``: ``float32[grid_h, grid_w, dim]`` covering the whole image (vlem interpolates it
    bilinearly to the pixels and normalises there). ``patch_size``, when given, is checked:
    ``grid_w * patch_size`` and ``grid_h * patch_size`` must be the image's width and height.
    """

    grid: Any
    patch_size: Optional[int] = None


def _progress_adapter(progress):
    """Turns ``progress`` (a callable taking an event dict, or a tqdm-like object with
    ``update``) into the callable the Rust side calls once per event."""
    if hasattr(progress, "update"):
        bar = progress

        def on_event(event):
            if event["event"] == "tracked":
                bar.update(1)
            elif hasattr(bar, "set_postfix"):
                bar.set_postfix(points=event.get("map_len"))

        return on_event
    return progress


class StudyTable(list):
    """A study's table: one dict per cell with a result (the columns of ``study.csv``: ``cell``,
    ``sequence``, ``tracker``, ``encoder``, ``map``, ``status``, ``miou``, ``map_bytes``,
    ``peak_resident_bytes``, per-stage ``*_ms``, ``error``, ...)."""

    def to_dataframe(self):
        """The table as a pandas DataFrame (pandas is not a dependency of vlem: install it)."""
        try:
            import pandas
        except ImportError as e:
            raise ImportError(
                "StudyTable.to_dataframe needs pandas: python -m pip install pandas"
            ) from e
        return pandas.DataFrame(list(self))

    def failed(self) -> List[dict]:
        """The rows of cells that failed (``status == "failed"``), each with its ``error``."""
        return [row for row in self if row.get("status") != "ok"]


def _cell_launcher():
    """The command that runs one study cell in a child process: this interpreter importing this
    package (found on the child's path even when it is not installed)."""
    package_root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    path = os.environ.get("PYTHONPATH")
    env = {"PYTHONPATH": package_root + (os.pathsep + path if path else "")}
    code = "import sys, vlem._vlem as v; v._study_cell(sys.argv[1])"
    return [sys.executable, "-c", code], env


def study(
    study_file: Union[str, "os.PathLike[str]"],
    out: Union[str, "os.PathLike[str]"] = "out/study",
    *,
    shard: Optional[str] = None,
    force: bool = False,
    report: bool = False,
    progress: Optional[Callable[[dict], Any]] = None,
) -> StudyTable:
    """Runs the comparison study ``study_file`` (the TOML format of ``vlem study``: a ``[study]``
    table with ``base``, and ``[[maps]]``, ``[[encoders]]``, ``[[trackers]]``, ``[[sequences]]``
    variants) and returns its table.

    Every cell maps and evaluates (semseg3d) in a child process of this interpreter, so a crash
    loses one cell and peak memory is the cell's own. Results land in ``out/cells/<cell>/``;
    finished cells are skipped when the study runs again (``force=True`` reruns them), so an
    interrupted study resumes. ``shard="i/n"`` runs a slice of the cells; ``report=True`` runs
    none and only gathers. ``out/study.csv`` is written either way. ``progress`` receives one
    dict per event (``{"event": "planned", "total": n}``, ``{"event": "started" | "finished",
    "cell": i, "label": ..., "status": ...}``). A failed cell is a row with ``status ==
    "failed"`` and its ``error`` (and a warning), not an exception.
    """
    launcher, env = _cell_launcher()
    rows = _vlem._study(
        os.fspath(study_file),
        os.fspath(out),
        launcher,
        env,
        shard=shard,
        force=force,
        report=report,
        progress=progress,
    )
    table = StudyTable(rows)
    failed = table.failed()
    if failed:
        warnings.warn(
            f"{len(failed)} study cell(s) failed, e.g. cell {failed[0]['cell']}: {failed[0]['error']}",
            stacklevel=2,
        )
    return table

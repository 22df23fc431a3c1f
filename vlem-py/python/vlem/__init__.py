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

See ``help(vlem.Pipeline)``, ``help(vlem.Map)`` and ``help(vlem.Feed)``.
"""

from dataclasses import dataclass
from typing import Any, Optional

from ._vlem import (  # noqa: F401  (re-exported)
    ConfigError,
    DatasetError,
    EncoderError,
    Feed,
    Intrinsics,
    Map,
    MapFileError,
    Pipeline,
    QueryError,
    StageError,
    VlemError,
    __version__,
    plugins,
)

__all__ = [
    "ConfigError",
    "DatasetError",
    "EncoderError",
    "Feed",
    "Intrinsics",
    "Map",
    "MapFileError",
    "PatchGrid",
    "Pipeline",
    "QueryError",
    "Segments",
    "StageError",
    "VlemError",
    "__version__",
    "plugins",
]


@dataclass
class Segments:
    """What a Python encoder's ``encode_image`` returns for segment embeddings.

    ``index``: integer ``[h, w]`` array, the segment of each pixel (``-1``: no embedding);
    ``table``: ``float32[segments, dim]``, one embedding per segment (vlem normalises the rows).
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

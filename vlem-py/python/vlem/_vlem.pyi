"""Type stubs of vlem's extension module (re-exported by ``vlem``)."""

import os
from typing import Any, Callable, Dict, List, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

__version__: str

class VlemError(Exception): ...
class ConfigError(VlemError): ...
class DatasetError(VlemError): ...
class StageError(VlemError): ...
class EncoderError(StageError): ...
class MapFileError(VlemError): ...
class QueryError(VlemError): ...
class EvalError(VlemError): ...

PathLike = Union[str, os.PathLike]
Config = Union[PathLike, Dict[str, Any]]

def plugins() -> List[Dict[str, str]]: ...
def eval_trajectory(
    estimate: PathLike,
    reference: PathLike,
    *,
    delta: int = 1,
    max_time_diff: float = 0.02,
    scale: bool = False,
) -> Dict[str, Any]: ...
def eval_semseg3d(
    config: Config,
    map: PathLike,
    *,
    dataset: Optional[PathLike] = None,
    max_frames: Optional[int] = None,
    classes: str = "nyu40",
    prompts: Optional[Union[Dict[str, str], PathLike]] = None,
    protocol: str = "vlem",
    stride: int = 1,
    voxel_size: Optional[float] = None,
    radius: float = 0.05,
    k: int = 5,
    config_dir: Optional[PathLike] = None,
) -> Dict[str, Any]: ...
def eval_semseg2d(
    config: Config,
    *,
    dataset: Optional[PathLike] = None,
    max_frames: Optional[int] = None,
    classes: str = "nyu40",
    prompts: Optional[Union[Dict[str, str], PathLike]] = None,
    stride: int = 30,
    config_dir: Optional[PathLike] = None,
) -> Dict[str, Any]: ...
def class_names(classes: str = "nyu40") -> List[str]: ...
def study_cells(study: PathLike) -> List[Dict[str, Any]]: ...
def _study(
    study: PathLike,
    out: PathLike,
    launcher: List[str],
    env: Dict[str, str],
    *,
    shard: Optional[str] = None,
    force: bool = False,
    report: bool = False,
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
) -> List[Dict[str, Any]]: ...
def _study_cell(dir: PathLike) -> None: ...

class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    def __init__(self, width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> None: ...
    @staticmethod
    def from_matrix(k: npt.ArrayLike, width: int, height: int) -> "Intrinsics": ...

Progress = Union[Callable[[Dict[str, Any]], None], Any]

class Map:
    kind: str
    dim: int
    frames_integrated: int
    points: npt.NDArray[np.float32]
    colours: npt.NDArray[np.uint8]
    @staticmethod
    def load(path: Union[str, os.PathLike]) -> "Map": ...
    def __len__(self) -> int: ...
    def embeddings(self, dtype: str = "float32") -> np.ndarray: ...
    def snapshot(self, dtype: str = "float32") -> Dict[str, Any]: ...
    def scores(self, texts: Union[str, Sequence[str]]) -> npt.NDArray[np.float32]: ...
    def query(
        self,
        texts: Union[str, Sequence[str]],
        *,
        segmenter: str = "threshold",
        threshold: Optional[float] = None,
        baseline: Optional[str] = None,
        grasp: bool = False,
    ) -> Dict[str, Any]: ...
    def save(self, path: Union[str, os.PathLike]) -> int: ...

class Feed:
    map: Map
    status: Dict[str, Any]
    def push(
        self,
        colour: npt.NDArray[np.uint8],
        depth: Union[npt.NDArray[np.float32], npt.NDArray[np.uint16]],
        *,
        timestamp: Optional[float] = None,
        pose: Optional[npt.ArrayLike] = None,
        depth_scale: float = 1000.0,
        block: bool = True,
    ) -> Optional[int]: ...
    def finish(self) -> Dict[str, Any]: ...
    def __enter__(self) -> "Feed": ...
    def __exit__(self, exc_type: Any = None, exc_value: Any = None, traceback: Any = None) -> bool: ...

class Pipeline:
    config: str
    map: Map
    status: Dict[str, Any]
    trajectory: npt.NDArray[np.float64]
    def __init__(
        self, config: Union[str, os.PathLike, Dict[str, Any]], *, config_dir: Optional[Union[str, os.PathLike]] = None
    ) -> None: ...
    def run(
        self,
        dataset: Optional[Union[str, os.PathLike]] = None,
        *,
        max_frames: Optional[int] = None,
        progress: Optional[Progress] = None,
        out: Optional[Union[str, os.PathLike]] = None,
    ) -> Dict[str, Any]: ...
    def start(
        self,
        intrinsics: Intrinsics,
        *,
        poses: Optional[bool] = None,
        capacity: int = 4,
        progress: Optional[Progress] = None,
    ) -> Feed: ...

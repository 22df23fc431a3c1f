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

def plugins() -> List[Dict[str, str]]: ...

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
    ) -> Dict[str, Any]: ...
    def start(
        self,
        intrinsics: Intrinsics,
        *,
        poses: Optional[bool] = None,
        capacity: int = 4,
        progress: Optional[Progress] = None,
    ) -> Feed: ...

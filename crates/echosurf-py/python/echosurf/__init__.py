"""echosurf from Python: read PLUS tracked sequences, extract surfaces, fit and evaluate the RBF.

The work runs in the Rust library with the GIL released; errors of the library (a bad file, whose
name the message gives; a failed fit; an exceeded memory budget) are raised as
:class:`EchosurfError`.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, NamedTuple, Optional, Union

import numpy as np

from . import _echosurf
from ._echosurf import EchosurfError, Model

__version__: str = _echosurf.__version__

__all__ = [
    "EchosurfError",
    "Extraction",
    "Model",
    "Sequence",
    "Surface",
    "extract",
    "extract_surfaces",
    "fit",
    "options_toml",
    "read_sequence",
]

PathLike = Union[str, "os.PathLike[str]"]
#: Called as ``progress(stage, fraction)`` with the stage's name and 0.0 ... 1.0; it runs with the
#: GIL held, and an exception it raises stops the work and is raised by the call that started it.
ProgressCallback = Callable[[str, float], Any]


@dataclass(frozen=True)
class Sequence:
    """A tracked ultrasound sequence as :func:`read_sequence` returns it.

    ``frames`` holds the pixels, MF-oriented (rows from near to far), shape (frames, height,
    width) or (frames, height, width, channels) in the file's element type. ``transforms`` maps
    each transform name (``"ProbeToTracker"``, ... without the ``Transform`` suffix) to its
    (frames, 4, 4) float64 matrices (NaN where a frame lacks it) and ``transform_valid`` to its
    per-frame status (``OK`` = True). ``image_valid`` is each frame's ``ImageStatus`` and
    ``timestamps_s`` its timestamp in seconds (NaN where missing).
    """

    frames: np.ndarray
    timestamps_s: np.ndarray
    image_valid: np.ndarray
    transforms: Dict[str, np.ndarray]
    transform_valid: Dict[str, np.ndarray]
    orientation: str
    width: int
    height: int
    channels: int
    element_type: str


class Extraction(NamedTuple):
    """One surface from :func:`extract`: vertices (N, 3) float64 in mm, faces (M, 3) int32
    (counter-clockwise seen from outside), and the report ``echosurf extract --report`` writes."""

    vertices: np.ndarray
    faces: np.ndarray
    report: Dict[str, Any]


class Surface(NamedTuple):
    """One surface of :func:`extract_surfaces`: its iso-level, vertices (N, 3) float64, faces
    (M, 3) int32 and vertex normals (N, 3) float64 (or (0, 3) when the surfacer made none)."""

    level: float
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray


def read_sequence(path: PathLike) -> Sequence:
    """Reads a tracked sequence (``.mha``, ``.mhd`` + data file, ``.igs.nrrd``)."""
    return Sequence(**_echosurf.read_sequence(os.fspath(path)))


def _options_json(options: Dict[str, Any]) -> str:
    """The user-tier keywords as the JSON object the library reads, refusing non-finite numbers."""
    converted: Dict[str, Any] = {}
    for key, value in options.items():
        if isinstance(value, np.ndarray):
            value = value.tolist()
        elif isinstance(value, np.generic):
            value = value.item()
        elif isinstance(value, tuple):
            value = list(value)
        try:
            json.dumps(value, allow_nan=False)
        except (TypeError, ValueError):
            raise ValueError(
                f"{key}: {value!r} is not a finite number, a string, a bool or a list of numbers"
            ) from None
        converted[key] = value
    return json.dumps(converted)


def _fspath(path: Optional[PathLike]) -> Optional[str]:
    return None if path is None else os.fspath(path)


def extract_surfaces(
    sequence_path: PathLike,
    calibration_path: PathLike,
    *,
    config: Optional[PathLike] = None,
    init: Optional[PathLike] = None,
    space: str = "ras",
    memory_budget_mb: Optional[float] = None,
    progress: Optional[ProgressCallback] = None,
    **options: Any,
) -> "tuple[List[Surface], Dict[str, Any]]":
    """Like :func:`extract`, for any number of iso-levels (``iso=[40, 60]``): every surface, in
    level order, and the report."""
    surfaces, report = _echosurf.extract(
        os.fspath(sequence_path),
        os.fspath(calibration_path),
        _options_json(options),
        config=_fspath(config),
        init=_fspath(init),
        space=space,
        memory_budget_mb=memory_budget_mb,
        progress=progress,
    )
    return [Surface(*s) for s in surfaces], json.loads(report)


def extract(
    sequence_path: PathLike,
    calibration_path: PathLike,
    *,
    config: Optional[PathLike] = None,
    init: Optional[PathLike] = None,
    space: str = "ras",
    memory_budget_mb: Optional[float] = None,
    progress: Optional[ProgressCallback] = None,
    **options: Any,
) -> Extraction:
    """Extracts the surface of a tracked sweep, as ``echosurf extract`` does, and returns
    ``(vertices, faces, report)``.

    ``calibration_path`` is the PLUS device-set XML with the Image->Probe calibration. The options
    are the defaults, then ``config`` (the TOML ``echosurf extract --print-config`` writes), then
    the user-tier keywords: ``iso`` ("auto" or a level), ``smoothing_mm``, ``sheet`` ("auto",
    "iso", "ridge"), ``resolution_mm``, ``max_samples``, ``cleanup``, ``method`` ("rbf", "voxel")
    and ``seed``. ``init`` is a band file (PNG mask or JSON polygon) for the first frame, ``space``
    "ras" (the default, as the CLI) or "lps", ``memory_budget_mb`` the budget the run is checked
    against (default: half the machine's memory). The same input and options give the same
    vertices and faces as ``echosurf extract`` writes. Several levels: :func:`extract_surfaces`.
    """
    surfaces, report = extract_surfaces(
        sequence_path,
        calibration_path,
        config=config,
        init=init,
        space=space,
        memory_budget_mb=memory_budget_mb,
        progress=progress,
        **options,
    )
    if len(surfaces) != 1:
        raise ValueError(
            f"extract() returns one surface, the options give {len(surfaces)} levels: "
            "use extract_surfaces()"
        )
    surface = surfaces[0]
    return Extraction(surface.vertices, surface.faces, report)


def fit(
    points: Any,
    values: Any,
    *,
    smoothing: float = 1.0,
    accuracy: float = 2.0,
    solver: str = "auto",
    max_centres: Optional[int] = None,
    reduce: bool = False,
    seed: int = 0,
    memory_budget_mb: Optional[float] = None,
    progress: Optional[ProgressCallback] = None,
) -> Model:
    """Fits the smoothing biharmonic RBF to ``values`` (N,) at ``points`` (N, 3) in mm, as
    ``echosurf fit`` does (same defaults), and returns the :class:`Model`.

    ``smoothing`` is the weight w in mm (0 interpolates, larger is smoother), ``accuracy`` the
    largest allowed system residual in grey levels, ``solver`` "auto", "direct", "pu" or "fast".
    """
    points_array = np.ascontiguousarray(points, dtype=np.float64)
    values_array = np.ascontiguousarray(values, dtype=np.float64)
    if points_array.ndim != 2 or points_array.shape[1:] != (3,):
        raise ValueError(f"points must have shape (N, 3), got {points_array.shape}")
    if values_array.ndim != 1:
        raise ValueError(f"values must have shape (N,), got {values_array.shape}")
    for name, number in (("smoothing", smoothing), ("accuracy", accuracy)):
        if not math.isfinite(number):
            raise ValueError(f"{name} must be finite, got {number}")
    return _echosurf.fit(
        points_array,
        values_array,
        float(smoothing),
        float(accuracy),
        solver=solver,
        max_centres=max_centres,
        reduce=reduce,
        seed=seed,
        memory_budget_mb=memory_budget_mb,
        progress=progress,
    )


def options_toml(
    *,
    config: Optional[PathLike] = None,
    memory_budget_mb: Optional[float] = None,
    **options: Any,
) -> str:
    """The full option set :func:`extract` would run with these arguments, as the TOML
    ``echosurf extract --print-config`` writes (without its ``[outputs]``); checks them as
    :func:`extract` does."""
    return _echosurf.options_toml(
        _options_json(options), config=_fspath(config), memory_budget_mb=memory_budget_mb
    )

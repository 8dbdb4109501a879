"""Type stubs of the native module (crates/echosurf-py/src/lib.rs); use the wrappers in
``echosurf`` rather than these directly."""

from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import numpy.typing as npt

__version__: str

class EchosurfError(Exception):
    """An error of the echosurf library: a bad or unreadable file (the message names it), an
    option out of range, a failed fit or a memory budget that would be exceeded."""

class Model:
    """A fitted RBF model (from :func:`fit` or :meth:`Model.load`)."""

    @property
    def report_json(self) -> str:
        """The fit report as JSON (``echosurf fit --json``); empty for a loaded model."""
    @property
    def centres(self) -> int:
        """Number of centres (summed over the patches for partition of unity)."""
    @property
    def smoothing(self) -> float:
        """The smoothing weight w (mm) the model was fitted with."""
    def evaluate(
        self, points: npt.ArrayLike
    ) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Values (N,) and gradients (N, 3) of the model at ``points`` (N, 3), mm."""
    def save(self, path: str) -> None:
        """Writes the model as ``.esrbf`` (what ``echosurf fit --out`` writes), atomically."""
    @staticmethod
    def load(path: str) -> "Model":
        """Reads a ``.esrbf`` model."""

def read_sequence(path: str) -> Dict[str, Any]: ...
def user_option_names() -> List[str]: ...
def extract(
    sequence_path: str,
    calibration_path: str,
    options_json: str,
    config: Optional[str] = None,
    init: Optional[str] = None,
    space: str = "ras",
    memory_budget_mb: Optional[float] = None,
    progress: Optional[Callable[[str, float], Any]] = None,
) -> Tuple[
    List[
        Tuple[
            float,
            npt.NDArray[np.float64],
            npt.NDArray[np.int32],
            npt.NDArray[np.float64],
        ]
    ],
    str,
]: ...
def fit(
    points: npt.NDArray[np.float64],
    values: npt.NDArray[np.float64],
    smoothing: float,
    accuracy: float,
    solver: str = "auto",
    max_centres: Optional[int] = None,
    reduce: bool = False,
    seed: int = 0,
    memory_budget_mb: Optional[float] = None,
    progress: Optional[Callable[[str, float], Any]] = None,
) -> Model: ...
def options_toml(
    options_json: str,
    config: Optional[str] = None,
    memory_budget_mb: Optional[float] = None,
) -> str: ...

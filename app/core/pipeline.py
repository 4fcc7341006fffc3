"""One comparison from end to end: align, localise, detect, decide.

This is the function the CLI (``scandiff compare``) and the service's worker both call, so a
result over HTTP is identical to the CLI's on the same inputs and parameters.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud

ProgressCallback = Callable[[str, float], None]
"""Called as ``progress(stage, fraction_done)`` with fraction in [0, 1]."""

LABEL_UNCHANGED = 0
LABEL_CHANGED = 1
LABEL_UNOBSERVED = -1


@dataclass(frozen=True)
class RegionSummary:
    """One connected cluster of changed points, in file coordinates."""

    kind: str  # "added" (in the scan, not in the reference) or "removed"
    n_points: int
    centroid: list[float]
    bbox_min: list[float]
    bbox_max: list[float]
    mean_distance: float
    max_distance: float


@dataclass(frozen=True)
class ComparisonResult:
    """Everything one comparison produced.

    ``reference_label`` and ``scan_label`` have one entry per row of the source file (points
    dropped on load are -1): 0 unchanged, 1 changed, -1 unobserved.
    """

    method: str
    variant: str
    params: dict[str, Any]
    score: float
    threshold: float
    changed: bool
    calibration: dict[str, Any]
    registration: dict[str, Any]
    regions: list[RegionSummary]
    n_reference: int
    n_scan: int
    reference_label: NDArray[np.int8]
    scan_label: NDArray[np.int8]
    reference_distance: NDArray[np.float32]
    scan_distance: NDArray[np.float32]
    timings: dict[str, float] = field(default_factory=dict)

    def to_json_dict(self) -> dict[str, Any]:
        """The JSON object printed by ``scandiff compare --json``."""
        raise NotImplementedError

    def write_labels_npz(self, path: str | Path) -> None:
        """Write ``reference_changed``, ``scan_changed``, ``reference_label``, ``scan_label``."""
        raise NotImplementedError


def compare(
    reference: PointCloud,
    scan: PointCloud,
    *,
    method: str = "gmm",
    variant: str = "improved",
    align: bool = True,
    random_state: int = 0,
    params: Mapping[str, Any] | None = None,
    progress: ProgressCallback | None = None,
) -> ComparisonResult:
    """Compare ``scan`` against ``reference``; see the module docstring."""
    raise NotImplementedError

"""A stand-in for ``app.core.pipeline.compare`` so job durability tests run fast.

The durability machinery (claim, lease, recovery) does not depend on the numbers; this fake
returns a deterministic result shaped like :class:`app.core.pipeline.ComparisonResult` in a few
milliseconds.  It reaches the worker through the jobs' one test seam,
:data:`app.jobs.hooks.job_hooks`: tests set ``job_hooks.compare`` to :func:`fake_compare`
(in-process, with ``monkeypatch``); :data:`CONSUMER_BOOTSTRAP` starts a consumer process with it
installed (:func:`install`), so the consumer never imports the real pipeline.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud
from app.core.explanation import explain_comparison
from app.core.quality import quality_warnings
from app.jobs.hooks import job_hooks

CONSUMER_BOOTSTRAP = (
    "import sys, app.testing.fake_pipeline as fake; fake.install(); "
    "from app.jobs.consumer import main; sys.exit(main())"
)


@dataclass(frozen=True)
class FakeRegion:
    """A region with the fields of ``RegionSummary``."""

    kind: str
    n_points: int
    centroid: list[float]
    bbox_min: list[float]
    bbox_max: list[float]
    mean_distance: float
    max_distance: float
    evidence: str = "seen_empty"
    confidence: float | None = None

    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON types."""
        return asdict(self)


@dataclass(frozen=True)
class FakeResult:
    """The :class:`app.core.comparison.protocol.Comparison` the worker reads (no origins)."""

    score: float
    threshold: float
    changed: bool
    calibration: dict[str, Any]
    registration: dict[str, Any]
    regions: list[FakeRegion]
    reference_label: NDArray[np.int8]
    scan_label: NDArray[np.int8]
    reference_distance: NDArray[np.float32]
    scan_distance: NDArray[np.float32]
    reference_region: NDArray[np.int32]
    scan_region: NDArray[np.int32]
    timings: dict[str, float] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)
    uncertain_regions: list[FakeRegion] = field(default_factory=list)
    localisation: dict[str, Any] = field(default_factory=dict)
    sensor_origins: dict[str, list[dict[str, Any]]] | None = None
    visibility: dict[str, dict[str, Any]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @cached_property
    def quality_warnings(self) -> list[dict[str, Any]]:
        """The core's warnings of this result."""
        return quality_warnings(self)

    @cached_property
    def explanation(self) -> dict[str, Any]:
        """The core's explanation of this result."""
        return explain_comparison(self)

    def write_labels_npz(self, path: str | Path) -> None:
        """Same arrays as the real result."""
        with open(path, "wb") as handle:
            np.savez_compressed(
                handle,
                reference_changed=self.reference_label == 1,
                scan_changed=self.scan_label == 1,
                reference_label=self.reference_label,
                scan_label=self.scan_label,
            )


def fake_compare(
    reference: PointCloud,
    scan: PointCloud,
    *,
    method: str = "gmm",
    variant: str = "improved",
    align: bool = True,
    random_state: int = 0,
    params: Mapping[str, Any] | None = None,
    progress: Callable[[str, float], None] | None = None,
    threads: int | None = None,
    site_calibration: Mapping[str, Any] | None = None,
    geometry_cache: object | None = None,
) -> FakeResult:
    """A deterministic result: the scan's points beyond x > 1 are an "added" region."""
    for stage, fraction in (("align", 0.05), ("localise", 0.35), ("detect", 0.65)):
        if progress is not None:
            progress(stage, fraction)
    added = scan.points[:, 0] > 1.0
    scan_label = np.zeros(scan.n_source, dtype=np.int8)
    scan_label[scan.source_index[added]] = 1
    regions = []
    if added.any():
        box = scan.points[added]
        regions.append(
            FakeRegion(
                "added",
                int(added.sum()),
                box.mean(axis=0).tolist(),
                box.min(axis=0).tolist(),
                box.max(axis=0).tolist(),
                0.5,
                float("nan") if params and params.get("nan_max") else 1.0,
            )
        )
    return FakeResult(
        score=float(added.mean()),
        threshold=0.01,
        changed=bool(added.mean() > 0.01),
        calibration={"noise": np.float64(0.001), "samples": np.arange(3)},
        registration={"transform": np.eye(4), "fitness": np.float32(1.0), "rmse": float("inf")},
        regions=regions,
        reference_label=np.zeros(reference.n_source, dtype=np.int8),
        scan_label=scan_label,
        reference_distance=np.zeros(reference.n_source, dtype=np.float32),
        scan_distance=np.where(scan_label == 1, 1.0, 0.0).astype(np.float32),
        reference_region=np.full(reference.n_source, -1, dtype=np.int32),
        scan_region=np.where(scan_label == 1, 0, -1).astype(np.int32),
        timings={"align": 0.001},
        params={"variant": variant, "random_state": random_state, **dict(params or {})},
    )


def install() -> None:
    """Make the jobs of this process compare with :func:`fake_compare` (the real one is slow)."""
    job_hooks.compare = fake_compare

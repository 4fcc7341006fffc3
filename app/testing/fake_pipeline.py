"""A stand-in for ``app.core.pipeline.compare`` so job durability tests run fast.

The durability machinery (claim, lease, recovery) does not depend on the numbers; this fake
returns a deterministic :class:`app.core.pipeline.ComparisonResult` (the real type, with its
typed reports) in a few milliseconds.  It reaches the worker through the jobs' one test seam,
:data:`app.jobs.hooks.job_hooks`: tests set ``job_hooks.compare`` to :func:`fake_compare`
(in-process, with ``monkeypatch``); :data:`CONSUMER_BOOTSTRAP` starts a consumer process with it
installed (:func:`install`), so the consumer never imports the real pipeline.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Unpack

import numpy as np

from app.core.cloud import PointCloud
from app.core.comparison.result import ComparisonResult, RegionSummary
from app.jobs.hooks import job_hooks
from app.testing.results import calibration_report, registration_report

if TYPE_CHECKING:  # not imported: loading the detectors would cost every fake consumer seconds
    from app.core.comparison.load import PairOptions

CONSUMER_BOOTSTRAP = (
    "import sys, app.testing.fake_pipeline as fake; fake.install(); "
    "from app.jobs.consumer import main; sys.exit(main())"
)


def fake_compare(
    reference: PointCloud,
    scan: PointCloud,
    *,
    progress: Callable[[str, float], None] | None = None,
    site_calibration: Mapping[str, Any] | None = None,
    geometry_cache: object | None = None,
    **options: Unpack[PairOptions],
) -> ComparisonResult:
    """A deterministic result: the scan's points beyond x > 1 are an "added" region."""
    method, variant = options.get("method", "gmm"), options.get("variant", "improved")
    params = options.get("params")
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
            RegionSummary(
                "added",
                int(added.sum()),
                box.mean(axis=0).tolist(),
                box.min(axis=0).tolist(),
                box.max(axis=0).tolist(),
                0.5,
                float("nan") if params and params.get("nan_max") else 1.0,
            )
        )
    changed = bool(added.mean() > 0.01)
    return ComparisonResult(
        method=method,
        variant=variant,
        params={
            "variant": variant,
            "random_state": options.get("random_state", 0),
            **dict(params or {}),
        },
        score=float(added.mean()),
        threshold=0.01,
        changed=changed,
        # numpy values and a non-finite number, as a detector's and GICP's can be
        calibration=calibration_report(
            {"noise": np.float64(0.001), "samples": np.arange(3)},
            changed=changed,
            n_regions=len(regions),
        ),
        registration=registration_report(fitness=np.float32(1.0), rmse=float("inf")),
        regions=regions,
        n_reference=len(reference),
        n_scan=len(scan),
        reference_label=np.zeros(reference.n_source, dtype=np.int8),
        scan_label=scan_label,
        reference_distance=np.zeros(reference.n_source, dtype=np.float32),
        scan_distance=np.where(scan_label == 1, 1.0, 0.0).astype(np.float32),
        reference_region=np.full(reference.n_source, -1, dtype=np.int32),
        scan_region=np.where(scan_label == 1, 0, -1).astype(np.int32),
        timings={"align": 0.001},
    )


def install() -> None:
    """Make the jobs of this process compare with :func:`fake_compare` (the real one is slow)."""
    job_hooks.compare = fake_compare

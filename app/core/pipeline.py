"""One comparison from end to end, as explicit stages (:mod:`app.core.comparison`).

This is the function the CLI (``scandiff compare``) and the service's worker both call, so a
result over HTTP is identical to the CLI's on the same inputs and parameters.

Stages, each a function of :mod:`app.core.comparison` taking and returning dataclasses (call
them one by one to compare part of a pair: a subsample to align, a crop to localise):

1. **load** (:func:`~app.core.comparison.load.load_pair`): the parameters validated and both
   clouds shifted by one rounded origin taken from the reference, so georeferenced coordinates
   keep their millimetres in float arithmetic; every coordinate reported is shifted back.
2. **origins** (:mod:`~app.core.comparison.origins`): each cloud's sensor origins (the
   reference's before alignment, the scan's after it).
3. **align** (:func:`~app.core.comparison.align.align_scan`): registration of the scan onto
   the reference (GICP via small_gicp), or the identity with its fit measured.
4. **localise** (:func:`~app.core.comparison.localise.localise_pair`): per-point labels
   (changed / unchanged / unobserved) for both clouds and connected regions
   (:mod:`app.core.localise`).
5. **decide** (:mod:`~app.core.comparison.decide`): the paper's global EMD score between the
   parts of the two clouds that both sensors observed, with a threshold calibrated from the
   clouds' own resampling noise, then the decision rule.
6. **assemble** (:func:`~app.core.comparison.assemble.assemble_result`): one
   :class:`ComparisonResult` in file coordinates.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar, Unpack

from threadpoolctl import threadpool_limits

from app.core.cache.geometry import GeometryCache
from app.core.cloud import PointCloud
from app.core.comparison.align import Alignment, align_scan
from app.core.comparison.assemble import assemble_result
from app.core.comparison.decide import decide_change, detect_change
from app.core.comparison.load import LoadedPair, PairOptions, load_pair
from app.core.comparison.localise import (
    REFERENCE_AHEAD_MIN_POINTS,
    localise_pair,
    reference_neighbourhoods_ahead,
    scan_neighbourhoods_ahead,
    searches_ahead,
)
from app.core.comparison.memory import ReferenceMemory
from app.core.comparison.origins import (
    SensorOrigins,
    resolve_reference_origins,
    resolve_scan_origins,
)
from app.core.comparison.result import ComparisonResult, RegionSummary
from app.core.comparison_settings import parse_comparison_params
from app.core.localise import Localisation

__all__ = [
    "REFERENCE_AHEAD_MIN_POINTS",
    "ComparisonResult",
    "LocaliseStep",
    "ProgressCallback",
    "RegionSummary",
    "compare",
    "parse_comparison_params",
    "run_stages",
]

ProgressCallback = Callable[[str, float], None]
"""Called as ``progress(stage, fraction_done)`` with fraction in [0, 1]."""

Value = TypeVar("Value")


@dataclass(frozen=True)
class Matched:
    """The stages up to localisation: origins, alignment, labels and the region size floor."""

    origins: SensorOrigins
    alignment: Alignment
    localisation: Localisation
    min_region_points: int


def compare(
    reference: PointCloud,
    scan: PointCloud,
    *,
    progress: ProgressCallback | None = None,
    site_calibration: Mapping[str, Any] | None = None,
    geometry_cache: GeometryCache | None = None,
    **options: Unpack[PairOptions],
) -> ComparisonResult:
    """Compare ``scan`` against ``reference``; see the module docstring.

    ``method``, ``variant``, ``align``, ``random_state``, ``params`` and ``threads`` are the
    keyword arguments of :func:`~app.core.comparison.load.load_pair` (:class:`PairOptions`).

    Parameters
    ----------
    reference, scan : PointCloud
        The clouds as read from their files.
    method : {"gmm", "pca", "planes"}
        Or one of the paper's names (``"pe"``, ``"PE-EMD"``...); the result carries the
        canonical name.
    variant : {"improved", "paper"}
    align : bool
        Register the scan onto the reference first (recommended for robot scans).
    random_state : int
        Seeds every random choice, so a result can be replayed exactly.
    params : mapping, optional
        Detector keyword parameters, plus the reserved keys ``"registration"`` and
        ``"localisation"`` (dicts of keyword parameters for those stages), ``"decision"``
        (one of :data:`app.core.comparison_settings.DECISION_RULES`) and
        ``"reference_origin"`` / ``"scan_origin"`` (sensor positions in each file's frame,
        overriding what the file says: 3 numbers, or a list of them for a cloud merged from
        several stations, whose ``station_index`` attribute, if any, says which took each
        point), ``"estimate_origins"`` (default true: estimate a missing or contradicted
        origin from the points, :mod:`app.core.origins.resolve`) and ``"recover_stations"``
        (``"auto"``, default: a cloud left without an origin whose sampling is a lidar's,
        :func:`app.core.origins.sampling.lidar_sampling`, gets its stations recovered,
        :func:`app.core.origins.station_recovery.recover_stations`, a second or two per cloud; when
        none are, it is a merged lidar cloud with unknown stations and the other cloud's
        candidates get the origin-free surface test; ``true``: recover whatever the sampling;
        ``false``: never).
        The origins used are reported in ``sensor_origins``, contradicted ones in ``warnings``.
    progress : callable, optional
        ``progress(stage, fraction)`` after each stage.
    threads : int, optional
        Threads the localiser may use (default: ``OMP_NUM_THREADS`` if set, else every CPU
        this process may run on).  Detectors run their BLAS calls on one thread (small
        matrices: more threads only contend).  Results do not depend on it.
    site_calibration : mapping, optional
        A site's thresholds learned from its reviewed jobs
        (:func:`app.core.site_calibration.learn_site_calibration`); applied when learned for
        this method and variant.  Its provenance is in ``calibration.site`` either way.
    geometry_cache : GeometryCache, optional
        Where the reference's k-NN geometry, resolved origin and alignment arrays are kept
        between comparisons (read when valid, written otherwise, :mod:`app.core.cache.geometry`,
        :mod:`app.core.cache.reference_origin`, :mod:`app.core.cache.reference_alignment`).
        Results do not depend on it.

    Returns
    -------
    ComparisonResult

    Raises
    ------
    InputError
        Unknown method, variant or parameter; clouds that cannot be aligned.
    """
    loaded = load_pair(reference, scan, **options)
    return run_stages(
        loaded,
        progress=progress,
        site_calibration=site_calibration,
        geometry_cache=geometry_cache,
    )


class LocaliseStep(Protocol):
    """Stage 4 done another way, with the samples that bound the stages around it: the tiled
    comparison's (:mod:`app.core.tiling.compare`, tile by tile within a memory budget)."""

    @property
    def registration_sample(self) -> int | None:
        """Align on at most about this many points of each cloud (None: all)."""

    @property
    def detection_sample(self) -> int | None:
        """Score at most this many points of each cloud (None: all)."""

    @property
    def detection_seed(self) -> int:
        """Seeds the choice of those points."""

    @property
    def params(self) -> Mapping[str, Any]:
        """Parameters reported in effect besides the comparison's own."""

    @property
    def detect_fraction(self) -> float:
        """The progress reported when detection starts."""

    def localise(
        self,
        loaded: LoadedPair,
        origins: SensorOrigins,
        alignment: Alignment,
        report: ProgressCallback,
        timings: dict[str, float],
    ) -> tuple[Localisation, int]:
        """Labels and regions of both clouds, and the region size floor they used."""


def run_stages(
    loaded: LoadedPair,
    *,
    progress: ProgressCallback | None = None,
    site_calibration: Mapping[str, Any] | None = None,
    geometry_cache: GeometryCache | None = None,
    localise_step: LocaliseStep | None = None,
) -> ComparisonResult:
    """Stages 2-6 of a loaded pair (see :func:`compare` for the parameters).

    Parameters
    ----------
    localise_step : LocaliseStep, optional
        Stage 4 done another way (no neighbour searches ahead, no geometry cache); None:
        :func:`~app.core.comparison.localise.localise_pair` on the whole clouds.

    Returns
    -------
    ComparisonResult
    """

    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, fraction)

    timings: dict[str, float] = {}
    memory = ReferenceMemory.of(geometry_cache, loaded)
    # BLAS on one thread: the stages' products are (n, 3) x (3, 3) and memory-bound, and
    # OpenBLAS's second thread spins after each of them (~0.15 CPU s at 1M + 1M, the same
    # result); the detector limits its own BLAS calls likewise
    with threadpool_limits(limits=1, user_api="blas"):
        matched = _match(loaded, memory, report, timings, localise_step)
    memory.keep()
    report("detect", 0.65 if localise_step is None else localise_step.detect_fraction)
    started = time.perf_counter()
    detected = detect_change(
        loaded.settings.detector,
        loaded.reference_points,
        matched.alignment.aligned_scan,
        matched.localisation,
        sample_points=None if localise_step is None else localise_step.detection_sample,
        random_state=0 if localise_step is None else localise_step.detection_seed,
    )
    timings["detect"] = time.perf_counter() - started
    decision = decide_change(
        detected.detection,
        matched.localisation.regions,
        min_region_points=matched.min_region_points,
        rule=loaded.settings.decision,
        method=loaded.method,
        variant=loaded.variant,
        site_calibration=site_calibration,
    )
    report("done", 1.0)
    return assemble_result(
        loaded,
        matched.origins,
        matched.alignment,
        matched.localisation,
        detected,
        decision,
        timings,
        None if localise_step is None else localise_step.params,
    )


def _timed(timings: dict[str, float], name: str, run: Callable[[], Value]) -> Value:
    """``run()``, its seconds added to ``timings[name]``."""
    started = time.perf_counter()
    value = run()
    timings[name] = timings.get(name, 0.0) + time.perf_counter() - started
    return value


def _match(
    loaded: LoadedPair,
    memory: ReferenceMemory,
    report: ProgressCallback,
    timings: dict[str, float],
    localise_step: LocaliseStep | None = None,
) -> Matched:
    """Stages 2-4: origins, alignment and localisation, with the neighbour searches ahead.

    With a second thread the reference's neighbour search starts first and runs while the
    reference's origin is resolved and the scan aligned (none of which needs it); on one
    thread the origin comes first, so that a cache written by the search holds it.  The
    scan's own search runs while its origin is resolved.  A ``localise_step`` of its own
    (tiles) has no searches ahead.
    """
    settings = loaded.settings
    ahead = localise_step is None and searches_ahead(
        settings.align, loaded.threads, len(loaded.reference_points)
    )
    sample = None if localise_step is None else localise_step.registration_sample
    reference_origins = None
    if not ahead:
        reference_origins = _timed(
            timings, "origins", lambda: resolve_reference_origins(loaded, memory)
        )
    report("align", 0.05)
    with reference_neighbourhoods_ahead(
        loaded.reference_points, settings.localisation, ahead, memory.cache, memory.facts
    ) as reference_neighbourhoods:
        if reference_origins is None:
            reference_origins = _timed(
                timings, "origins", lambda: resolve_reference_origins(loaded, memory)
            )
        alignment = _timed(
            timings,
            "align",
            lambda: align_scan(loaded, memory.alignment, sample_points=sample),
        )
        with scan_neighbourhoods_ahead(
            alignment.aligned_scan, settings.localisation, ahead, loaded.threads
        ) as scan_neighbourhoods:
            scan_origins = _timed(
                timings,
                "origins",
                lambda: resolve_scan_origins(loaded, alignment, reference_origins),
            )
            origins = SensorOrigins(reference_origins, scan_origins)
            loaded.release_scan_points()  # a shifted copy when the files are georeferenced
            report("localise", 0.35)
            started = time.perf_counter()
            if localise_step is not None:
                localisation, min_region_points = localise_step.localise(
                    loaded, origins, alignment, report, timings
                )
            else:
                localisation = localise_pair(
                    reference_origins.epoch(loaded.reference_points, reference_neighbourhoods),
                    scan_origins.epoch(alignment.aligned_scan, scan_neighbourhoods),
                    threads=loaded.threads,
                    localisation_params=settings.localisation,
                )
                min_region_points = int(localisation.parameters.get("min_region_points", 1))
    timings["localise"] = time.perf_counter() - started
    return Matched(origins, alignment, localisation, min_region_points)

"""Stage 4, **localise**: per-point labels and regions of both clouds
(:func:`app.core.localise.localise_changes`), with the neighbour searches started ahead.

The reference's nearest-neighbour search is the largest single cost of localisation; from
:data:`REFERENCE_AHEAD_MIN_POINTS` points and with two threads it runs on a second thread while
the scan is aligned (:func:`reference_neighbourhoods_ahead`), and the scan's while its origin is
resolved (:func:`scan_neighbourhoods_ahead`).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from app.core.cache.geometry import GeometryCache, reference_neighbourhoods
from app.core.localise import (
    EpochCloud,
    Localisation,
    Neighbourhoods,
    NeighbourhoodSearch,
    localise_changes,
    start_neighbourhood_search,
)

REFERENCE_AHEAD_MIN_POINTS = 50_000
"""From this many reference points (and with >= 2 threads) the reference's nearest-neighbour
search starts on a second thread while the scan is aligned: alignment uses one core, and the
search is the largest single cost of localisation (gain in ``docs/performance.md``)."""


def searches_ahead(align: bool, threads: int, n_reference: int) -> bool:
    """Whether the neighbour searches run ahead: alignment on, >= 2 threads and a reference of
    at least :data:`REFERENCE_AHEAD_MIN_POINTS` points."""
    return align and threads >= 2 and n_reference >= REFERENCE_AHEAD_MIN_POINTS


Prepared = Neighbourhoods | NeighbourhoodSearch | None
"""Neighbourhoods found (or being found) before :func:`localise_pair`, or None."""


@contextmanager
def reference_neighbourhoods_ahead(
    reference_points: NDArray[np.float64],
    localisation_params: Mapping[str, Any],
    enabled: bool,
    cache: GeometryCache | None = None,
    facts: Mapping[str, tuple[str, Any]] | None = None,
) -> Iterator[Prepared]:
    """The reference's neighbourhood search running on a second thread, or None (not
    ``enabled``, a small cloud, or see :func:`start_neighbourhood_search`).  On leaving, a
    search still running is stopped at its next chunk and waited for, so no thread outlives
    the comparison.  With a ``cache``, from it when it holds them, else written to it (with
    ``facts``)."""
    ahead = enabled and len(reference_points) >= REFERENCE_AHEAD_MIN_POINTS
    search = reference_neighbourhoods(
        reference_points, localisation_params, cache=cache, ahead=ahead, facts=facts
    )
    try:
        yield search
    finally:
        if isinstance(search, NeighbourhoodSearch):
            search.cancel()


@contextmanager
def scan_neighbourhoods_ahead(
    aligned_scan: NDArray[np.float64],
    localisation_params: Mapping[str, Any],
    enabled: bool,
    threads: int,
) -> Iterator[Prepared]:
    """The aligned scan's neighbourhood search on a thread of its own (``enabled`` and from
    :data:`REFERENCE_AHEAD_MIN_POINTS` points), else None; stopped on leaving."""
    search = (
        start_neighbourhood_search(aligned_scan, openmp_threads=threads, **localisation_params)
        if enabled and len(aligned_scan) >= REFERENCE_AHEAD_MIN_POINTS
        else None
    )
    try:
        yield search
    finally:
        if isinstance(search, NeighbourhoodSearch):
            search.cancel()


def localise_pair(
    reference: EpochCloud,
    scan: EpochCloud,
    *,
    threads: int,
    localisation_params: Mapping[str, Any],
) -> Localisation:
    """Labels and regions of both clouds, on ``threads`` OpenMP threads.

    Parameters
    ----------
    reference : EpochCloud
        The reference (local frame) with its sensor origins, or any part of it
        (:meth:`EpochCloud.subset`: a crop).
    scan : EpochCloud
        The aligned scan in the same frame, with its origins in it.
    threads : int
    localisation_params : mapping
        :data:`app.core.localise.DEFAULT_PARAMETERS` keywords.

    Returns
    -------
    Localisation
    """
    with threadpool_limits(limits=threads, user_api="openmp"):
        return localise_changes(
            reference,
            scan,
            # Not registration.rmse: that includes sampling distance and real change (0.15 m
            # on KITTI); localise measures the remaining misalignment itself from surfaces.
            registration_rmse=0.0,
            threads=threads,
            **localisation_params,
        )

"""Localisation's keyword parameters, its input checks and the chunk sizes every step shares."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.errors import InputError
from app.core.parameters import ParamSpec, validate_parameters

__all__ = [
    "DEFAULT_PARAMETERS",
    "PARAMETER_SPECS",
    "as_origin",
    "as_origins",
    "as_station_index",
    "resolve_parameters",
]

DEFAULT_PARAMETERS: dict[str, Any] = {
    "n_neighbors": 10,
    "threshold_factor": 3.5,
    "support_factor": None,
    "cluster_factor": 2.5,
    "coverage_factor": 10.0,
    "visibility_margin_factor": 1.0,
    "visibility_angle_factor": 2.5,
    "visibility_beyond_fraction": 0.5,
    "visibility_miss_factor": 4.0,
    "origin_free_test": "auto",
    "min_change_distance": 0.10,
}
"""Keyword parameters of :func:`~app.core.localise.changes.localise_changes` and their defaults.

n_neighbors
    Neighbours (besides the point) of the local plane fit, spacing and noise estimate.  10
    spans two rings of a lidar whose rings are twice as far apart as its columns; line-shaped
    neighbourhoods are refitted with 3x more anyway.
threshold_factor
    ``tau`` in standard deviations of the combined noise (3.5: ~1 in 2000 two-sided under
    Gaussian noise; the minimum over neighbouring discs makes false candidates rarer still).
support_factor
    Support radius in the other cloud's local spacings; None calibrates it (3.5 x the lower
    quartile of nearest-neighbour distances in local spacings, clipped to [0.5, 2]).
cluster_factor
    Changed points closer than this many local spacings belong to one region.
coverage_factor
    Without the other sensor's origin: a candidate farther than this many of the other
    cloud's local spacings from it is unobserved.  Without a viewpoint a removed object and
    a hole in the other cloud's coverage look alike: larger values find more of large changes
    and flag more rims of holes (shadows).  Single-viewpoint scans should pass origins.
visibility_margin_factor
    Scales the range margin that makes a return "clearly" before or beyond a candidate:
    ``sqrt((t_own / cos(incidence))^2 + t_other^2)`` with ``t = threshold_factor * sigma``.
visibility_angle_factor
    Returns within this many typical angular steps of the candidate's direction are the
    other sensor's view of it (at most 8 returns are used).
visibility_beyond_fraction
    Fraction of the rays crossing the candidate's surface near it that must pass beyond it.
visibility_miss_factor
    "Near": within ``max(miss_factor * own spacing, candidate's distance)`` of the candidate.
origin_free_test
    Without the other sensor's origins: ``"coverage"`` (the coverage test alone) or
    ``"gaps"`` (a candidate lying on the other cloud's surface between its samples, like a
    floor seen only at grazing angles, is unchanged; then the coverage test:
    :mod:`~app.core.localise.gaps`).  ``"gaps"`` is opt-in: it removes false changes in the
    blind discs of merged surveys but also parts of true changes on the paper's corridor.
    ``"surfaces"``: gaps, shadows and changes told apart from both clouds' surfaces alone,
    with neighbourhoods that grow from the local gap (:mod:`~app.core.localise.origin_free`);
    the fallback for merged lidar surveys whose stations are not known nor recovered until
    issue 29.  ``"auto"`` (default), ``"maps"``: fused maps (handheld RGB-D, mobile laser
    scanning, voxel-filtered robot maps, merged surveys whose stations are unknown) whose
    candidates are judged a cluster at a time from the surfaces both epochs share
    (:mod:`~app.core.localise.map_evidence`: a patch of a surface that continues unmoved in
    the other epoch is a coverage difference, an object whose place the other epoch covered
    is a change).  On robot maps swept along a path it finds what ``"surfaces"`` misses (IoU
    0.86-1.0 against 0-0.90, bench.moving_maps); on merged surveys both keep unchanged scenes
    quiet.  A value set explicitly is used whatever the clouds.
min_change_distance
    Smallest change reported (metres): a point is changed only when it lies farther than
    ``max(tau, min_change_distance)`` from the other cloud's surface.  0.10: the issue-15
    definition of a change ("more than 10 cm from every surface of the other epoch's world"),
    which keeps the band where a removed or added object met the floor (its lowest few
    centimetres, within 10 cm of the floor left) unchanged; 0 reports every change the noise
    lets through (``tau`` alone, ~2-4 cm on 1 cm range noise).  It is also the tolerance along
    the normal of a point near a surface sampled sparsely (a floor at grazing angles, whose
    support radius reaches tens of centimetres): farther off its plane, the point is not on
    it.
"""

PARAMETER_SPECS: dict[str, ParamSpec] = {
    "n_neighbors": ParamSpec("positive_int", low=3),
    "threshold_factor": ParamSpec("positive"),
    "support_factor": ParamSpec("positive", optional=True),
    "cluster_factor": ParamSpec("positive"),
    "coverage_factor": ParamSpec("positive"),
    "visibility_margin_factor": ParamSpec("positive"),
    "visibility_angle_factor": ParamSpec("positive"),
    "visibility_beyond_fraction": ParamSpec("positive", high=1.0),
    "visibility_miss_factor": ParamSpec("positive"),
    "origin_free_test": ParamSpec(
        "choice", choices=("auto", "maps", "gaps", "coverage", "surfaces")
    ),
    "min_change_distance": ParamSpec("float", low=0.0),
}
"""How each of :data:`DEFAULT_PARAMETERS` is validated (same names, same order)."""

# The chunk sizes keep each step's temporaries under 1 MiB, the mmap threshold that
# app.kit.allocator fixes for the CLI and the workers: a larger block is a fresh mapping whose
# pages fault (and are zeroed) on first touch, every chunk again, while a smaller one reuses
# the heap's pages and stays in cache.  Each point's result is the same whatever the chunk.
CHUNK = 8_192
"""Points per step of per-point array work (plane fits, spacing, distances, ray directions):
a (chunk, k + 1) float64 gather of the k = 11 neighbours is 0.75 MiB."""
QUERY_CHUNK = 8_192
"""Points per k-nearest-neighbour query (and per check of a search's cancellation): the
(chunk, k + 1) distances of k = 11 are 0.75 MiB."""
GATHER_CHUNK = 2_048
"""Points per step of (chunk, neighbours, 3) gathers: 0.52 MiB per float64 temporary of the
k + 1 = 11 neighbours."""


def resolve_parameters(params: dict[str, Any]) -> dict[str, Any]:
    """Defaults merged with ``params``, validated; raises InputError naming the bad one.

    Parameters
    ----------
    params : dict
        Keyword parameters, a subset of :data:`DEFAULT_PARAMETERS`.

    Returns
    -------
    dict
        Every parameter: ``n_neighbors`` an int, ``support_factor`` a float or None, the
        others floats.
    """
    return validate_parameters(
        PARAMETER_SPECS, params, stage="localisation", defaults=DEFAULT_PARAMETERS
    )


def as_origin(origin: NDArray | None, name: str) -> NDArray[np.float64] | None:
    """A sensor origin as a float64 array of shape (3,), or None when not given.

    Raises
    ------
    InputError
        Not three finite numbers.
    """
    if origin is None:
        return None
    array = np.asarray(origin, dtype=np.float64).reshape(-1)
    if array.shape != (3,) or not np.isfinite(array).all():
        raise InputError(f"{name} must be 3 finite numbers, got {np.asarray(origin).tolist()}")
    return array


def as_origins(origins: NDArray | None, name: str) -> NDArray[np.float64] | None:
    """Sensor origins (one station or several) as a float64 array of shape (k, 3), or None.

    Parameters
    ----------
    origins : array_like, shape (3,) or (k, 3), or None
        One origin, or one per station of the cloud.
    name : str
        Named in the error message.

    Raises
    ------
    InputError
        Not three finite numbers, nor a non-empty list of them.
    """
    if origins is None:
        return None
    try:
        array = np.asarray(origins, dtype=np.float64)
    except (TypeError, ValueError):
        array = None
    if array is not None and array.shape == (3,):
        array = array[None, :]
    if array is None or array.ndim != 2 or array.shape[0] < 1 or array.shape[1] != 3:
        raise InputError(
            f"{name} must be 3 finite numbers (x, y, z) or a list of them, one per station, "
            f"got {_shown(origins)}"
        )
    if not np.isfinite(array).all():
        bad = int(np.flatnonzero(~np.isfinite(array).all(axis=1))[0])
        raise InputError(
            f"{name}: station {bad}'s origin must be 3 finite numbers, got {array[bad].tolist()}"
        )
    return np.ascontiguousarray(array)


def as_station_index(
    station: NDArray | None, n_points: int, n_stations: int | None, name: str
) -> NDArray[np.int64] | None:
    """A per-point station index as int64 of shape (n,), checked against the origins.

    Parameters
    ----------
    station : array_like, shape (n,), or None
        Index into the cloud's origins of the station that took each point.
    n_points : int
        The cloud's number of points.
    n_stations : int or None
        Number of origins given for the cloud (None: no origins, the index cannot be used).
    name : str

    Raises
    ------
    InputError
        Not integers, not one per point, out of range, or given without origins.
    """
    if station is None:
        return None
    array = np.asarray(station)
    if array.ndim != 1 or array.shape[0] != n_points:
        raise InputError(
            f"{name} must have one station index per point ({n_points}), got shape {array.shape}"
        )
    if array.dtype.kind == "f":
        if not np.isfinite(array).all() or (array != np.round(array)).any():
            raise InputError(f"{name} must hold whole numbers (station indices)")
    elif array.dtype.kind not in "iub":
        raise InputError(f"{name} must hold integer station indices, got {array.dtype}")
    array = array.astype(np.int64)
    if n_stations is None:
        raise InputError(f"{name} needs the stations' origins: give one origin per station")
    if n_points and (array.min() < 0 or array.max() >= n_stations):
        raise InputError(
            f"{name} must lie in 0..{n_stations - 1} (one per given origin), got values from "
            f"{int(array.min())} to {int(array.max())}"
        )
    return array


def _shown(value: object, limit: int = 120) -> str:
    """``value`` for an error message, cut to ``limit`` characters."""
    try:
        text = repr(np.asarray(value).tolist())
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."

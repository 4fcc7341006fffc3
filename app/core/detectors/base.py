"""What every change detector shares: parameters, input checks, sub-sampling and the decision.

A detector turns two point clouds into one number, ``d(reference, scan)`` (the paper's
``d(S, T)``), and decides ``changed`` by comparing it with a threshold calibrated on the
clouds' own resampling noise (:mod:`app.core.detectors.calibration`).

Subclasses provide three things:

* :meth:`ChangeDetector._context`: whatever both clouds must share and is derived from the
  reference (a scale, an orientation origin, a fitted reference model ...);
* :meth:`ChangeDetector._score`: the distance between two *working* point sets given that
  context (once for the real pair, and again for every resampled pair during calibration);
* class attributes ``_variant_defaults`` (the method's own hyper-parameters per variant).

The base class does the rest: parameter validation and ``get_params``, input validation,
reducing big clouds to at most ``max_points`` working points (on a common voxel grid for the
improved variants, so the descriptor reflects geometry rather than sensor density), seeding
every random choice from ``random_state``, and calibration.
"""

from __future__ import annotations

import warnings
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from app.core.cloud import as_points, column_extreme
from app.core.detectors import calibration
from app.core.detectors.voxel_grid import (
    auto_voxel_size,
    voxel_representatives,
)
from app.core.errors import InputError
from app.core.parameters import ParamSpec, validate_parameters
from app.core.threads import available_threads, concurrently

VARIANTS = ("improved", "paper")

MIN_WORKING_POINTS = 10
"""Fewest points a cloud may have: below this no descriptor is meaningful."""


@dataclass(frozen=True)
class Detection:
    """The outcome of :meth:`ChangeDetector.detect`.

    Attributes
    ----------
    score : float
        ``d(reference, scan)`` for the detector's method and variant.
    threshold : float
        Calibrated decision threshold (same units as ``score``).
    changed : bool
        ``score > threshold``.
    calibration : dict
        JSON-serialisable account of how ``threshold`` was obtained (scheme, number of
        resamples, null statistics, nominal false-alarm rate, p-value ...).
    """

    score: float
    threshold: float
    changed: bool
    calibration: dict[str, Any]


COMMON_SPECS: dict[str, ParamSpec] = {
    "false_alarm_rate": ParamSpec("float", 1e-6, 0.5),
    "n_resamples": ParamSpec("int", 3, 10_000),
    "calibration": ParamSpec("choice", choices=calibration.SCHEMES),
    "max_points": ParamSpec("int", MIN_WORKING_POINTS, 10_000_000),
    "voxel_size": ParamSpec("voxel"),
}
COMMON_DEFAULTS: dict[str, dict[str, Any]] = {
    "improved": {
        "false_alarm_rate": 0.01,
        "n_resamples": 20,
        "calibration": "auto",
        "max_points": 4000,
        "voxel_size": "auto",
    },
    "paper": {
        "false_alarm_rate": 0.01,
        "n_resamples": 20,
        "calibration": "auto",
        "max_points": 4000,
        "voxel_size": 0.0,
    },
}


def point_keys(points: NDArray[np.float64], seed: int) -> NDArray[np.uint64]:
    """A pseudo-random 64-bit key per point, computed from its coordinates and ``seed``.

    Selections made by key (the smallest keys, or the smallest key per voxel) are uniformly
    random for a given seed, yet depend only on the points themselves: the same cloud, in
    any order, always gives the same working set, so ``d(S, S) = 0`` exactly.

    Parameters
    ----------
    points : ndarray, shape (n, 3), float64
    seed : int

    Returns
    -------
    ndarray, shape (n,), uint64
    """

    bits = np.ascontiguousarray(points, dtype=np.float64).view(np.uint64).reshape(-1, 3)
    start = (seed * 0x9E3779B97F4A7C15 + 1) % 2**64
    keys = np.full(bits.shape[0], np.uint64(start))
    # a block of rows at a time, in place: the (n,) temporaries of each step were fresh
    # mappings whose pages faulted in (~20k at 1M points), in the comparison's serial end
    shifted = np.empty(min(KEY_BLOCK_ROWS, bits.shape[0]), dtype=np.uint64)
    for first in range(0, bits.shape[0], KEY_BLOCK_ROWS):
        block = keys[first : first + KEY_BLOCK_ROWS]
        scratch = shifted[: block.shape[0]]
        for column in range(3):
            block ^= bits[first : first + KEY_BLOCK_ROWS, column]
            _mix_in_place(block, scratch)
    return keys


KEY_BLOCK_ROWS = 1 << 15
"""Rows whose keys :func:`point_keys` mixes at once (0.25 MiB a temporary)."""


def _mix_in_place(values: NDArray[np.uint64], scratch: NDArray[np.uint64]) -> None:
    """splitmix64's finaliser applied to ``values`` in place (``scratch``: same shape)."""
    for shift, factor in ((30, 0xBF58476D1CE4E5B9), (27, 0x94D049BB133111EB), (31, None)):
        np.right_shift(values, np.uint64(shift), out=scratch)
        values ^= scratch
        if factor is not None:
            values *= np.uint64(factor)


def smallest_keys(keys: NDArray[np.uint64], count: int) -> NDArray[np.int64]:
    """Sorted indices of the ``count`` smallest ``keys`` (a random subset of that size)."""
    if count >= keys.size:
        return np.arange(keys.size, dtype=np.int64)
    return np.sort(np.argpartition(keys, count - 1)[:count]).astype(np.int64)


def median_spacing(points: NDArray[np.float64], rng: np.random.Generator) -> float:
    """Median nearest-neighbour distance of ``points`` (n, 3), from up to 1000 query points."""
    queries = points[rng.choice(points.shape[0], min(1000, points.shape[0]), replace=False)]
    from scipy.spatial import cKDTree  # on first use: API processes need no scipy

    distances, _ = cKDTree(points).query(queries, k=2)
    spacing = float(np.median(distances[:, 1]))
    if spacing > 0:
        return spacing
    positive = distances[:, 1][distances[:, 1] > 0]
    return float(positive.min()) if positive.size else 1.0


def _keys_of(
    reference: NDArray[np.float64], scan: NDArray[np.float64], seed: int, *, voxel_size: float
) -> tuple[NDArray[np.uint64] | None, NDArray[np.uint64] | None]:
    """Both clouds' :func:`point_keys` when they will be thinned on a grid (``voxel_size`` >
    0), else (None, None)."""
    if voxel_size <= 0:
        return None, None
    return point_keys(reference, seed), point_keys(scan, seed)


class ChangeDetector(ABC):
    """Base class of the EMD change detectors; see the module docstring.

    Parameters
    ----------
    variant : {"improved", "paper"}
    random_state : int
        Seeds every random choice (sub-sampling, EM initialisation, plane sampling,
        calibration resamples): the same inputs and ``random_state`` give the same result.
    **params
        Hyper-parameters; see ``_variant_defaults`` of each subclass and
        :data:`COMMON_DEFAULTS`. Unknown names raise :class:`InputError`.
    """

    method: ClassVar[str]
    _specs: ClassVar[dict[str, ParamSpec]] = {}
    _ignored_warnings: ClassVar[tuple[type[Warning], ...]] = ()
    """Warnings the method raises by design (e.g. EM stopped after a fixed number of
    iterations), ignored for a whole :meth:`detect` or :meth:`distance` call. They are set once
    in the calling thread (``warnings.catch_warnings`` is not thread-safe)."""
    _variant_defaults: ClassVar[dict[str, dict[str, Any]]] = {}
    _score_draws: ClassVar[bool] = True
    """Whether :meth:`_score` draws from the generator it is given; False lets the
    calibration's resamples be scored on two threads, in any order, to the same values."""

    def __init__(self, variant: str = "improved", *, random_state: int = 0, **params: Any):
        if variant not in VARIANTS:
            raise InputError(f"variant must be one of {list(VARIANTS)}, got {variant!r}")
        if isinstance(random_state, bool) or not isinstance(random_state, int | np.integer):
            raise InputError(f"random_state must be an integer, got {random_state!r}")
        if random_state < 0:
            raise InputError(f"random_state must be >= 0, got {random_state}")
        self.variant = variant
        self.random_state = int(random_state)
        self.params: dict[str, Any] = validate_parameters(
            self.param_specs(variant),
            params,
            owner=f"the {self.method!r} detector (variant {variant!r})",
            defaults={**COMMON_DEFAULTS[variant], **self._variant_defaults[variant]},
            also_valid=("random_state", "variant"),
        )

    @classmethod
    def param_specs(cls, variant: str) -> dict[str, ParamSpec]:
        """The hyper-parameters ``variant`` accepts: the common ones, then the method's own."""
        own = {
            name: cls._specs[name] for name in cls._variant_defaults[variant] if name in cls._specs
        }
        return {**COMMON_SPECS, **own}

    def get_params(self) -> dict[str, Any]:
        """JSON-serialisable parameters; ``make_detector(method, **get_params())`` rebuilds it."""
        return {"variant": self.variant, "random_state": self.random_state, **self.params}

    def __repr__(self) -> str:
        arguments = ", ".join(f"{key}={value!r}" for key, value in self.get_params().items())
        return f"{type(self).__name__}({arguments})"

    # ----------------------------------------------------------------------------------------
    # to be provided by each method

    @abstractmethod
    def _context(
        self,
        reference: NDArray[np.float64],
        scan: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> dict[str, Any]:
        """What both working sets share, derived from the working reference (and scan).

        Computed once per call and reused for every calibration resample.
        """

    @abstractmethod
    def _score(
        self,
        first: NDArray[np.float64],
        second: NDArray[np.float64],
        context: dict[str, Any],
        rng: np.random.Generator,
        is_resample: bool,
    ) -> float:
        """``d(first, second)`` on working sets; ``is_resample`` is True during calibration."""

    # ----------------------------------------------------------------------------------------
    # shared machinery

    def _working_sets(
        self, reference: NDArray[np.float64], scan: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        """Thin both clouds to at most ``max_points`` points each.

        The improved variants first thin both clouds on one common voxel grid (so a scanner
        that saw a wall from close by, with ten times the density, weighs it no more than one
        that saw it from afar): by default (``voxel_size="auto"``, clouds bigger than
        ``max_points``) the grid on which the sparser cloud keeps about ``max_points`` points.
        Then they draw a uniform random subset. Every choice is made by
        :func:`point_keys`, so it depends on the points and ``random_state`` only.

        Returns
        -------
        reference_work : ndarray, shape (n', 3)
        scan_work : ndarray, shape (m', 3)
        info : dict
            ``voxel_size`` used (0 when none) and the working sizes.
        """
        max_points = self.params["max_points"]
        voxel_size = self.params["voxel_size"]
        seed = self.random_state
        # each cloud's steps on a thread of its own (numpy's array loops release the GIL): the
        # detection is the comparison's serial end (~0.2 CPU s of thinning at 1M + 1M)
        threads = available_threads()
        smaller = reference if reference.shape[0] <= scan.shape[0] else scan
        larger_count = max(reference.shape[0], scan.shape[0])
        thinned = voxel_size == "auto" and (
            larger_count > max_points and smaller.shape[0] > MIN_WORKING_POINTS
        )
        if voxel_size == "auto":
            # The grid at which the sparser cloud keeps ~max_points voxels (or ~half of its
            # points when it is smaller than that): both clouds then sample every surface at
            # about the same spacing.  The keys do not depend on it: found meanwhile.
            target = max(MIN_WORKING_POINTS, min(max_points, smaller.shape[0] // 2))
            voxel_size, keys = concurrently(
                threads,
                lambda: auto_voxel_size(smaller, target, threads) if thinned else 0.0,
                lambda: _keys_of(reference, scan, seed, voxel_size=float(thinned)),
            )
        else:
            keys = _keys_of(reference, scan, seed, voxel_size=voxel_size)
        origin = np.minimum(column_extreme(reference, np.minimum), column_extreme(scan, np.minimum))

        def working_set(cloud: NDArray[np.float64], cloud_keys: NDArray | None) -> NDArray:
            if voxel_size > 0:
                cloud = cloud[voxel_representatives(cloud, voxel_size, origin, cloud_keys)]
            kept_keys = point_keys(cloud, seed)
            kept = smallest_keys(kept_keys, max_points)
            # Canonical order (by key): the same points in any order give the same working set.
            return cloud[kept[np.argsort(kept_keys[kept], kind="stable")]]

        sets = concurrently(
            threads, lambda: working_set(reference, keys[0]), lambda: working_set(scan, keys[1])
        )
        info: dict[str, Any] = {
            "voxel_size": float(voxel_size),
            "grid_origin": origin.tolist() if voxel_size > 0 else None,
            "n_reference_working": int(sets[0].shape[0]),
            "n_scan_working": int(sets[1].shape[0]),
        }
        return sets[0], sets[1], info

    @contextmanager
    def _numerics(self) -> Iterator[None]:
        """One BLAS/OpenMP thread and :attr:`_ignored_warnings` ignored, for one call."""
        # read first: a detector's libraries, imported on first use, load before the limit
        # is set, so that it applies to their thread pools too
        ignored = self._ignored_warnings
        with threadpool_limits(limits=1), warnings.catch_warnings():
            for category in ignored:
                warnings.simplefilter("ignore", category)
            yield

    def _rngs(self) -> tuple[np.random.Generator, np.random.Generator]:
        """Independent generators for scoring and calibration."""
        seeds = np.random.SeedSequence(self.random_state).spawn(2)
        return np.random.default_rng(seeds[0]), np.random.default_rng(seeds[1])

    def _prepare(
        self, reference: NDArray, scan: NDArray
    ) -> tuple[
        NDArray[np.float64],
        NDArray[np.float64],
        dict[str, Any],
        dict[str, Any],
        np.random.Generator,
        np.random.Generator,
    ]:
        reference = as_points(reference, "reference")
        scan = as_points(scan, "scan")
        score_rng, calibration_rng = self._rngs()
        reference_work, scan_work, info = self._working_sets(reference, scan)
        context = self._context(reference_work, scan_work, score_rng)
        return reference_work, scan_work, context, info, score_rng, calibration_rng

    def distance(self, reference: NDArray, scan: NDArray) -> float:
        """``d(reference, scan)`` for this method and variant.

        Parameters
        ----------
        reference : array_like, shape (n, 3)
            Reference cloud, local coordinates.
        scan : array_like, shape (m, 3)
            Later scan of the same place, same frame.

        Returns
        -------
        float
            Non-negative distance; 0 for identical clouds (up to EM / sampling noise).
        """
        with self._numerics():
            reference_work, scan_work, context, _, score_rng, _ = self._prepare(reference, scan)
            return float(self._score(reference_work, scan_work, context, score_rng, False))

    def detect(self, reference: NDArray, scan: NDArray) -> Detection:
        """Distance plus a threshold calibrated on the clouds' own resampling noise.

        Parameters
        ----------
        reference : array_like, shape (n, 3)
        scan : array_like, shape (m, 3)

        Returns
        -------
        Detection

        Notes
        -----
        BLAS and OpenMP run on one thread inside (small matrices, where more threads only
        contend; scikit-learn's k-means, which the detectors used before
        :mod:`app.core.detectors.kmeans`, took up to 0.4 s instead of 3 ms with two OpenMP
        threads on a busy machine).
        """
        with self._numerics():
            return self._detect(reference, scan)

    def _detect(self, reference: NDArray, scan: NDArray) -> Detection:
        reference_work, scan_work, context, info, score_rng, calibration_rng = self._prepare(
            reference, scan
        )
        score = float(self._score(reference_work, scan_work, context, score_rng, False))

        def resample_score(first: NDArray[np.float64], second: NDArray[np.float64]) -> float:
            if min(first.shape[0], second.shape[0]) < MIN_WORKING_POINTS:
                return float("nan")
            return float(self._score(first, second, context, calibration_rng, True))

        scheme = self.params["calibration"]
        if scheme == "auto":
            scheme = "paired" if info["voxel_size"] > 0 else "permutation"
        pairing_voxel = 0.0
        if scheme == "paired":
            pairing_voxel = info["voxel_size"] or median_spacing(reference_work, calibration_rng)
        null = calibration.null_distribution(
            reference_work,
            scan_work,
            resample_score,
            scheme=scheme,
            n_resamples=self.params["n_resamples"],
            rng=calibration_rng,
            pairing_voxel=pairing_voxel,
            pairing_origin=None if info["grid_origin"] is None else np.array(info["grid_origin"]),
            threads=1 if self._score_draws else available_threads(),
        )
        n_failed = int(np.sum(~np.isfinite(null)))
        if null.size - n_failed < 2:
            raise InputError(
                f"cannot calibrate the {self.method}/{self.variant} detector: it failed on "
                f"{n_failed} of {null.size} resampled pairs"
            )
        decision = calibration.threshold_from_null(null, self.params["false_alarm_rate"])
        report = {
            **decision.report(score),
            "calibration": scheme,
            "pairing_voxel": pairing_voxel if scheme == "paired" else None,
            "n_failed_resamples": n_failed,
            **info,
            "method": self.method,
            "variant": self.variant,
        }
        return Detection(
            score=score,
            threshold=decision.threshold,
            changed=bool(score > decision.threshold),
            calibration=report,
        )

"""Decision thresholds from the clouds' own resampling noise.

A global distance is only useful with a threshold that says how large it gets when *nothing*
changed. That depends on the scene, the sensor noise, the number of points and the detector,
so no constant works across sites. We estimate it from the two clouds themselves:

``auto`` (default)
    ``paired`` when the detector thinned both clouds on a common voxel grid (big clouds),
    ``permutation`` otherwise (clouds small enough to be used whole).
``paired``
    A permutation test stratified by a voxel grid (the working grid when the clouds were
    thinned on one, else the reference's median nearest-neighbour spacing). In a voxel that
    both clouds reach, the reference's and the scan's points are dealt out again at random
    (keeping each cloud's count in that voxel); points in voxels only one cloud reaches go to
    either resampled set with probability 1/2. Under "no change" points of one voxel are
    exchangeable, so the resampled pairs differ by what two samplings of the same surfaces
    differ by (noise and sub-voxel sampling); a changed region (voxels only one cloud
    reaches) is split evenly and cancels. Unlike a plain permutation it keeps the spatial
    layout of both clouds: thinned clouds are one point per voxel, and a plain permutation
    then opens holes and doubles points that neither real cloud has, inflating the null
    (figures in docs/performance.md and bench/results/paper.md). On clouds
    that were *not* thinned (several points of each cloud per voxel) it conditions on each
    voxel's counts and comes out too small for independent samplings (a false alarm on a
    1200-point rescan in the tests), hence ``auto``.
``permutation``
    Pool the reference and scan working sets, shuffle, split back into sets of the original
    sizes ``n`` and ``m`` and compute the detector's distance between them, ``n_resamples``
    times. If the two clouds are independent samples of one unchanged surface (the null
    hypothesis), the observed pair is just one more such split, so these distances follow the
    null distribution exactly, sizes included (a two-sample permutation test). A real change
    is diluted over both resampled sets, so it does not inflate the null.
``split_half``
    Split each cloud into random halves and compute the distance between the halves; the
    halves have half the points, so each value is rescaled by
    ``sqrt((1/n + 1/m) / (1/n_1 + 1/n_2))`` (distances between descriptor estimates grow like
    their sampling standard error). Never mixes the clouds, but relies on that scaling law.

All three treat the pair as two independent samplings of the same surfaces. The paper's
corridor is not that: its reference and scan are the *same* 300 points with independent
noise, so every scheme is conservative there (false alarms well below the nominal rate,
less power); see bench/results/paper.md.

The threshold is an upper prediction bound for one more null value: with ``L`` the logs of the
null distances (their distribution is skewed and positive; logs make it close to normal),
``threshold = exp(mean(L) + t_{R-1, 1-alpha} * std(L) * sqrt(1 + 1/R))`` for ``R`` resamples
and nominal false-alarm rate ``alpha`` (Student-t because mean and std are estimated from
``R`` values). The null's right tail is heavy: on the corridor this rule keeps false alarms
near the nominal rate where normal and gamma fits exceed it (figures in docs/detectors.md).
``calibration`` in the result reports all of it,
including the permutation p-value ``(1 + #{null >= score}) / (R + 1)``.

What it does *not* capture: noise that is not sampling noise (registration residuals,
different viewpoints and occlusions, moving people). Those are handled upstream (registration,
mutually-observed points) or by raising ``false_alarm_rate``'s strictness; see
docs/detectors.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import column_extreme
from app.core.threads import for_each_chunk

SCHEMES = ("auto", "paired", "permutation", "split_half")

PairScore = Callable[[NDArray[np.float64], NDArray[np.float64]], float]


def null_distribution(
    reference: NDArray[np.float64],
    scan: NDArray[np.float64],
    score: PairScore,
    *,
    scheme: str,
    n_resamples: int,
    rng: np.random.Generator,
    pairing_voxel: float = 0.0,
    pairing_origin: NDArray[np.float64] | None = None,
    threads: int = 1,
) -> NDArray[np.float64]:
    """Distances between resampled sets that share no change, scaled to the pair's sizes.

    Parameters
    ----------
    reference : ndarray, shape (n, 3)
    scan : ndarray, shape (m, 3)
    score : callable
        ``score(first, second) -> float``, the detector's distance on working sets.
    scheme : {"paired", "permutation", "split_half"}
        Already resolved (not ``auto``).
    n_resamples : int
        Number of null distances to compute (``split_half`` alternates between the clouds).
    rng : numpy.random.Generator
    pairing_voxel : float
        Edge of the voxels whose points ``paired`` exchanges (> 0 for that scheme).
    pairing_origin : ndarray, shape (3,), optional
        Corner of that grid: the thinning grid's, so each voxel holds at most one point of
        each cloud (default: the pooled minimum).
    threads : int
        From 2, the ``paired`` and ``permutation`` resamples are drawn on the calling thread
        (``rng`` in the same order) and scored on that many threads meanwhile: only for a
        ``score`` that draws nothing from ``rng`` itself, so the values are the same as on
        one thread.

    Returns
    -------
    ndarray, shape (n_resamples,)
    """
    n_reference, n_scan = reference.shape[0], scan.shape[0]
    values = np.empty(n_resamples)
    if scheme == "paired":
        if pairing_voxel <= 0:
            raise ValueError("the paired scheme needs pairing_voxel > 0")
        pooled = np.concatenate([reference, scan])
        resampler = VoxelPairing(reference, scan, pairing_voxel, pairing_origin)
        drawn = (resampler.draw(rng) for _ in range(n_resamples))
        _score_drawn(values, score, ((pooled[to], pooled[~to]) for to in drawn), threads)
    elif scheme == "permutation":
        pooled = np.concatenate([reference, scan])
        orders = (rng.permutation(pooled.shape[0]) for _ in range(n_resamples))
        pairs = ((pooled[order[:n_reference]], pooled[order[n_reference:]]) for order in orders)
        _score_drawn(values, score, pairs, threads)
    elif scheme == "split_half":
        target_variance = 1.0 / n_reference + 1.0 / n_scan
        for index in range(n_resamples):
            cloud = reference if index % 2 == 0 else scan
            order = rng.permutation(cloud.shape[0])
            half = cloud.shape[0] // 2
            first, second = cloud[order[:half]], cloud[order[half:]]
            scale = math.sqrt(target_variance / (1.0 / first.shape[0] + 1.0 / second.shape[0]))
            values[index] = scale * score(first, second)
    else:
        raise ValueError(f"unknown calibration scheme {scheme!r}; valid: {list(SCHEMES)}")
    return values


def _score_drawn(
    values: NDArray[np.float64],
    score: PairScore,
    pairs: Iterator[tuple[NDArray[np.float64], NDArray[np.float64]]],
    threads: int,
) -> None:
    """``values[i] = score(*pair)`` for the ``i``-th resampled pair.  On one thread each pair
    is drawn, then scored, in turn; from 2 ``threads`` each is drawn on the calling thread (in
    the generator's order) while those drawn before it are scored, each score written to its
    own entry."""

    def score_one(numbered: tuple[int, tuple[NDArray, NDArray]]) -> None:
        index, pair = numbered
        values[index] = score(*pair)

    for_each_chunk(score_one, enumerate(pairs), threads)


class VoxelPairing:
    """Exchanges of reference and scan points that share a voxel (the ``paired`` scheme).

    Parameters
    ----------
    reference : ndarray, shape (n, 3)
    scan : ndarray, shape (m, 3)
    voxel_size : float
        Edge of the cubic cells of one grid shared by both clouds.
    origin : ndarray, shape (3,), optional
        A corner of the grid (default: the pooled minimum).

    Notes
    -----
    A voxel holding ``a`` reference and ``b`` scan points (both > 0) is a stratum: each draw
    deals its ``a + b`` points at random, ``a`` to the first set and ``b`` to the second.
    Points in voxels only one cloud reaches go to either set with probability 1/2 each, so a
    changed region (scan-only or reference-only voxels) is split evenly between the two
    resampled sets and cancels instead of entering the null.
    """

    def __init__(
        self,
        reference: NDArray[np.float64],
        scan: NDArray[np.float64],
        voxel_size: float,
        origin: NDArray[np.float64] | None = None,
    ):
        pooled = np.concatenate([reference, scan])
        corner = (
            column_extreme(pooled, np.minimum)
            if origin is None
            else np.asarray(origin, dtype=np.float64)
        )
        cells = np.floor((pooled - corner) / voxel_size).astype(np.int64)
        cells -= column_extreme(cells, np.minimum)
        extent = column_extreme(cells, np.maximum) + 1
        keys = (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]
        _, voxel = np.unique(keys, return_inverse=True)
        from_reference = np.arange(pooled.shape[0]) < reference.shape[0]
        reference_count = np.bincount(voxel[from_reference], minlength=voxel.max() + 1)
        scan_count = np.bincount(voxel[~from_reference], minlength=voxel.max() + 1)
        shared = (reference_count > 0) & (scan_count > 0)
        self.paired = np.flatnonzero(shared[voxel])
        self.unpaired = np.flatnonzero(~shared[voxel])
        self.voxel = voxel[self.paired]
        order = np.argsort(self.voxel, kind="stable")
        self.voxel_start = np.searchsorted(self.voxel[order], self.voxel)
        self.quota = reference_count[self.voxel]
        self.size = pooled.shape[0]

    @property
    def paired_fraction(self) -> float:
        """Fraction of all points in voxels both clouds reach."""
        return self.paired.size / self.size

    def draw(self, rng: np.random.Generator) -> NDArray[np.bool_]:
        """One exchange: True for the points of the pooled set that go to the first set."""
        to_first = np.zeros(self.size, dtype=bool)
        order = np.lexsort((rng.random(self.paired.size), self.voxel))
        rank = np.empty(self.paired.size, dtype=np.int64)
        rank[order] = np.arange(self.paired.size)
        rank -= self.voxel_start
        to_first[self.paired] = rank < self.quota
        to_first[self.unpaired] = rng.random(self.unpaired.size) < 0.5
        return to_first


@dataclass(frozen=True)
class NullDecision:
    """A threshold and the null statistics it came from."""

    threshold: float
    false_alarm_rate: float
    null: NDArray[np.float64]
    log_mean: float
    log_std: float
    t_quantile: float
    zero_fraction: float = 0.0

    def report(self, score: float) -> dict[str, Any]:
        """JSON-serialisable summary (goes into :attr:`Detection.calibration`)."""
        n_resamples = int(self.null.size)
        exceed = int(np.sum(self.null >= score))
        return {
            "rule": "log-normal upper prediction bound (Student-t)",
            "false_alarm_rate": self.false_alarm_rate,
            "n_resamples": n_resamples,
            "null_mean": float(self.null.mean()),
            "null_std": float(self.null.std(ddof=1)) if n_resamples > 1 else 0.0,
            "null_max": float(self.null.max()),
            "null_log_mean": self.log_mean,
            "null_log_std": self.log_std,
            "t_quantile": self.t_quantile,
            "null_values": [float(value) for value in self.null],
            "p_value": (1 + exceed) / (n_resamples + 1),
            "null_zero_fraction": self.zero_fraction,
        }


def threshold_from_null(null: NDArray[np.float64], false_alarm_rate: float) -> NullDecision:
    """Upper ``1 - false_alarm_rate`` prediction bound of a log-normal fitted to ``null``.

    Null distances that are exactly zero (a descriptor that came out identical, e.g. the
    same planes) are a point mass the log-normal cannot hold: with a fraction ``pi_0`` of
    zeros, the bound is taken at level ``1 - false_alarm_rate / (1 - pi_0)`` of the positive
    values (zero-inflated log-normal).

    Parameters
    ----------
    null : ndarray, shape (R,)
        Null distances, non-negative; NaN entries (resamples the descriptor failed on) are
        dropped, at least 2 must remain.
    false_alarm_rate : float
        Nominal probability that an unchanged pair exceeds the threshold.

    Returns
    -------
    NullDecision
    """
    null = np.asarray(null, dtype=np.float64)
    null = null[np.isfinite(null)]  # a resample the descriptor could not describe
    if null.size < 2:
        raise ValueError("need at least 2 finite null distances")
    scale = float(null.max())
    positive = null[null > 1e-12 * scale] if scale > 0 else null[:0]
    if positive.size < 2:
        # (Almost) always identical descriptors: any distance above the largest null is change.
        return NullDecision(scale, false_alarm_rate, null, -math.inf, 0.0, math.inf, 1.0)
    zero_fraction = 1.0 - positive.size / null.size
    level = 1.0 - false_alarm_rate / (1.0 - zero_fraction)
    if level <= 0.0:
        return NullDecision(0.0, false_alarm_rate, null, -math.inf, 0.0, 0.0, zero_fraction)
    logs = np.log(positive)
    log_mean = float(logs.mean())
    log_std = float(logs.std(ddof=1))
    # Student's t quantile: scipy.stats.t.ppf's own function, without scipy.stats' ~0.3 s import
    from scipy import special  # on first use: API processes need no scipy

    t_quantile = float(special.stdtrit(positive.size - 1, level))
    inflation = math.sqrt(1.0 + 1.0 / positive.size)
    threshold = math.exp(log_mean + t_quantile * log_std * inflation)
    return NullDecision(
        threshold, false_alarm_rate, null, log_mean, log_std, t_quantile, zero_fraction
    )

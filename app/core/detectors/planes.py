"""PE-EMD: compare the planes extracted from two clouds (paper section III-C, eq. (5)).

The paper's randomised *fuzzy plane* extraction, steps 0-9:

1. ``L`` is an empty list of candidate planes with weights.
2. Draw 3 random non-collinear points ``P1, P2, P3``.
3. ``pi = (a, b, c, d)`` with ``a x + b y + c z = d`` through them, ``(a, b, c)`` unit.
4. Candidates ``rho`` in ``L`` close to ``pi``: ``|v_pi - v_rho| < epsilon`` and the distances of
   ``P1, P2, P3`` to ``rho`` all below ``delta``.
5-6. If none, add ``pi`` with weight 1; otherwise replace them all by their weighted average
   (``pi`` with weight 1), weight = sum of weights. (We renormalise the averaged ``(a, b, c)``
   to unit length.)
7. Repeat 2-6 ``N`` times.
8. If the largest weight in ``L`` is below ``m``, stop. Otherwise remove the points within
   ``eta`` of the heaviest plane(s) and record each plane with its number of such points.
9. Repeat 1-8 on the remaining points; stop when fewer than ``p`` remain.

Each cloud becomes planes ``(a, b, c, d)`` in R^4 weighted by inlier counts; eq. (1) with
Euclidean ground distance in R^4 gives ``d_PE``.

``paper``: exactly that, with fixed thresholds ``epsilon = 0.1``, ``delta = eta = 0.1``
(scene units, metres; the paper gives no values), ``N = 500``, ``m = 5``, ``p = 15``; the
normal's sign is whatever the cross product of the random triple gives. When a cloud yields
no plane (noise sigma >~ eta), eq. (1) is undefined and :class:`ExtractionError` is raised.

``improved``:

* **orientation**: ``(n, d)`` and ``(-n, -d)`` are the same plane but 2 apart in R^4. Every
  candidate is written in Hesse normal form relative to the reference's centroid ``o``
  (``n . (x - o) = d`` with ``d >= 0``), for both clouds, so step 6 averages like with like
  and equal planes get equal parameters.
* **thresholds from the data**: the noise ``sigma`` is estimated from local plane fits
  (median smallest eigenvalue of 12-neighbour covariances) and the spacing ``s`` from
  nearest-neighbour distances of the reference; ``eta = delta = max(2.5 sigma, 0.25 s)``,
  ``epsilon = clip(5 sigma / r, 0.05, 0.5)`` with ``r`` the RMS radius (the normal error of
  a triple with baseline ``~r``), ``p = max(15, 2% of the points)``.
* **voting and refinement**: steps 4-7 become one vectorised vote (each candidate's weight
  is the number of candidates it would absorb under the tests of step 4, so the result no
  longer depends on the order of the triples, and it is one matrix operation instead of a
  Python loop per triple); the 10 best-supported candidates (support >= ``m`` = 3) are
  refitted by least squares to their ``eta``-inliers (3 times) and the one with most
  inliers is extracted (RANSAC's criterion: the best-supported candidate alone is often a
  diagonal through two noisy walls). Its parameters then average all its points instead of
  ~N/9 random triples; planes with fewer than ``p`` inliers are not extracted, and a round
  without an acceptable plane is retried with fresh triples (3 failed rounds stop the
  extraction). ``N = 300``.
  At the end every point is counted for its *nearest* extracted plane (within ``eta``): the
  greedy removal of step 8 hands the points near an intersection to whichever plane
  happened to come first.
* **ground distance**: Euclidean in R^4 on ``(n, d / r)``, the offset in units of the
  reference's RMS radius ``r``, so distances (and ``unexplained_cost``) are scale-free.
* **weights**: inlier *fractions* of each cloud (a denser scan does not weigh more), plus the
  fraction of points explained by no plane as one more mass, at ground distance
  ``unexplained_cost`` from every plane; both sides then carry mass 1, so points that leave a
  plane for an object too small to become a plane still count.
"""

from __future__ import annotations

import hashlib
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from app.core.detectors.base import ChangeDetector
from app.core.detectors.plane_extraction import PlaneSettings, extract_fuzzy_planes
from app.core.emd import earth_movers_distance, euclidean_ground_distances
from app.core.errors import InputError
from app.core.parameters import ParamSpec


class ExtractionError(InputError):
    """The paper variant found no plane in one of the clouds, so eq. (1) is undefined."""


def estimate_noise_and_spacing(
    points: NDArray[np.float64], rng: np.random.Generator, n_neighbours: int = 12
) -> tuple[float, float]:
    """Surface noise and point spacing from local plane fits.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    rng : numpy.random.Generator
        Picks up to 500 query points.
    n_neighbours : int

    Returns
    -------
    noise_std : float
        ``sqrt(median smallest eigenvalue of the neighbourhood covariance * (k-1)/(k-3))``:
        the residual standard deviation of a local plane fit (corrected for the 3 fitted
        degrees of freedom); the median ignores edges and corners.
    spacing : float
        Median distance to the nearest neighbour.
    """
    n_points = points.shape[0]
    neighbours = min(n_neighbours, n_points)
    queries = points[rng.choice(n_points, min(500, n_points), replace=False)]
    from scipy.spatial import cKDTree  # on first use: API processes need no scipy

    tree = cKDTree(points)
    distances, indices = tree.query(queries, k=neighbours)
    spacing = float(np.median(distances[:, 1])) if neighbours > 1 else 0.0
    patches = points[indices]  # (q, k, 3)
    centred = patches - patches.mean(axis=1, keepdims=True)
    covariances = np.einsum("qki,qkj->qij", centred, centred) / max(neighbours - 1, 1)
    smallest = np.linalg.eigvalsh(covariances)[:, 0]
    correction = (neighbours - 1) / max(neighbours - 3, 1)
    noise_std = float(np.sqrt(max(np.median(smallest), 0.0) * correction))
    return noise_std, spacing


class PlanesDetector(ChangeDetector):
    """PE-EMD change detector; see the module docstring for the two variants.

    Parameters
    ----------
    variant : {"improved", "paper"}
    random_state : int
    n_iterations : int
        ``N``, random triples per round (paper 500: with 200, the paper's merge stopped before
        the first plane on half of the corridor pairs at variance 1e-3; improved 300).
    min_weight : int
        ``m``: paper 5 (triples merged into the heaviest candidate); improved 3 (votes).
    normal_tolerance, merge_distance, inlier_distance : float
        Paper only: ``epsilon`` (0.1), ``delta`` and ``eta`` (0.1, scene units).
    min_points : int
        Paper only: ``p`` (15). Improved: ``max(15, min_point_fraction * n)``.
    min_point_fraction : float
        Improved only (0.02).
    noise_multiplier : float
        Improved only: ``eta = delta = max(noise_multiplier * sigma, 0.25 * spacing)`` (2.5).
    unexplained_cost : float
        Improved only: ground distance between the "no plane" mass and any plane (1.0).
    **params
        The common ones; see :mod:`app.core.detectors.base`.
    """

    method: ClassVar[str] = "planes"
    _specs: ClassVar[dict[str, ParamSpec]] = {
        "n_iterations": ParamSpec("int", 3, 100_000),
        "min_weight": ParamSpec("int", 1, 100_000),
        "normal_tolerance": ParamSpec("float", 0.0, 2.0),
        "merge_distance": ParamSpec("float", 0.0, None),
        "inlier_distance": ParamSpec("float", 0.0, None),
        "min_points": ParamSpec("int", 3, 10_000_000),
        "min_point_fraction": ParamSpec("float", 0.0, 1.0),
        "noise_multiplier": ParamSpec("float", 0.0, 100.0),
        "unexplained_cost": ParamSpec("float", 0.0, 100.0),
    }
    _variant_defaults: ClassVar[dict[str, dict[str, Any]]] = {
        "improved": {
            "n_iterations": 300,
            "min_weight": 3,
            "min_point_fraction": 0.02,
            "noise_multiplier": 2.5,
            "unexplained_cost": 1.0,
        },
        # The paper's sequential merge is a Python loop per triple: fewer, smaller extractions
        # keep detect() within ~1-2 s of CPU at 200k points.
        "paper": {
            "max_points": 2000,
            "n_resamples": 10,
            "n_iterations": 500,
            "min_weight": 5,
            "normal_tolerance": 0.1,
            "merge_distance": 0.1,
            "inlier_distance": 0.1,
            "min_points": 15,
        },
    }

    def _context(
        self,
        reference: NDArray[np.float64],
        scan: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> dict[str, Any]:
        params = self.params
        if self.variant == "paper":
            settings = PlaneSettings(
                normal_tolerance=params["normal_tolerance"],
                merge_distance=params["merge_distance"],
                inlier_distance=params["inlier_distance"],
                n_iterations=params["n_iterations"],
                min_weight=params["min_weight"],
                min_points=params["min_points"],
            )
            return {"settings": settings}
        origin = reference.mean(axis=0)
        rms_radius = float(np.sqrt(np.mean(np.sum((reference - origin) ** 2, axis=1))))
        noise_std, spacing = estimate_noise_and_spacing(reference, rng)
        inlier_distance = max(params["noise_multiplier"] * noise_std, 0.25 * spacing, 1e-9)
        normal_tolerance = float(np.clip(5.0 * noise_std / max(rms_radius, 1e-12), 0.05, 0.5))
        min_points = max(15, int(params["min_point_fraction"] * reference.shape[0]))
        settings = PlaneSettings(
            normal_tolerance=normal_tolerance,
            merge_distance=inlier_distance,
            inlier_distance=inlier_distance,
            n_iterations=params["n_iterations"],
            min_weight=params["min_weight"],
            min_points=min_points,
            orientation_origin=origin,
            refine=True,
            n_candidates=10,
            max_failed_rounds=3,
        )
        return {
            "settings": settings,
            "noise_std": noise_std,
            "spacing": spacing,
            "rms_radius": max(rms_radius, 1e-12),
        }

    def descriptor(
        self, points: NDArray[np.float64], context: dict[str, Any]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Weighted points for eq. (1): planes (k, 4) and their weights (k,).

        The random triples are drawn from a generator seeded by ``random_state`` and the
        points' bytes: the same cloud always gives the same planes (so ``d(S, S) = 0``), two
        different clouds get independent draws.

        Improved: inlier fractions plus, as the last row, the unexplained fraction (its plane
        row is NaN and is handled by :meth:`_score`).
        """
        content = hashlib.blake2b(np.ascontiguousarray(points).tobytes(), digest_size=8)
        rng = np.random.default_rng([self.random_state, int.from_bytes(content.digest(), "little")])
        planes, counts, n_unexplained = extract_fuzzy_planes(points, context["settings"], rng)
        if self.variant == "paper":
            return planes, counts
        fractions = np.append(counts, n_unexplained) / points.shape[0]
        return np.vstack([planes, np.full((1, 4), np.nan)]), fractions

    def _score(
        self,
        first: NDArray[np.float64],
        second: NDArray[np.float64],
        context: dict[str, Any],
        rng: np.random.Generator,
        is_resample: bool,
    ) -> float:
        planes_a, weights_a = self.descriptor(first, context)
        planes_b, weights_b = self.descriptor(second, context)
        if self.variant == "paper":
            if planes_a.shape[0] == 0 or planes_b.shape[0] == 0:
                # Eq. (1) is undefined without mass on both sides.
                if is_resample:
                    return float("nan")  # calibration drops it
                raise ExtractionError(
                    f"the paper's plane extraction found {planes_a.shape[0]} plane(s) in the "
                    f"reference and {planes_b.shape[0]} in the scan with its fixed thresholds "
                    f"(eta = {self.params['inlier_distance']:g}); eq. (1) needs planes on both "
                    "sides. Noisier data needs larger thresholds, or use variant='improved'"
                )
            ground = euclidean_ground_distances(planes_a, planes_b)
            return earth_movers_distance(weights_a, weights_b, ground).distance
        # (n, d / r): offsets in units of the reference's RMS radius, so the ground distance
        # (and unexplained_cost) mean the same in a corridor and in a warehouse.
        scale = np.array([1.0, 1.0, 1.0, 1.0 / context["rms_radius"]])
        ground = euclidean_ground_distances(planes_a[:-1] * scale, planes_b[:-1] * scale)
        cost = self.params["unexplained_cost"]
        full = np.zeros((planes_a.shape[0], planes_b.shape[0]))
        full[:-1, :-1] = ground
        full[-1, :-1] = cost
        full[:-1, -1] = cost
        return earth_movers_distance(weights_a, weights_b, full).distance

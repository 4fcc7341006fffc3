"""Rigid alignment of a scan to the reference scan of the same site (small_gicp GICP).

Robots report their pose with errors of centimetres and tenths of a degree (more after a long
drive: the KITTI frames in ../shared/data are 0.9 m apart); without alignment every wall would
show up as a change. :func:`register_scan` estimates the rigid transform that maps scan
coordinates into the reference frame with generalised ICP (``small_gicp``, C++), coarse to fine.

**Sample**: a cloud of more than :data:`SAMPLE_POINTS` points is aligned on a uniform random
sample of that many of its points (:func:`registration_sample`; the same draw for both clouds, so
a scan identical to its reference still aligns to the identity).  Everything below, the quality
figures included, is computed on the samples: on a 1M-point pair this is 0.2-0.3 instead of
0.8 CPU s, and moves the transform by ~0.01-0.02 degrees and ~1 mm (figures in
docs/performance.md).  The transform is checked on the whole clouds afterwards by the
localiser's misalignment residual (:func:`app.core.localise.distance.alignment_residual`),
which widens the noise threshold by whatever misalignment remains.

**Parameters** (when not given):

- ``spacing``: median nearest-neighbour distance, the finer of the two clouds
  (:func:`estimate_point_spacing`).
- Fine sample: the voxel-grid centroids at ``grid = 2 x spacing`` (this evens out lidar density,
  which is extreme near the sensor), then a uniform random sample of at most
  :data:`FINE_POINT_BUDGET` of them per cloud. Random thinning keeps the sampling unbiased:
  thinning with a coarser voxel grid instead biases GICP, because the two grids cut box edges
  differently (figures in docs/performance.md).
- ``voxel_size`` = the mean spacing of that sample, ``grid x sqrt(count / budget)`` when the grid
  keeps more than the budget (surfaces: count ~ 1/voxel^2), else ``grid``.
- ``max_correspondence_distance`` = ``4 x voxel_size``.

**Stages**:

1. Coarse: voxel-grid centroids at ``4 x voxel_size``, correspondences up to 4 x that
   (16 voxels): captures pose errors of that size (0.5 m / 5 degrees in a room scanned at 3 cm,
   0.9 m between KITTI frames). If fewer than ``min_fitness`` of the coarse points then have a
   reference neighbour, the clouds do not overlap and the fine stage is skipped.
2. Fine: the fine samples, from the coarse result, at ``max_correspondence_distance``, with
   tight convergence thresholds (``voxel_size / 1000`` and 0.006 degrees).
3. Proof: a result farther than ``max_correspondence_distance`` from the starting transform (a
   repeated structure locked one period off, or a real large error) is kept only when it beats
   the fine stage started from the starting transform, if that converged, by a margin, on a
   score that differing coverage does not fool (:mod:`app.core.registration_choice`).

Both clouds are shifted by the reference's bounding-box centre first (small_gicp's voxel grid
holds 21-bit coordinates, and rotations are better conditioned about the data); the returned
transform is expressed in the callers' coordinates.

The quality figures have one definition everywhere (:func:`evaluate_alignment`): both clouds are
voxel-downsampled at ``voxel_size``; ``fitness`` is the fraction of downsampled scan points with
a downsampled reference point within ``max_correspondence_distance`` after the transform, and
``rmse`` the RMS distance of those inliers (it includes the sampling distance between the two
voxel grids, up to about half a voxel).  :func:`register_scan` and
:func:`identity_registration` downsample the ``grid`` centroids they already have rather than
every point again (faster, with the same quality figures to 1e-3; see docs/performance.md);
the coarse stage starts from them too.  A fitness below ``min_fitness`` means the clouds do not
overlap (different sites, or a scan so far off that alignment failed): :class:`RegistrationError`.

**What depends on the reference alone** (its point spacing, ``grid`` centroids, their coarse
and quality-figure downsamplings) can be handed over by a
:class:`~app.core.cache.reference_memory.ReferenceMemory` (kept in the reference's geometry cache
by :mod:`app.core.cache.reference_alignment`); each is recalled under the parameters it was
computed with, so the result is the same with or without one.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.cache.reference_memory import ReferenceMemory, recalled
from app.core.cloud import PointCloud, column_extreme
from app.core.errors import RegistrationError
from app.core.registration_choice import largest_displacement, proven_transform
from app.core.registration_result import Registration
from app.core.registration_result import apply_transform as apply_transform
from app.core.registration_result import rotation_angle_degrees as rotation_angle_degrees

SAMPLE_POINTS = 200_000
"""Most points of each cloud the alignment sees (a uniform random sample beyond this)."""
SAMPLE_SEED = 0
"""Seed of :func:`registration_sample`'s draw (the same for both clouds)."""
FINE_POINT_BUDGET = 30_000
"""Most points per cloud in the fine stage (a uniform random sample beyond this)."""

FINE_VOXELS_PER_SPACING = 2.0
COARSE_VOXEL_FACTOR = 4.0
CORRESPONDENCE_VOXEL_FACTOR = 4.0
NUM_NEIGHBOURS = 20
"""Neighbours used by small_gicp to estimate each point's covariance."""

MAX_ITERATIONS = {"coarse": 40, "fine": 20}
"""GICP iterations per stage (the fine stage starts close to the solution)."""
MIN_POINTS_AFTER_DOWNSAMPLING = 20
NO_ALIGN_HINT = "compare without aligning"
"""How to skip the alignment, in no interface's words: a :class:`RegistrationError` carries
``how_to_fix = "skip_alignment"`` and the API (the job's ``"align": false``) or the CLI
(``--no-align``) appends its own knob."""
VOXEL_GRID_LIMIT = 2**19
"""Largest |coordinate| / voxel accepted: small_gicp's voxel keys are 21-bit signed (2**20),
halved for safety. Points beyond would be silently dropped."""

CloudLike = PointCloud | NDArray[np.floating]


def estimate_point_spacing(
    points: NDArray, sample_size: int = 2000, random_state: int = 0
) -> float:
    """Median distance from a point to its nearest distinct neighbour, on a random sample.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    sample_size : int
        Points whose nearest neighbour is looked up (all when n is smaller).
    random_state : int
        Seed of the sample.

    Returns
    -------
    float
        The median spacing; 0.0 when fewer than two distinct points exist.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 2:
        return 0.0
    rng = np.random.default_rng(random_state)
    sample = points[rng.choice(len(points), size=min(sample_size, len(points)), replace=False)]
    distances, _ = KDTree(np.ascontiguousarray(points)).query(sample, k=min(4, len(points)))
    distances = np.where(distances > 0.0, distances, np.inf).min(axis=1)
    distances = distances[np.isfinite(distances)]
    return float(np.median(distances)) if distances.size else 0.0


def evaluate_alignment(
    reference: CloudLike,
    scan: CloudLike,
    transform: NDArray,
    max_correspondence_distance: float,
    *,
    voxel_size: float | None = None,
) -> tuple[float, float]:
    """Fitness and RMSE of ``scan`` mapped by ``transform`` against ``reference``.

    Parameters
    ----------
    reference, scan : PointCloud or ndarray, shape (n, 3)
    transform : ndarray, shape (4, 4)
        Maps scan coordinates into the reference frame.
    max_correspondence_distance : float
        A scan point is an inlier when its nearest reference point is at most this far.
    voxel_size : float, optional
        Voxel-downsample both clouds first (what :func:`register_scan` does, so figures are
        comparable); default: use every point.

    Returns
    -------
    fitness : float
        Fraction of scan points that are inliers.
    rmse : float
        RMS inlier distance; NaN when there is no inlier.
    """
    reference_points = np.ascontiguousarray(_points_of(reference, "reference"), dtype=np.float64)
    scan_points = np.ascontiguousarray(_points_of(scan, "scan"), dtype=np.float64)
    if voxel_size is not None:
        centre = _centre_of(reference_points)
        reference_points = _downsample(reference_points - centre, voxel_size) + centre
        scan_points = _downsample(scan_points - centre, voxel_size) + centre
    return _inlier_fit(reference_points, scan_points, transform, max_correspondence_distance)


def _inlier_fit(
    reference_points: NDArray[np.float64],
    scan_points: NDArray[np.float64],
    transform: NDArray,
    max_correspondence_distance: float,
) -> tuple[float, float]:
    """Fitness and RMSE of :func:`evaluate_alignment` on the points as given."""
    moved = apply_transform(scan_points, transform)
    distances, _ = KDTree(np.ascontiguousarray(reference_points)).query(
        np.ascontiguousarray(moved), k=1, distance_upper_bound=max_correspondence_distance
    )
    inliers = distances[np.isfinite(distances)]
    fitness = float(inliers.size / max(len(moved), 1))
    rmse = float(np.sqrt(np.mean(inliers**2))) if inliers.size else float("nan")
    return fitness, rmse


def identity_registration(
    reference: CloudLike,
    scan: CloudLike,
    *,
    max_correspondence_distance: float | None = None,
    voxel_size: float | None = None,
    reference_memory: ReferenceMemory | None = None,
) -> Registration:
    """No alignment (``--no-align``): the identity, with fitness and RMSE measured.

    ``voxel_size`` and ``max_correspondence_distance`` default to the rule of
    :func:`register_scan`, so the figures are comparable with an aligned run;
    ``reference_memory`` as there.
    """
    reference_points = registration_sample(_points_of(reference, "reference"))
    scan_points = registration_sample(_points_of(scan, "scan"))
    plan = _plan(
        reference_points,
        scan_points - _centre_of(reference_points),
        voxel_size,
        max_correspondence_distance,
        reference_memory,
    )
    identity = np.eye(4)
    fitness, rmse = plan.fit_quality(identity)
    return Registration(identity, fitness, rmse, True, 0, "none", plan.distance, plan.voxel_size)


def _coarse_target(
    plan: _Plan, voxel: float, num_threads: int, memory: ReferenceMemory | None
) -> tuple[Any, Any]:
    """The reference's coarse-stage small_gicp cloud and tree (``plan.reference_grid``, (g, 3),
    downsampled at ``voxel``), recalled from ``memory`` or made and handed to it."""
    import small_gicp

    key = (plan.grid, voxel, num_threads)
    coarse_points = None if memory is None else memory.recall("coarse", key)
    if coarse_points is not None:  # what preprocess_points gave: the same cloud and tree
        return _gicp_cloud(coarse_points, num_threads)
    target, tree = small_gicp.preprocess_points(
        plan.reference_grid, voxel, num_neighbors=NUM_NEIGHBOURS, num_threads=num_threads
    )
    if memory is not None:
        memory.remember("coarse", key, _xyz(target.points()))
    return target, tree


def register_scan(
    reference: CloudLike,
    scan: CloudLike,
    *,
    voxel_size: float | None = None,
    max_correspondence_distance: float | None = None,
    initial_transform: NDArray | None = None,
    min_fitness: float = 0.3,
    num_threads: int = 1,
    reference_memory: ReferenceMemory | None = None,
) -> Registration:
    """Align ``scan`` to ``reference`` (coarse-to-fine GICP; see the module docstring).

    Parameters
    ----------
    reference, scan : PointCloud or ndarray, shape (n, 3)
        Coordinates near the origin preferably (local frame); any frame works.
    voxel_size : float, optional
        Fine-stage point spacing (the coarse stage uses 4x); default from the point spacing
        and :data:`FINE_POINT_BUDGET`.
    max_correspondence_distance : float, optional
        Fine-stage inlier distance; default ``4 x voxel_size``.
    initial_transform : ndarray, shape (4, 4), optional
        Initial guess mapping scan into reference coordinates (e.g. from odometry).
    min_fitness : float
        Raise :class:`RegistrationError` when the final fitness is lower.
    num_threads : int
        Threads small_gicp may use.
    reference_memory : ReferenceMemory, optional
        What was worked out from this reference before (the same result either way; what it
        lacks is computed and handed to it).

    Returns
    -------
    Registration

    Raises
    ------
    RegistrationError
        Too few points, the optimisation diverged, or the clouds do not overlap
        (fitness < ``min_fitness``).
    """
    import small_gicp

    reference_points = registration_sample(_points_of(reference, "reference"))
    scan_points = registration_sample(_points_of(scan, "scan"))
    centre = _centre_of(reference_points)
    local_scan = scan_points - centre
    plan = _plan(
        reference_points, local_scan, voxel_size, max_correspondence_distance, reference_memory
    )
    initial = np.eye(4) if initial_transform is None else _checked_transform(initial_transform)
    local_transform = _translated(initial, -centre)

    coarse_voxel = COARSE_VOXEL_FACTOR * plan.voxel_size
    coarse_distance = CORRESPONDENCE_VOXEL_FACTOR * coarse_voxel
    coarse_target, coarse_tree = _coarse_target(plan, coarse_voxel, num_threads, reference_memory)
    coarse_source, _ = small_gicp.preprocess_points(
        plan.scan_grid, coarse_voxel, num_neighbors=NUM_NEIGHBOURS, num_threads=num_threads
    )
    stages = [(coarse_target, coarse_tree, coarse_source, coarse_distance, False)]
    if min(coarse_target.size(), coarse_source.size()) < MIN_POINTS_AFTER_DOWNSAMPLING:
        stages = []  # too coarse for this small cloud: the fine stage alone will do
    fine_target, fine_tree = _gicp_cloud(plan.reference_sample, num_threads)
    fine_source, _ = _gicp_cloud(plan.scan_sample, num_threads)
    stages.append((fine_target, fine_tree, fine_source, plan.distance, True))

    iterations = 0
    converged = False
    for target, target_tree, source, distance, is_fine in stages:
        local_transform, stage_iterations, converged, stage_fitness = _gicp_stage(
            (target, target_tree, source), local_transform, distance, is_fine, plan, num_threads
        )
        iterations += stage_iterations
        if not is_fine and stage_fitness < min_fitness:
            # The fine stage only refines within a quarter of this distance: it cannot bring
            # more points into overlap, and on non-overlapping clouds it would spend seconds.
            raise _no_overlap_error(stage_fitness, distance, min_fitness)

    start = _translated(initial, -centre)
    if len(stages) > 1 and largest_displacement(plan.scan_sample, local_transform, start) > (
        plan.distance
    ):  # far from the start: the fine stage from the start too, and the better (see the module)
        near, near_iterations, near_converged, _ = _gicp_stage(
            (fine_target, fine_tree, fine_source), start, plan.distance, True, plan, num_threads
        )
        iterations += near_iterations
        if near_converged:  # else still sliding (along a corridor, say): no rival basin
            local_transform, _ = proven_transform(
                plan.reference_sample,
                plan.scan_sample,
                local_transform,
                near,
                plan.distance,
                plan.grid / 2.0,
            )

    transform = _translated(local_transform, centre)
    fitness, rmse = plan.fit_quality(local_transform)
    if fitness < min_fitness:
        raise _no_overlap_error(fitness, plan.distance, min_fitness)
    return Registration(
        transform,
        fitness,
        rmse,
        converged,
        iterations,
        "small_gicp",
        plan.distance,
        plan.voxel_size,
    )


def _gicp_stage(
    clouds: tuple[Any, Any, Any],
    start: NDArray[np.float64],
    distance: float,
    is_fine: bool,
    plan: _Plan,
    num_threads: int,
) -> tuple[NDArray[np.float64], int, bool, float]:
    """One GICP stage of :func:`register_scan` from ``start`` (4, 4), on ``clouds`` (target,
    its tree, source): the transform (4, 4), iterations, convergence and inlier share."""
    import small_gicp

    target, target_tree, source = clouds
    step = plan.voxel_size if is_fine else COARSE_VOXEL_FACTOR * plan.voxel_size
    result = small_gicp.align(
        target,
        source,
        target_tree,
        init_T_target_source=start,
        registration_type="GICP",
        max_correspondence_distance=distance,
        num_threads=num_threads,
        max_iterations=MAX_ITERATIONS["fine" if is_fine else "coarse"],
        rotation_epsilon=1e-4 if is_fine else np.radians(0.1),
        translation_epsilon=step * 1e-3,
    )
    transform = np.asarray(result.T_target_source, dtype=np.float64)
    if not np.isfinite(transform).all():
        diverged = "the alignment diverged (non-finite transform); check the inputs, or "
        raise RegistrationError(diverged + NO_ALIGN_HINT)
    inliers = result.num_inliers / max(source.size(), 1)
    return transform, int(result.iterations), bool(result.converged), inliers


def _no_overlap_error(fitness: float, distance: float, min_fitness: float) -> RegistrationError:
    return RegistrationError(
        f"the scan does not overlap the reference: only {fitness:.0%} of its points lie within "
        f"{distance:.3g} m of the reference after alignment (at least {min_fitness:.0%} needed, "
        'the registration parameter "min_fitness"); check that both scans are of the same '
        f"site, or {NO_ALIGN_HINT}"
    )


@dataclass(frozen=True)
class _Plan:
    """The parameters of one alignment and the fine-stage samples (local coordinates)."""

    voxel_size: float
    distance: float
    reference_sample: NDArray[np.float64]
    scan_sample: NDArray[np.float64]
    grid: float
    reference_grid: NDArray[np.float64]  # (p, 3) voxel-grid centroids at ``grid``, local frame
    scan_grid: NDArray[np.float64]  # (q, 3)
    reference_memory: ReferenceMemory | None = None

    def fit_quality(self, local_transform: NDArray[np.float64]) -> tuple[float, float]:
        """:func:`evaluate_alignment` of the grid centroids at ``voxel_size`` (local frame);
        the reference's side recalled from :attr:`reference_memory` when it has it."""
        if self.voxel_size <= self.grid:
            return evaluate_alignment(
                self.reference_grid, self.scan_grid, local_transform, self.distance
            )
        reference_points = np.ascontiguousarray(self.reference_grid)
        centre = _centre_of(reference_points)
        reference_fit = recalled(
            self.reference_memory,
            "fit",
            (self.grid, self.voxel_size),
            lambda: _downsample(reference_points - centre, self.voxel_size) + centre,
        )
        scan_points = np.ascontiguousarray(self.scan_grid)
        scan_fit = _downsample(scan_points - centre, self.voxel_size) + centre
        return _inlier_fit(reference_fit, scan_fit, local_transform, self.distance)


def _plan(
    reference_points: NDArray[np.float64],
    local_scan: NDArray[np.float64],
    voxel_size: float | None,
    max_correspondence_distance: float | None,
    reference_memory: ReferenceMemory | None = None,
) -> _Plan:
    """Apply the documented parameter rule; draw the fine-stage samples.

    ``reference_points`` in the callers' frame (shifted here by their bounding-box centre,
    only when something is not recalled from ``reference_memory``), ``local_scan`` already
    shifted by that centre.
    """
    low = column_extreme(reference_points, np.minimum)
    high = column_extreme(reference_points, np.maximum)
    centre = (low + high) / 2.0  # _centre_of(reference_points)

    @cache
    def local_reference() -> NDArray[np.float64]:
        return reference_points - centre

    # = np.abs(local_reference()).max(): subtracting ``centre`` keeps the order of each column
    reference_reach = float(max(np.abs(low - centre).max(), np.abs(high - centre).max()))
    reach = max(reference_reach, np.abs(local_scan).max())
    grid_floor = reach / VOXEL_GRID_LIMIT
    if voxel_size is not None:
        if voxel_size <= 0:
            raise ValueError("voxel_size must be positive")
        if voxel_size < grid_floor:
            raise RegistrationError(
                f"voxel_size {voxel_size:.3g} m is too small for a cloud reaching {reach:.3g} m "
                f"from its centre (at least {grid_floor:.3g} m); pass a larger voxel_size"
            )
    reference_spacing = recalled(
        reference_memory,
        "spacing",
        (),
        lambda: np.array([estimate_point_spacing(local_reference())]),
    )
    spacing = min(float(reference_spacing[0]), estimate_point_spacing(local_scan))
    grid = max(FINE_VOXELS_PER_SPACING * spacing, grid_floor, 1e-9)
    if voxel_size is not None:
        grid = min(grid, voxel_size)
    reference_grid = recalled(
        reference_memory, "grid", (grid,), lambda: _downsample(local_reference(), grid)
    )
    scan_grid = _downsample(local_scan, grid)
    if voxel_size is None:
        count = max(len(reference_grid), len(scan_grid))
        voxel_size = grid * float(np.sqrt(max(1.0, count / FINE_POINT_BUDGET)))
    if max_correspondence_distance is None:
        max_correspondence_distance = CORRESPONDENCE_VOXEL_FACTOR * voxel_size
    elif max_correspondence_distance <= 0:
        raise ValueError("max_correspondence_distance must be positive")
    rng = np.random.default_rng(0)
    samples = []
    for role, points in (("reference", reference_grid), ("scan", scan_grid)):
        if len(points) < MIN_POINTS_AFTER_DOWNSAMPLING:
            if grid <= grid_floor:  # the grid was widened because of how far the clouds reach
                reaches = {
                    "reference": reference_reach,
                    "scan": float(np.abs(local_scan).max()),
                }
                farthest = max(reaches, key=lambda name: reaches[name])
                raise RegistrationError(
                    f"cannot align: the {farthest} has points {reaches[farthest]:.3g} m from the "
                    f"reference's centre, which forces a {grid:.3g} m alignment grid at which the "
                    f"{role} keeps only {len(points)} points; check the {farthest} for stray "
                    f"points with absurd coordinates, or {NO_ALIGN_HINT}"
                )
            raise RegistrationError(
                f"too few points to align: the {role} keeps {len(points)} points at a "
                f"{grid:.3g} m voxel grid"
            )
        if len(points) > FINE_POINT_BUDGET:
            points = points[np.sort(rng.choice(len(points), FINE_POINT_BUDGET, replace=False))]
        samples.append(points)
    return _Plan(
        float(voxel_size),
        float(max_correspondence_distance),
        *samples,
        grid,
        reference_grid,
        scan_grid,
        reference_memory,
    )


def _gicp_cloud(points: NDArray[np.float64], num_threads: int):
    """A small_gicp cloud with per-point covariances, and its k-d tree."""
    import small_gicp

    cloud = small_gicp.PointCloud(points)
    tree = small_gicp.KdTree(cloud, num_threads)
    small_gicp.estimate_covariances(cloud, tree, NUM_NEIGHBOURS, num_threads)
    return cloud, tree


def _downsample(points: NDArray[np.float64], voxel_size: float) -> NDArray[np.float64]:
    """Voxel-grid centroids (small_gicp); ``points`` must be near the origin (21-bit grid)."""
    import small_gicp

    downsampled = small_gicp.voxelgrid_sampling(points, voxel_size, 1)
    return np.asarray(downsampled.points(), dtype=np.float64)[:, :3]


def _xyz(points: NDArray) -> NDArray[np.float64]:
    """The (n, 3) coordinates of small_gicp's (n, 4) homogeneous points, a contiguous copy."""
    return np.ascontiguousarray(np.asarray(points, dtype=np.float64)[:, :3])


def registration_sample(
    points: NDArray[np.floating], most: int | None = None
) -> NDArray[np.float64]:
    """A uniform random sample of ``most`` of ``points`` (all of them when there are fewer).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    most : int, optional
        The sample's size when ``n`` exceeds it; default :data:`SAMPLE_POINTS`.

    Returns
    -------
    ndarray, shape (min(n, most), 3), float64
        The chosen rows in their order in ``points`` (the draw depends on ``n`` and ``most``
        alone: two clouds of the same size keep the same rows).
    """
    most = SAMPLE_POINTS if most is None else most
    if len(points) <= most:
        return np.ascontiguousarray(points, dtype=np.float64)
    rows = np.random.default_rng(SAMPLE_SEED).choice(len(points), most, replace=False)
    return np.ascontiguousarray(points[np.sort(rows)], dtype=np.float64)


def _points_of(cloud: CloudLike, role: str) -> NDArray[np.floating]:
    """The (n, 3) points of ``cloud``, checked (float32 or float64, as given)."""
    points = cloud.points if isinstance(cloud, PointCloud) else np.asarray(cloud)
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{role} points must have shape (n, 3), got {points.shape}")
    if len(points) < MIN_POINTS_AFTER_DOWNSAMPLING:
        raise RegistrationError(
            f"the {role} has only {len(points)} points; at least "
            f"{MIN_POINTS_AFTER_DOWNSAMPLING} are needed to align"
        )
    if not np.isfinite(points).all():
        raise ValueError(f"{role} points contain NaN or inf")
    return points


def _centre_of(points: NDArray[np.float64]) -> NDArray[np.float64]:
    return (column_extreme(points, np.minimum) + column_extreme(points, np.maximum)) / 2.0


def _translated(transform: NDArray[np.float64], shift: NDArray[np.float64]) -> NDArray:
    """The same motion expressed in coordinates shifted by ``shift`` (x' = x + shift)."""
    moved = transform.copy()
    moved[:3, 3] = transform[:3, 3] + shift - transform[:3, :3] @ shift
    return moved


def _checked_transform(transform: NDArray) -> NDArray[np.float64]:
    matrix = np.asarray(transform, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ValueError("initial_transform must be a finite (4, 4) matrix")
    return matrix

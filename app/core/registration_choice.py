"""Which of two alignments to keep when the coarse stage moved the scan far from its start.

:func:`app.core.registration.register_scan`'s coarse stage matches points up to 16 voxels apart
(1.6 m in a warehouse scanned at 2.5 cm): it captures real pose errors of that size, and it can
also lock a repeated structure one period off (pallet racks, shelves, columns), where the
shifted scan overlaps the reference about as well as the true one: two terrestrial surveys of a
warehouse whose stations saw different aisles were registered 0.6-1.0 m off.  Maps are usually
already near-aligned (a robot's pose error is centimetres and tenths of a degree; co-registered
surveys share their frame), so a result far from the starting transform must prove itself:
:func:`proven_transform` compares it with the fine stage started from the starting transform
itself, and keeps the far one only when its :func:`overlap_score` beats the near one's by
:data:`FAR_SCORE_MARGIN` (:func:`~app.core.registration.register_scan` asks only when that fine
stage converged: one still sliding, along a corridor say, has found no basin of its own).

On the TLS warehouses whose coarse stage locked the racks off (scenes 005, 2205, 2304 of
``bench.moving_maps``) the far result scored 0.69, 1.08 and 0.53 times the near one (the
converged fit from the identity, the truth); where a scan was moved 1-1.5 m and the near fit
converged short of it (TLS warehouse 104 moved 0.8-1.5 m), the far (true) result scored 1.5-1.8
times the near one.

The score is not fooled by differing coverage the way the scan-side fitness is (a scan that
saw an aisle more than the reference puts that aisle onto the reference's racks when shifted
by a period, gaining inliers): it averages the fitness both ways (the reference's points
unmatched under the shift count against it) and multiplies it by the share of the scan's
points near a reference plane that lie on it (a rotated or half-locked fit leaves a residual
of centimetres where the true fit leaves the noise).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.registration_result import apply_transform

FAR_SCORE_MARGIN = 1.25
"""A far alignment is kept when its score is at least this many times the near one's."""
PLANE_NEIGHBOURS = 8
"""Reference neighbours a scan point's local plane is fitted to in :func:`overlap_score`."""
PLANARITY = 0.1
"""A neighbourhood is a plane when its smallest covariance eigenvalue is under this share of
the middle one."""


def largest_displacement(
    points: NDArray[np.float64], first: NDArray[np.float64], second: NDArray[np.float64]
) -> float:
    """How far apart two transforms put ``points`` at most.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    first, second : ndarray, shape (4, 4)

    Returns
    -------
    float
        The largest distance between a point moved by ``first`` and by ``second``.
    """
    difference = (first - second)[:3]
    moved = points @ difference[:, :3].T + difference[:, 3]
    return float(np.sqrt((moved**2).sum(axis=1).max())) if len(points) else 0.0


def overlap_score(
    reference: NDArray[np.float64],
    scan: NDArray[np.float64],
    transform: NDArray[np.float64],
    distance: float,
    on_plane: float,
) -> float:
    """Mutual fitness times the share of on-plane scan points, of ``scan`` moved by
    ``transform`` against ``reference``.

    Parameters
    ----------
    reference : ndarray, shape (p, 3)
    scan : ndarray, shape (q, 3)
        Moved by ``transform`` before scoring.
    transform : ndarray, shape (4, 4)
    distance : float
        Inlier distance of the fitness both ways (scan to reference and back).
    on_plane : float
        A scan point lies on its reference plane when it is at most this far from it.

    Returns
    -------
    float
        In [0, 1]: ``(scan fitness + reference fitness) / 2`` times the share of scan points,
        among those whose :data:`PLANE_NEIGHBOURS` reference neighbours lie within
        ``distance`` and form a plane, that are within ``on_plane`` of that plane (1 when
        there are none).
    """
    moved = apply_transform(scan, transform)
    neighbours = min(PLANE_NEIGHBOURS, len(reference))
    distances, rows = KDTree(reference).query(moved, k=neighbours)
    distances = distances.reshape(len(moved), neighbours)
    rows = rows.reshape(len(moved), neighbours)
    scan_fitness = np.mean(distances[:, 0] <= distance)
    back, _ = KDTree(moved).query(reference, k=1, distance_upper_bound=distance)
    reference_fitness = np.mean(np.isfinite(back))
    near = distances[:, -1] <= distance
    patches = reference[rows[near]]  # (m, k, 3)
    centres = patches.mean(axis=1)
    spread = patches - centres[:, None, :]
    eigenvalues, eigenvectors = np.linalg.eigh(np.einsum("mki,mkj->mij", spread, spread))
    planar = eigenvalues[:, 0] < PLANARITY * eigenvalues[:, 1]
    normals = eigenvectors[planar, :, 0]
    residuals = np.abs(np.einsum("mi,mi->m", moved[near][planar] - centres[planar], normals))
    on_plane_share = float(np.mean(residuals <= on_plane)) if residuals.size else 1.0
    return float((scan_fitness + reference_fitness) / 2.0) * on_plane_share


def proven_transform(
    reference: NDArray[np.float64],
    scan: NDArray[np.float64],
    far: NDArray[np.float64],
    near: NDArray[np.float64],
    distance: float,
    on_plane: float,
) -> tuple[NDArray[np.float64], bool]:
    """``far`` when it proves itself against ``near``, else ``near``.

    Parameters
    ----------
    reference : ndarray, shape (p, 3)
    scan : ndarray, shape (q, 3)
    far : ndarray, shape (4, 4)
        The alignment the coarse stage led to, far from the starting transform.
    near : ndarray, shape (4, 4)
        The fine stage's alignment started from the starting transform.
    distance, on_plane : float
        As in :func:`overlap_score`.

    Returns
    -------
    transform : ndarray, shape (4, 4)
    far_kept : bool
        Whether ``far`` was kept: the two agree within ``on_plane`` (the same solution), or
        ``far``'s :func:`overlap_score` is at least :data:`FAR_SCORE_MARGIN` times ``near``'s.
    """
    if largest_displacement(scan, far, near) <= on_plane:
        return far, True
    far_score = overlap_score(reference, scan, far, distance, on_plane)
    near_score = overlap_score(reference, scan, near, distance, on_plane)
    if far_score >= FAR_SCORE_MARGIN * near_score:
        return far, True
    return near, False

"""The result of :func:`app.core.registration.register_scan`, and :func:`apply_transform` that
moves points by it (kept apart from the alignment's code, which
:mod:`app.core.cache.reference_alignment` hashes into its cache key)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Registration:
    """The result of aligning a scan to its reference.

    Attributes
    ----------
    transform : ndarray, shape (4, 4), float64
        Homogeneous rigid transform mapping scan coordinates into the reference frame.
    fitness : float
        Fraction of (voxel-downsampled) scan points with a reference neighbour within
        ``max_correspondence_distance`` after alignment, in [0, 1].
    rmse : float
        RMS distance of those inlier correspondences (same units as the points); NaN when
        there is no inlier.
    converged : bool
        Whether the final GICP stage met its convergence thresholds (always True for "none").
    iterations : int
        GICP iterations over all stages.
    method : str
        ``"small_gicp"`` or ``"none"`` (identity, e.g. ``--no-align``).
    max_correspondence_distance : float
        Inlier distance of the final stage and of ``fitness``/``rmse``.
    voxel_size : float
        Fine-stage voxel size, also used for ``fitness``/``rmse``.
    """

    transform: NDArray[np.float64]
    fitness: float
    rmse: float
    converged: bool
    iterations: int
    method: str
    max_correspondence_distance: float
    voxel_size: float

    @property
    def translation(self) -> NDArray[np.float64]:
        """Translation part of :attr:`transform`, shape (3,)."""
        return self.transform[:3, 3].copy()

    @property
    def rotation_degrees(self) -> float:
        """Angle of the rotation part of :attr:`transform`, in degrees."""
        return rotation_angle_degrees(self.transform[:3, :3])

    def to_json_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary (transform as nested lists, NaN rmse as None).

        The translation is left to ``transform`` on purpose: callers that re-express the
        transform in another frame (e.g. file coordinates) replace that one key.
        """
        return {
            "transform": self.transform.tolist(),
            "fitness": float(self.fitness),
            "rmse": None if not np.isfinite(self.rmse) else float(self.rmse),
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "method": self.method,
            "max_correspondence_distance": float(self.max_correspondence_distance),
            "voxel_size": float(self.voxel_size),
            "rotation_degrees": self.rotation_degrees,  # frame-independent, unlike translation
        }


def rotation_angle_degrees(rotation: NDArray) -> float:
    """Angle of a 3x3 rotation matrix, in degrees (0 for the identity)."""
    cosine = (np.trace(np.asarray(rotation, dtype=np.float64)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def apply_transform(points: NDArray, transform: NDArray) -> NDArray[np.float64]:
    """Apply a homogeneous rigid transform to points.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    transform : ndarray, shape (4, 4)

    Returns
    -------
    ndarray, shape (n, 3), float64
        ``points @ R.T + t``.
    """
    points = np.asarray(points, dtype=np.float64)
    transform = np.asarray(transform, dtype=np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]

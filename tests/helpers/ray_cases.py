"""Ray-test cases built by hand: candidates on one flat face, and their status seen by a station.

Shared by the ray test's unit tests (edge-on faces, grazing rays, surfaces sampled in lines),
which each place a face of the own cloud and cast a synthetic lidar at it.
"""

from __future__ import annotations

import numpy as np

from app.core.localise.rays import Candidates, RayTest, ray_visibility
from app.core.localise.surface import LocalGeometry, local_geometry


def ray_test(tolerance: float, **overrides: float) -> RayTest:
    """The ray test's settings these cases use, with normal and range tolerance ``tolerance``."""
    settings = {
        "normal_tolerance": tolerance,
        "range_tolerance": tolerance,
        "margin_factor": 1.0,
        "angle_factor": 2.5,
        "beyond_fraction": 0.5,
        "miss_factor": 4.0,
    }
    return RayTest(**(settings | overrides))


def face_candidates(
    points: np.ndarray,
    own: LocalGeometry,
    chosen: np.ndarray,
    normal: tuple[float, float, float],
    surface_distance: np.ndarray,
) -> Candidates:
    """Candidates at ``points[chosen]`` (shape (m,)) on a face of the given normal."""
    return Candidates(
        index=chosen,
        points=points[chosen],
        normal=np.tile(np.array(normal, dtype=np.float32), (chosen.size, 1)),
        linear=np.zeros(chosen.size, dtype=bool),
        spacing=own.spacing[chosen],
        surface_distance=np.asarray(surface_distance, dtype=np.float64),
    )


def status_seen_by(
    candidates: Candidates,
    own: LocalGeometry,
    other_points: np.ndarray,
    sensor: np.ndarray,
    test: RayTest,
) -> np.ndarray:
    """The ray status of each candidate seen by one station of the other epoch at ``sensor``
    whose returns are ``other_points`` (shape (k, 3))."""
    other = local_geometry(other_points, 10)
    status, _ = ray_visibility(
        candidates,
        own=own,
        other_points=other_points,
        other_origin=sensor,
        test=test,
        other_normals=other.normal,
        other_linear=other.linear,
    )
    return status

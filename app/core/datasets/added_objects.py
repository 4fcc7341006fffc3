"""Objects added to a real scan: a box of points on its ground, sampled far more densely than
a lidar would (every face whole, on a regular grid), as a user's edited or merged cloud may be.

Used to test that the origin searches are not outweighed by such points
(:func:`~app.core.origins.voxels.whole_voxels` with ``thin_crowded``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["GRID_STEPS", "box_on_the_ground"]

GRID_STEPS = 81
"""Grid points along each edge of a face (81: a 4 x 1.8 x 1.5 m car-sized box has 39k points)."""


def box_on_the_ground(
    points: NDArray[np.float64],
    low_xy: tuple[float, float],
    high_xy: tuple[float, float],
    height: float,
    steps: int = GRID_STEPS,
) -> NDArray[np.float64]:
    """The six faces of a box standing on the ground of ``points`` (n, 3), on a grid.

    The ground is the 10th percentile of the heights of the points within 2 m (in x and y) of
    the box's centre (of all points when none is there).  Each face is a ``steps`` x ``steps``
    grid; points shared by two faces are kept once (rounded to the millimetre).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The scan (z up).
    low_xy, high_xy : tuple of float
        The box's corners in the top view.
    height : float
    steps : int

    Returns
    -------
    ndarray, shape (m, 3)
    """
    centre = (np.asarray(low_xy) + np.asarray(high_xy)) / 2.0
    near = np.all(np.abs(points[:, :2] - centre) < 2.0, axis=1)
    ground = float(np.percentile(points[near, 2] if near.any() else points[:, 2], 10))
    low = np.array([*low_xy, ground])
    high = np.array([*high_xy, ground + height])
    grid = np.arange(0.0, 1.0 + 1e-9, 1.0 / (steps - 1))
    first, second = np.meshgrid(grid, grid, indexing="ij")
    faces = []
    for axis in range(3):
        others = [other for other in range(3) if other != axis]
        for side in (0.0, 1.0):
            unit = np.zeros((first.size, 3))
            unit[:, others[0]] = first.ravel()
            unit[:, others[1]] = second.ravel()
            unit[:, axis] = side
            faces.append(low + unit * (high - low))
    return np.unique(np.round(np.vstack(faces), 3), axis=0)

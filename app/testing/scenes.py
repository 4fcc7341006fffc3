"""Small synthetic point clouds: random grid points, a room, a corridor."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def random_points(n: int = 64, seed: int = 0) -> NDArray[np.float64]:
    """(n, 3) coordinates exactly representable in float32 (on a 1/64 grid: LZF-compressible)."""
    rng = np.random.default_rng(seed)
    return np.round(rng.uniform(-50.0, 50.0, size=(n, 3)) * 64) / 64


def room_points(
    n_points: int = 3000,
    seed: int | np.random.Generator = 0,
    *,
    noise: float = 0.005,
    with_box: bool = False,
) -> NDArray[np.float64]:
    """A floor and two walls of a 6 x 4 x 2.5 m room with Gaussian ``noise`` (m), (n_points, 3).

    ``seed`` is a seed or a generator to draw from (then left advanced).  ``with_box`` adds a
    0.8 m box on the floor (a sixth of ``n_points`` more points).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    third = n_points // 3
    floor = np.column_stack(
        [rng.uniform(0, 6, third), rng.uniform(0, 4, third), rng.normal(0, noise, third)]
    )
    wall_x = np.column_stack(
        [rng.uniform(0, 6, third), rng.normal(4, noise, third), rng.uniform(0, 2.5, third)]
    )
    rest = n_points - 2 * third
    wall_y = np.column_stack(
        [rng.normal(0, noise, rest), rng.uniform(0, 4, rest), rng.uniform(0, 2.5, rest)]
    )
    parts = [floor, wall_x, wall_y]
    if with_box:
        parts.append(rng.uniform([2.5, 1.5, 0.0], [3.3, 2.3, 0.8], (third // 2, 3)))
    return np.vstack(parts)


def corridor_points(n_points: int, *, added_box: bool, seed: int) -> NDArray[np.float64]:
    """Points on the walls x = +-1 of a corridor; with ``added_box``, a box near x = 1.5."""
    rng = np.random.default_rng(seed)
    y = rng.uniform(-2, 2, n_points)
    z = rng.uniform(0, 2, n_points)
    x = np.where(rng.random(n_points) < 0.5, -1.0, 1.0) + rng.normal(0, 0.005, n_points)
    points = np.column_stack([x, y, z])
    if added_box:
        box = rng.uniform([1.2, -0.3, 0.0], [1.8, 0.3, 0.6], (n_points // 10, 3))
        points = np.vstack([points, box])
    return points

"""A timed room scan and TUM trajectories for the trajectory upload tests (plain and resumable)."""

from __future__ import annotations

import numpy as np

from app.testing.files import ply_bytes
from app.testing.scenes import room_points

N_POINTS = 3000
POINT_TIMES = np.linspace(100.0, 110.0, N_POINTS)


def timed_ply(seed: int = 1) -> bytes:
    return ply_bytes(room_points(N_POINTS, seed), extra={"time": POINT_TIMES})


def tum(times: np.ndarray, quaternion: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0)) -> bytes:
    rows = [
        f"{time!r} {1.0 + 0.1 * number} 2.0 1.2 " + " ".join(map(repr, quaternion))
        for number, time in enumerate(map(float, times))
    ]
    return ("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows)).encode()


GOOD = tum(np.linspace(99.0, 111.0, 25))

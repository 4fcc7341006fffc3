"""Both clouds of a comparison in one point file: the reference, then the scan aligned to it.

The one layout of ``scandiff compare --export`` and of a job's PLY/LAS labels download
(:mod:`app.services.results`): the points of both clouds in the reference's file frame, with
per-point fields ``cloud`` (0 reference, 1 scan), ``label`` (1 changed, 0 unchanged, -1
unobserved), ``distance`` (to the other cloud's surface, NaN where unknown) and ``region`` (the
index of the point's change region, -1: none).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["both_clouds"]


def both_clouds(
    reference_points: NDArray[np.float64],
    scan_points: NDArray[np.float64],
    *,
    labels: tuple[NDArray[np.integer], NDArray[np.integer]],
    distances: tuple[NDArray[np.floating] | None, NDArray[np.floating] | None],
    regions: tuple[NDArray[np.integer] | None, NDArray[np.integer] | None],
) -> tuple[NDArray[np.float64], dict[str, NDArray]]:
    """The stacked points of both clouds and their per-point fields.

    Parameters
    ----------
    reference_points : ndarray, shape (n, 3)
    scan_points : ndarray, shape (m, 3)
        The scan already moved into the reference's frame.
    labels : (ndarray, ndarray), shapes (n,) and (m,)
        Per-point labels of each cloud, in the order of its points.
    distances : (ndarray or None, ndarray or None), shapes (n,) and (m,)
        Per-point distances; None (older results): NaN.
    regions : (ndarray or None, ndarray or None), shapes (n,) and (m,)
        Per-point region indices; None (older results): -1.

    Returns
    -------
    points : ndarray, shape (n + m, 3)
    fields : dict of str to ndarray, each shape (n + m,)
        ``cloud`` uint8, ``label`` int8, ``distance`` float32, ``region`` int32.
    """
    counts = (len(reference_points), len(scan_points))

    def stacked(
        pair: tuple[NDArray | None, NDArray | None], dtype: type, missing: float
    ) -> NDArray:
        return np.concatenate(
            [
                np.full(count, missing, dtype=dtype) if values is None else values.astype(dtype)
                for values, count in zip(pair, counts, strict=True)
            ]
        )

    fields = {
        "cloud": np.concatenate([np.zeros(counts[0], np.uint8), np.ones(counts[1], np.uint8)]),
        "label": stacked(labels, np.int8, 0),
        "distance": stacked(distances, np.float32, np.nan),
        "region": stacked(regions, np.int32, -1),
    }
    return np.vstack([reference_points, scan_points]), fields

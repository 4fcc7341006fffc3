"""Stage 3, **align**: the scan registered onto the reference (GICP via small_gicp), or the
identity with its fit measured when alignment is off."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.cache.reference_alignment import ReferenceAlignmentCache
from app.core.comparison.load import LoadedPair
from app.core.comparison.reports import RegistrationReport
from app.core.registration import (
    Registration,
    apply_transform,
    identity_registration,
    register_scan,
)

TRANSFORM_CHUNK = 1 << 20
"""Points per step of :func:`transformed` on float32 points (bounds its float64 temporaries)."""


@dataclass(frozen=True)
class Alignment:
    """The scan in the reference's local frame.

    Attributes
    ----------
    registration : Registration
        The transform (local frame) and its fit.
    aligned_scan : ndarray, shape (m, 3)
        The scan's local points moved by it.
    report : RegistrationReport
        Its fit, with the transform in the files' frame.
    """

    registration: Registration
    aligned_scan: NDArray[np.float64]
    report: RegistrationReport


def align_scan(
    loaded: LoadedPair,
    reference_memory: ReferenceAlignmentCache | None = None,
    *,
    sample_points: int | None = None,
) -> Alignment:
    """Register ``loaded``'s scan onto its reference (when ``settings.align``).

    Parameters
    ----------
    loaded : LoadedPair
        With its scan points (not released).
    reference_memory : ReferenceAlignmentCache, optional
        The reference's alignment arrays kept between comparisons.
    sample_points : int, optional
        Register on at most about this many points of each cloud, evenly strided (GICP thins
        both clouds on a voxel grid anyway), and report it; None: on every point.

    Returns
    -------
    Alignment

    Raises
    ------
    InputError
        Clouds that cannot be aligned.
    """
    scan_points = loaded.scan_points
    if scan_points is None:
        raise ValueError("the scan's local points were released before its alignment")
    reference_sample = strided(loaded.reference_points, sample_points)
    scan_sample = strided(scan_points, sample_points)
    if loaded.settings.align:
        registration = register_scan(
            reference_sample,
            scan_sample,
            reference_memory=reference_memory,
            **loaded.settings.registration,
        )
    else:
        registration = identity_registration(
            reference_sample, scan_sample, reference_memory=reference_memory
        )
    del reference_sample, scan_sample
    aligned_scan = transformed(scan_points, registration.transform)
    centre = scan_points.mean(
        axis=0, dtype=np.float64
    )  # how far the alignment moved the scan (metres)
    moved = apply_transform(centre[None], registration.transform)[0] - centre
    report = RegistrationReport.of(
        registration,
        file_frame_transform(registration.transform, loaded.local_origin),
        enabled=loaded.settings.align,
        translation_m=float(np.linalg.norm(moved)),
        sample_points=None
        if sample_points is None
        else min(len(loaded.reference_points), sample_points),
    )
    return Alignment(registration, aligned_scan, report)


def transformed(points: NDArray[np.floating], transform: NDArray[np.float64]) -> NDArray:
    """``points`` (n, 3) moved by ``transform`` (4, 4), keeping their dtype: float64 as
    :func:`~app.core.registration.apply_transform`; float32 (a pair read lean) a chunk of
    :data:`TRANSFORM_CHUNK` at a time, without a float64 copy of the whole cloud."""
    if points.dtype == np.float64:
        return apply_transform(points, transform)
    moved = np.empty(points.shape, dtype=points.dtype)
    for start in range(0, len(points), TRANSFORM_CHUNK):
        moved[start : start + TRANSFORM_CHUNK] = apply_transform(
            points[start : start + TRANSFORM_CHUNK], transform
        )
    return moved


def strided(points: NDArray[np.float64], most: int | None) -> NDArray[np.float64]:
    """Every k-th row of ``points``, shape (n, 3), so that about ``most`` remain (None: all)."""
    return points if most is None else points[:: max(1, len(points) // most)]


def file_frame_transform(
    local_transform: NDArray[np.float64], local_origin: NDArray[np.float64]
) -> NDArray[np.float64]:
    """A transform estimated in local coordinates, shape (4, 4), in the files' coordinates."""
    shift = np.eye(4)
    shift[:3, 3] = local_origin
    unshift = np.eye(4)
    unshift[:3, 3] = -local_origin
    return shift @ local_transform @ unshift

"""Opt-in artefacts of real fused RGB-D maps: tracking drift, flying pixels, missing patches.

A handheld map (:func:`app.core.datasets.handheld.handheld_pair`) is rendered from exact camera
poses.  Real fused maps (KinectFusion, BundleFusion, ORB-SLAM style pipelines) are not:

- **tracking drift**: the estimated pose of each frame wanders from the true one along the path
  (a smooth random walk of a few millimetres and a tenth of a degree or so), and a
  loop-closure-like step pulls the end back towards the start, partially.  A surface seen on
  two passes is fused twice, a little apart: doubled or thickened by 1-3 cm, corners smeared;
- **flying pixels**: a pixel on a depth edge (its neighbour hits another surface well behind or
  in front) mixes the two depths and lands in the air between them;
- **missing patches**: dark or shiny spots return no depth; a few patches of each epoch's
  surfaces are (mostly) missing.

The truth is untouched: it is computed from each sample's exact surface point (the point its
ray hit in the true world), so a point moved by drift or a flying pixel is changed only when its
surface is more than 10 cm from every surface of the other epoch's world.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

__all__ = [
    "REALISM_LEVELS",
    "DepthArtefacts",
    "drift_errors",
    "fly_edge_pixels",
    "missing_patches",
    "realism_artefacts",
]


@dataclass(frozen=True)
class DepthArtefacts:
    """The artefacts' sizes; ranges are drawn per epoch.

    Attributes
    ----------
    drift_shift : (float, float)
        Largest translation error (metres) of any frame of a path, after the loop closure.
    drift_angle_deg : (float, float)
        Largest rotation error (degrees) of any frame of a path, after the loop closure.
    loop_correction : (float, float)
        Share of the end's error the loop closure removes (spread linearly over the path).
    flying_share : float
        Share of the pixels on a depth edge whose depth is mixed with their neighbour's.
    edge_jump : float
        A depth edge: a 4-neighbour pixel hits another box (or the shell) more than this far
        (metres) in front or behind.
    holes : (int, int)
        Missing patches per epoch (inclusive range).
    hole_radius : (float, float)
        Radius (metres) of a missing patch around a surface point.
    hole_dropout : float
        Share of the samples inside a patch that are missing.
    """

    drift_shift: tuple[float, float] = (0.003, 0.012)
    drift_angle_deg: tuple[float, float] = (0.05, 0.3)
    loop_correction: tuple[float, float] = (0.4, 0.9)
    flying_share: float = 0.15
    edge_jump: float = 0.1
    holes: tuple[int, int] = (3, 8)
    hole_radius: tuple[float, float] = (0.08, 0.25)
    hole_dropout: float = 0.9


REALISM_LEVELS = ("none", "drift")
"""Values of ``realism``: ``"none"`` renders exact poses (the default), ``"drift"`` adds
:class:`DepthArtefacts`."""


def realism_artefacts(realism: str) -> DepthArtefacts | None:
    """The artefacts of a ``realism`` level (None for ``"none"``)."""
    if realism not in REALISM_LEVELS:
        raise ValueError(f"realism must be one of {REALISM_LEVELS}, got {realism!r}")
    return DepthArtefacts() if realism == "drift" else None


def _drifting(
    rng: np.random.Generator, count: int, correction: float, largest: float
) -> NDArray[np.float64]:
    """A smooth random walk (count, 3) from 0, less ``correction`` of its end's value spread
    linearly along it (a partial loop closure), scaled to ``largest`` norm."""
    if count < 2:
        return np.zeros((count, 3))
    velocity = np.cumsum(rng.normal(size=(count, 3)), axis=0)
    walk = np.cumsum(velocity, axis=0)
    walk -= walk[0]
    walk -= correction * np.linspace(0.0, 1.0, count)[:, None] * walk[-1:]
    norm = np.linalg.norm(walk, axis=1).max()
    return walk * (largest / norm) if norm > 0 else walk


def drift_errors(
    rng: np.random.Generator, count: int, artefacts: DepthArtefacts
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per frame of a path: the pose error as a rotation (count, 3, 3) and a shift (count, 3).

    Both are smooth random walks from zero at the first frame (the map's frame is the first
    frame's); a loop closure removes a drawn share of the last frame's error, growing linearly
    along the path; then each is scaled to its drawn largest size
    (:attr:`DepthArtefacts.drift_shift`, :attr:`DepthArtefacts.drift_angle_deg`).
    """
    correction = rng.uniform(*artefacts.loop_correction)
    shift = _drifting(rng, count, correction, rng.uniform(*artefacts.drift_shift))
    angle = _drifting(rng, count, correction, np.radians(rng.uniform(*artefacts.drift_angle_deg)))
    return Rotation.from_rotvec(angle).as_matrix(), shift


def fly_edge_pixels(
    depth: NDArray[np.float64],
    box: NDArray[np.int64],
    artefacts: DepthArtefacts,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Depths with flying pixels: some pixels on depth edges mixed with their neighbour's.

    Parameters
    ----------
    depth : ndarray, shape (f, rows, columns)
        Each frame's depth image (metres along the optical axis).
    box : ndarray, shape (f, rows, columns), int64
        The box each pixel hit (-1: the shell).
    artefacts : DepthArtefacts
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (f, rows, columns)
        ``depth`` with a share :attr:`DepthArtefacts.flying_share` of the edge pixels (the
        4-neighbour with the largest depth jump hits another box, more than
        :attr:`DepthArtefacts.edge_jump` away in depth) moved to a uniform mix of their own and
        that neighbour's depth.
    """
    jump = np.zeros_like(depth)
    for axis in (1, 2):
        for step in (1, -1):
            neighbour_depth = np.roll(depth, step, axis=axis)
            other_surface = np.roll(box, step, axis=axis) != box
            difference = np.where(other_surface, neighbour_depth - depth, 0.0)
            border = [slice(None)] * 3
            border[axis] = 0 if step == 1 else -1
            difference[tuple(border)] = 0.0
            difference = np.where(np.isfinite(difference), difference, 0.0)
            jump = np.where(np.abs(difference) > np.abs(jump), difference, jump)
    edge = np.abs(jump) > artefacts.edge_jump
    flying = edge & (rng.uniform(size=depth.shape) < artefacts.flying_share)
    mix = rng.uniform(0.1, 0.9, size=depth.shape)
    return np.where(flying, depth + mix * jump, depth)


def missing_patches(
    exact: NDArray[np.float64], artefacts: DepthArtefacts, rng: np.random.Generator
) -> NDArray[np.bool_]:
    """Which samples of one epoch remain, shape (s,): a drawn number of patches (balls around
    drawn surface points ``exact`` (s, 3)) lose a share :attr:`DepthArtefacts.hole_dropout`
    of their samples."""
    remaining = np.ones(len(exact), dtype=bool)
    if len(exact) == 0:
        return remaining
    count = int(rng.integers(artefacts.holes[0], artefacts.holes[1] + 1))
    centres = exact[rng.integers(0, len(exact), count)]
    radii = rng.uniform(*artefacts.hole_radius, count)
    dropped = rng.uniform(size=len(exact)) < artefacts.hole_dropout
    for centre, radius in zip(centres, radii, strict=True):
        inside = np.sum((exact - centre) ** 2, axis=1) <= radius**2
        remaining &= ~(inside & dropped)
    return remaining

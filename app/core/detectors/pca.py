"""PCA-EMD: compare the principal axes of two clouds (paper section III-A, eq. (2)).

``paper``
    Eigenvectors ``v_k`` of the 3x3 covariance matrix (as ``numpy.linalg.eigh`` returns them,
    with an arbitrary sign), each weighted by its eigenvalue ``lambda_k``; Euclidean ground
    distance between eigenvectors; eq. (1) with partial transport because the eigenvalue sums
    (total variances) of the two clouds differ.

``improved``
    Two defects of the paper's construction are fixed:

    * **sign**: ``v`` and ``-v`` are the same axis, yet ``|v - (-v)| = 2``. Whether numpy
      returns ``v`` or ``-v`` flips with tiny perturbations of the covariance, which alone
      reproduces the paper's large spread. The ground distance is made sign-invariant:
      ``min(|a - b|, |a + b|)``.
    * **what is weighted**: with eigenvalue weights the total masses differ, and eq. (1) simply
      leaves the surplus variance untransported, so a change that adds variance (an object in
      an empty corridor) is partly invisible; and the unit eigenvectors carry no size at all.
      The improved descriptor moves the size into the ground points, the axes scaled by their
      standard deviation ``sqrt(lambda_k) v_k`` (metres), and weighs each by its share of the
      variance ``lambda_k / sum(lambda)``: equal total masses, so the EMD is a true metric,
      in metres.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from app.core.detectors.base import ChangeDetector
from app.core.emd import earth_movers_distance, euclidean_ground_distances
from app.core.parameters import ParamSpec


def principal_axes(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Eigenvalues and unit eigenvectors of the sample covariance (1/(n-1), as the paper).

    Parameters
    ----------
    points : ndarray, shape (n, 3)

    Returns
    -------
    eigenvalues : ndarray, shape (3,)
        Ascending, clipped at 0.
    eigenvectors : ndarray, shape (3, 3)
        Row ``k`` is the unit eigenvector of ``eigenvalues[k]``, sign as numpy returns it.
    """
    covariance = np.cov(points, rowvar=False)
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    return np.clip(eigenvalues, 0.0, None), eigenvectors.T


def sign_invariant_distances(
    axes_a: NDArray[np.float64], axes_b: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``min(|a - b|, |a + b|)`` for every pair of rows: the distance between lines ``±a``, ``±b``.

    Parameters
    ----------
    axes_a : ndarray, shape (k, d)
    axes_b : ndarray, shape (l, d)

    Returns
    -------
    ndarray, shape (k, l)
    """
    minus = euclidean_ground_distances(axes_a, axes_b)
    plus = np.linalg.norm(axes_a[:, None, :] + axes_b[None, :, :], axis=2)
    return np.minimum(minus, plus)


def paper_pca_emd(
    values_a: NDArray[np.float64],
    vectors_a: NDArray[np.float64],
    values_b: NDArray[np.float64],
    vectors_b: NDArray[np.float64],
) -> float:
    """The paper's eq. (2) from two eigen-decompositions.

    Parameters
    ----------
    values_a, values_b : ndarray, shape (3,)
        Eigenvalues (the weights).
    vectors_a, vectors_b : ndarray, shape (3, 3)
        Unit eigenvectors as rows (the weighted points), Euclidean ground distance.
    """
    ground = euclidean_ground_distances(vectors_a, vectors_b)
    return earth_movers_distance(values_a, values_b, ground).distance


def improved_pca_emd(
    values_a: NDArray[np.float64],
    vectors_a: NDArray[np.float64],
    values_b: NDArray[np.float64],
    vectors_b: NDArray[np.float64],
) -> float:
    """Std-scaled axes weighted by variance share, sign-invariant ground distance (metres).

    Parameters
    ----------
    values_a, values_b : ndarray, shape (3,)
        Eigenvalues.
    vectors_a, vectors_b : ndarray, shape (3, 3)
        Unit eigenvectors as rows; their signs do not matter.
    """
    total_a, total_b = float(values_a.sum()), float(values_b.sum())
    if total_a <= 0 or total_b <= 0:
        # A cloud of identical points has no axes; compare sizes only.
        return abs(np.sqrt(total_a) - np.sqrt(total_b))
    axes_a = vectors_a * np.sqrt(values_a)[:, None]
    axes_b = vectors_b * np.sqrt(values_b)[:, None]
    ground = sign_invariant_distances(axes_a, axes_b)
    return earth_movers_distance(values_a / total_a, values_b / total_b, ground).distance


def paper_pca_distance(first: NDArray[np.float64], second: NDArray[np.float64]) -> float:
    """The paper's ``d_PCA`` between two clouds (n, 3) and (m, 3)."""
    return paper_pca_emd(*principal_axes(first), *principal_axes(second))


def improved_pca_distance(first: NDArray[np.float64], second: NDArray[np.float64]) -> float:
    """The improved ``d_PCA`` between two clouds (n, 3) and (m, 3), in metres."""
    return improved_pca_emd(*principal_axes(first), *principal_axes(second))


class PcaDetector(ChangeDetector):
    """PCA-EMD change detector; see the module docstring for the two variants.

    Parameters
    ----------
    variant : {"improved", "paper"}
    random_state : int
    **params
        Only the common ones (``false_alarm_rate``, ``n_resamples``, ``calibration``,
        ``max_points``, ``voxel_size``).
    """

    method: ClassVar[str] = "pca"
    _specs: ClassVar[dict[str, ParamSpec]] = {}
    _variant_defaults: ClassVar[dict[str, dict[str, Any]]] = {"improved": {}, "paper": {}}

    def _context(
        self,
        reference: NDArray[np.float64],
        scan: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> dict[str, Any]:
        return {}

    def _score(
        self,
        first: NDArray[np.float64],
        second: NDArray[np.float64],
        context: dict[str, Any],
        rng: np.random.Generator,
        is_resample: bool,
    ) -> float:
        if self.variant == "paper":
            return paper_pca_distance(first, second)
        return improved_pca_distance(first, second)

"""k-means as scikit-learn's ``KMeans(n_clusters, n_init=1, random_state=seed).fit``, in numpy.

The GMM detector starts its EM from k-means labels.  scikit-learn's import costs ~0.8 CPU s of
a command's start-up (``import sklearn.cluster``), more than the k-means itself on a working
set, so this module runs the same algorithm with the same operations:

* the data centred on its mean, the tolerance ``mean(var(X, axis=0)) * tol`` taken before;
* greedy k-means++ seeding (``2 + int(log k)`` local trials a centre) drawing from the same
  ``RandomState`` calls in the same order, with the same distance formula
  (``-2 x.y + |x|^2 + |y|^2``, clipped at 0);
* Lloyd iterations: labels by ``argmin(|c|^2 - 2 x.c)``, centres as sequential per-cluster
  sums times ``1 / count`` (scikit-learn's one-thread order), empty clusters moved to the
  points farthest from their centres, stop when no label changes or the squared centre shift
  is within the tolerance, then one last labelling if the labels had not settled.

The labels equal scikit-learn's (``tests/core/test_detector_libraries.py`` compares them on
many sets, the detectors' working sets among them); only the last bits of intermediate sums
may differ where scikit-learn's compiled loop orders them otherwise (several OpenMP threads, its
BLAS), which would change a label only at an exact tie.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

MAX_ITER = 300
"""scikit-learn's default ``max_iter``."""
TOL = 1e-4
"""scikit-learn's default ``tol`` (relative to the mean per-axis variance)."""


def _squared_distances(
    rows: NDArray[np.float64], points: NDArray[np.float64], squared_norms: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``max(0, -2 r.p + |r|^2 + |p|^2)``: scikit-learn's ``_euclidean_distances``, shape (m, n)."""
    distances = -2 * (rows @ points.T)
    distances += np.einsum("ij,ij->i", rows, rows)[:, None]
    distances += squared_norms.reshape(1, -1)
    np.maximum(distances, 0, out=distances)
    return distances


def plusplus_centres(
    points: NDArray[np.float64],
    n_clusters: int,
    squared_norms: NDArray[np.float64],
    random_state: np.random.RandomState,
) -> NDArray[np.float64]:
    """Greedy k-means++ seeds, drawn as scikit-learn's ``_kmeans_plusplus`` draws them.

    Parameters
    ----------
    points : ndarray, shape (n, d)
        Centred points.
    n_clusters : int
    squared_norms : ndarray, shape (n,)
        ``|x|^2`` of each point.
    random_state : numpy.random.RandomState
        Advanced exactly as scikit-learn advances it.

    Returns
    -------
    ndarray, shape (n_clusters, d)
    """
    n_samples = points.shape[0]
    weights = np.ones(n_samples)
    centres = np.empty((n_clusters, points.shape[1]))
    n_local_trials = 2 + int(np.log(n_clusters))
    centre_id = random_state.choice(n_samples, p=weights / weights.sum())
    centres[0] = points[centre_id]
    closest = _squared_distances(centres[0, np.newaxis], points, squared_norms)
    potential = closest @ weights
    for index in range(1, n_clusters):
        draws = random_state.uniform(size=n_local_trials) * potential
        candidates = np.searchsorted(np.cumsum(weights * closest), draws)
        np.clip(candidates, None, closest.size - 1, out=candidates)
        to_candidates = _squared_distances(points[candidates], points, squared_norms)
        np.minimum(closest, to_candidates, out=to_candidates)
        potentials = to_candidates @ weights.reshape(-1, 1)
        best = np.argmin(potentials)
        potential = potentials[best]
        closest = to_candidates[best]
        centres[index] = points[candidates[best]]
    return centres


def _assign(points: NDArray[np.float64], centres: NDArray[np.float64]) -> NDArray[np.intp]:
    """Nearest centre of each point by ``|c|^2 - 2 x.c`` (first on ties), shape (n,)."""
    centre_norms = np.einsum("ij,ij->i", centres, centres)
    return np.argmin(centre_norms[None, :] + -2.0 * (points @ centres.T), axis=1)


def _update(
    points: NDArray[np.float64], centres: NDArray[np.float64], labels: NDArray[np.intp]
) -> NDArray[np.float64]:
    """New centres: per-cluster means, empty clusters moved to the farthest points, (k, d)."""
    n_clusters = centres.shape[0]
    sums = np.stack(
        [
            np.bincount(labels, weights=points[:, axis], minlength=n_clusters)
            for axis in range(points.shape[1])
        ],
        axis=1,
    )
    counts = np.bincount(labels, minlength=n_clusters).astype(np.float64)
    empty = np.flatnonzero(counts == 0)
    if empty.size:
        distances = ((points - centres[labels]) ** 2).sum(axis=1)
        farthest = np.argpartition(distances, -empty.size)[: -empty.size - 1 : -1]
        if np.max(distances) != 0:
            for cluster, far in zip(empty, farthest, strict=True):
                old = labels[far]
                sums[old] -= points[far]
                sums[cluster] = points[far]
                counts[cluster] = 1.0
                counts[old] -= 1.0
    largest = int(np.argmax(counts))
    for cluster in range(n_clusters):
        if counts[cluster] > 0:
            sums[cluster] *= 1.0 / counts[cluster]
        else:  # as scikit-learn: an empty cluster sits on the largest one
            sums[cluster] = sums[largest]
    return sums


def kmeans_labels(
    points: NDArray[np.floating],
    n_clusters: int,
    random_state: np.random.RandomState,
    *,
    max_iter: int = MAX_ITER,
    tol: float = TOL,
) -> NDArray[np.intp]:
    """Labels of ``KMeans(n_clusters, n_init=1, random_state=random_state).fit(points)``.

    Parameters
    ----------
    points : array_like, shape (n, d)
        ``n >= n_clusters``; converted to float64.
    n_clusters : int
    random_state : numpy.random.RandomState
        Advanced as scikit-learn's fit advances it.
    max_iter : int
        Lloyd iterations at most.
    tol : float
        Stop when the summed squared centre shift is within ``tol`` times the mean variance.

    Returns
    -------
    ndarray, shape (n,)
        Cluster of each point, ``0 .. n_clusters - 1``.
    """
    points = np.array(points, dtype=np.float64, order="C")
    if points.ndim != 2 or points.shape[0] < n_clusters or n_clusters < 1:
        raise ValueError(
            f"k-means needs an (n, d) array with n >= n_clusters >= 1, got shape "
            f"{points.shape} and n_clusters={n_clusters}"
        )
    tolerance = float(np.mean(np.var(points, axis=0)) * tol) if tol else 0.0
    points -= points.mean(axis=0)
    squared_norms = np.einsum("ij,ij->i", points, points)
    centres = plusplus_centres(points, n_clusters, squared_norms, random_state)
    labels_old = np.full(points.shape[0], -1, dtype=np.intp)
    settled = False
    for _ in range(max_iter):
        labels = _assign(points, centres)
        new_centres = _update(points, centres, labels)
        shift = np.sqrt(((new_centres - centres) ** 2).sum(axis=1))
        centres = new_centres
        if np.array_equal(labels, labels_old):
            settled = True
            break
        if (shift**2).sum() <= tolerance:
            break
        labels_old = labels
    if not settled:
        labels = _assign(points, centres)
    return labels

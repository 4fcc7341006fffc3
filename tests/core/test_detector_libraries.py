"""The detectors without scikit-learn, scipy.stats or POT: their numpy k-means gives
scikit-learn's ``KMeans(n_init=1)`` labels, their t quantile is scipy.stats', and a detection
imports none of the three (the EMD against POT: tests/core/test_emd.py)."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest
from sklearn.cluster import KMeans
from threadpoolctl import threadpool_limits

from app.core.detectors.calibration import threshold_from_null
from app.core.detectors.kmeans import kmeans_labels


def random_set(kind: str, rng: np.random.Generator) -> np.ndarray:
    """A point set (n, 3) of one of the shapes k-means meets: blobs, planes, duplicates."""
    n = int(rng.integers(20, 3000))
    if kind == "anisotropic":
        return rng.normal(size=(n, 3)) * rng.uniform(0.05, 10.0, 3)
    if kind == "planes":  # points on a few horizontal planes, as in a room's floor and ceiling
        points = rng.uniform(-5.0, 5.0, (n, 3))
        points[:, 2] = np.round(points[:, 2])
        return points
    return np.round(rng.normal(size=(n, 3)) * 2.0)  # many duplicates: ties, empty clusters


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("kind", ["anisotropic", "planes", "duplicates"])
def test_labels_equal_scikit_learns(kind: str, threads: int) -> None:
    rng = np.random.default_rng(["anisotropic", "planes", "duplicates"].index(kind))
    differing = []
    with threadpool_limits(threads), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scikit-learn: fewer distinct clusters than asked
        for trial in range(40):
            points = random_set(kind, rng)
            n_clusters = int(rng.integers(1, 13))
            seed = int(rng.integers(0, 2**32))
            expected = KMeans(n_clusters, n_init=1, random_state=np.random.RandomState(seed))
            expected_labels = expected.fit(points).labels_
            labels = kmeans_labels(points, n_clusters, np.random.RandomState(seed))
            if not np.array_equal(labels, expected_labels):
                differing.append((trial, points.shape[0], n_clusters))
    assert differing == []


def test_the_empty_cluster_case_is_exercised() -> None:
    # 8 clusters over 5 distinct places: the case scikit-learn relocates and warns about
    places = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [0, 0, 4], [4, 4, 4]], dtype=float)
    points = np.repeat(places, 40, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        expected = KMeans(8, n_init=1, random_state=np.random.RandomState(3)).fit(points)
    labels = kmeans_labels(points, 8, np.random.RandomState(3))
    assert np.array_equal(labels, expected.labels_)
    assert np.unique(labels).size == 5


@pytest.mark.parametrize("n_clusters", [0, 11])
def test_too_few_points_or_no_clusters_are_refused(n_clusters: int) -> None:
    with pytest.raises(ValueError, match="n >= n_clusters >= 1"):
        kmeans_labels(np.zeros((10, 3)), n_clusters, np.random.RandomState(0))


def test_a_detection_imports_neither_scikit_learn_nor_pot_nor_scipy_stats() -> None:
    code = (
        "import sys, numpy as np\n"
        "from app.core.detectors import make_detector\n"
        "rng = np.random.default_rng(0)\n"
        "reference = rng.uniform(0, 4, (3000, 3))\n"
        "scan = reference + rng.normal(0, 0.01, reference.shape)\n"
        "for method in ('gmm', 'pca'):\n"
        "    for variant in ('improved', 'paper'):\n"
        "        make_detector(method, variant, max_points=1000, n_resamples=4).detect(\n"
        "            reference, scan)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('sklearn', 'ot')\n"
        "             or m.startswith('scipy.stats')))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300
    )
    assert result.stdout.strip() == "[]"


def test_the_thresholds_t_quantile_is_scipy_stats() -> None:
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(5)
    for size in (2, 3, 8, 20, 101, 2000):
        null = np.exp(rng.normal(-3.0, 1.0, size))
        for rate in (0.001, 0.01, 0.05, 0.3):
            decision = threshold_from_null(null, rate)
            expected = float(stats.t.ppf(1.0 - rate, df=size - 1))
            assert decision.t_quantile == expected

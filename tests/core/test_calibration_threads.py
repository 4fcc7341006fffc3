"""The calibration's resamples scored on two threads (app.core.detectors.calibration)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from app.core.detectors import calibration, make_detector
from app.core.detectors.base import ChangeDetector


@pytest.mark.parametrize("scheme", ["paired", "permutation"])
def test_resamples_scored_on_two_threads_give_the_one_thread_values(scheme):
    """All resamples drawn first, in the generator's order, then scored on two threads: the
    same null values in the same places as drawing and scoring one after the other."""
    rng = np.random.default_rng(11)
    reference = rng.normal(size=(600, 3))
    scan = rng.normal(size=(500, 3)) + 0.05
    scoring_threads: set[str] = set()

    def score(first, second):
        scoring_threads.add(threading.current_thread().name)
        return float(np.linalg.norm(first.mean(axis=0) - second.mean(axis=0)) + first.shape[0])

    values = {
        threads: calibration.null_distribution(
            reference,
            scan,
            score,
            scheme=scheme,
            n_resamples=12,
            rng=np.random.default_rng(5),
            pairing_voxel=0.5,
            threads=threads,
        )
        for threads in (1, 2)
    }
    np.testing.assert_array_equal(values[2], values[1])
    assert len(np.unique(values[1])) > 1
    assert any(name.startswith("chunks") for name in scoring_threads)


def test_only_a_score_that_draws_nothing_is_spread_over_threads(monkeypatch):
    """The GMM's score (EM from a seed or a shared start, then the EMD) draws nothing from the
    calibration's generator; a detector whose score might keeps one thread."""
    assert make_detector("gmm", "improved")._score_draws is False
    assert make_detector("gmm", "paper")._score_draws is False
    assert ChangeDetector._score_draws is True
    asked: list[int] = []
    null_distribution = calibration.null_distribution

    def recorded(*args, threads=1, **kwargs):
        asked.append(threads)
        return null_distribution(*args, threads=threads, **kwargs)

    monkeypatch.setattr(calibration, "null_distribution", recorded)
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    rng = np.random.default_rng(3)
    reference, scan = rng.normal(size=(400, 3)), rng.normal(size=(400, 3))
    two = make_detector("gmm", "improved", n_resamples=6).detect(reference, scan)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    one = make_detector("gmm", "improved", n_resamples=6).detect(reference, scan)
    assert asked == [2, 1]
    assert two == one

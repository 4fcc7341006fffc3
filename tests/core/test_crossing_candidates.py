"""Crossing surfaces: the low band of an object standing on ground both epochs saw.

A map's change threshold holds the alignment residual, the spread of the offsets between the
surfaces both epochs have.  On a real mobile-mapping pair the ground's own level changes and
drift take it to 6 cm and the threshold to 28 cm: the lowest 10-28 cm of a removed fence (the
MLS bike-parking pair) was no candidate.  A point whose own surface crosses the other epoch's
nearest surface is judged by the noise alone (``surface_levels.crossing_candidates``).
"""

from __future__ import annotations

import numpy as np

from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes

STEP = 0.05
FENCE_X = 0.3


def fence_on_bent_ground(seed: int, *, removed: bool = True):
    """Reference: ground and a 1 m fence panel (3 m long, across x = 0.3); scan: the ground
    bent by up to 8 cm (level at the fence), with the fence gone when ``removed``.  Returns the
    two clouds (shapes (n, 3), (m, 3)) and the reference's fence points' indices."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(-4, 4, STEP), np.arange(-3, 3, STEP), indexing="ij")
    ground = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    ground[:, :2] += rng.uniform(-STEP / 2, STEP / 2, (ground.shape[0], 2))
    along, up = np.meshgrid(
        np.arange(-1.5, 1.5, STEP), np.arange(STEP / 2, 1.0, STEP), indexing="ij"
    )
    fence = np.column_stack([np.full(along.size, FENCE_X), along.ravel(), up.ravel()])
    bare = ground[np.abs(ground[:, 0] - FENCE_X) >= STEP / 2]
    reference = np.vstack([bare, fence])
    scan = ground.copy() if removed else np.vstack([bare, fence])
    scan[:, 2] += 0.08 * np.sin(2.0 * scan[:, 0])
    reference += rng.normal(0.0, 0.005, reference.shape)
    scan += rng.normal(0.0, 0.005, scan.shape)
    return reference, scan, np.arange(bare.shape[0], reference.shape[0])


def test_a_removed_fence_low_band_is_changed_under_a_high_alignment_threshold():
    for seed in (0, 1):
        reference, scan, fence = fence_on_bent_ground(seed)
        found = localise_changes(reference, scan)
        assert found.parameters["change_threshold"] > 0.25  # the bent ground's residual
        height = reference[fence, 2]
        low_band = fence[(height > 0.12) & (height < 0.25)]
        changed = found.reference_label[low_band] == LABEL_CHANGED
        # on main 0-25 %: the band under the 28 cm threshold was no candidate
        assert changed.mean() >= 0.6
        assert np.mean(found.reference_label[fence] == LABEL_CHANGED) >= 0.8
        ground = np.setdiff1d(np.arange(reference.shape[0]), fence)
        assert np.count_nonzero(found.reference_label[ground] == LABEL_CHANGED) == 0
        assert np.count_nonzero(found.scan_label == LABEL_CHANGED) == 0


def test_a_fence_standing_in_both_epochs_is_no_change():
    reference, scan, _ = fence_on_bent_ground(2, removed=False)
    found = localise_changes(reference, scan)
    assert found.regions == []

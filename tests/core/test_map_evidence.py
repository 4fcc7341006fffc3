"""The map test on fused maps without sensor positions (issue 29): removals whose place the other
epoch covered are changes, patches of surfaces that continue unmoved in the other epoch are
coverage differences, listed as uncertain regions and never counted."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.localise import localise_changes
from app.core.localise.visibility import LABEL_CHANGED, LABEL_UNOBSERVED

SPACING = 0.03


def _plane(rng, origin, first, second, spacing=SPACING, noise=0.002):
    """Points on a rectangle (origin + s * first + t * second), jittered, with noise."""
    first, second = np.asarray(first, float), np.asarray(second, float)
    n_s = max(2, int(np.linalg.norm(first) / spacing))
    n_t = max(2, int(np.linalg.norm(second) / spacing))
    s, t = np.meshgrid((np.arange(n_s) + 0.5) / n_s, (np.arange(n_t) + 0.5) / n_t)
    s = s.ravel() + rng.uniform(-0.3, 0.3, s.size) / n_s
    t = t.ravel() + rng.uniform(-0.3, 0.3, t.size) / n_t
    points = np.asarray(origin, float) + s[:, None] * first + t[:, None] * second
    normal = np.cross(first, second)
    normal /= np.linalg.norm(normal)
    return points + rng.normal(0.0, noise, (points.shape[0], 1)) * normal


def _box(rng, low, high):
    """The five visible faces of a box standing on the floor (no bottom)."""
    low, high = np.asarray(low, float), np.asarray(high, float)
    size = high - low
    x, y, z = np.diag(size)
    return np.vstack(
        [
            _plane(rng, [low[0], low[1], high[2]], x, y),
            _plane(rng, low, x, z),
            _plane(rng, [low[0], high[1], low[2]], x, z),
            _plane(rng, low, y, z),
            _plane(rng, [high[0], low[1], low[2]], y, z),
        ]
    )


def _room(rng, *, floor_hole=None, box=None, ceiling_to=6.0):
    """A 6 x 4 x 2.5 m room's floor, two walls and ceiling (to x = ``ceiling_to``), sampled
    as a fused map is: uniformly, with what a box hides of the floor missing."""
    floor = _plane(rng, [0, 0, 0], [6, 0, 0], [0, 4, 0])
    keep = np.ones(floor.shape[0], bool)
    for hole in [h for h in (floor_hole, box) if h is not None]:
        low, high = hole
        keep &= ~(
            (floor[:, 0] > low[0])
            & (floor[:, 0] < high[0])
            & (floor[:, 1] > low[1])
            & (floor[:, 1] < high[1])
        )
    parts = [
        floor[keep],
        _plane(rng, [0, 0, 0], [6, 0, 0], [0, 0, 2.5]),
        _plane(rng, [0, 0, 0], [0, 4, 0], [0, 0, 2.5]),
        _plane(rng, [0, 0, 2.5], [ceiling_to, 0, 0], [0, 4, 0]),
    ]
    if box is not None:
        parts.append(_box(rng, box[0], box[1]))
    return np.vstack(parts)


CHAIR = ([2.5, 1.5, 0.0], [3.0, 2.0, 0.9])


def test_a_removed_object_whose_floor_the_scan_saw_is_removed():
    rng = np.random.default_rng(0)
    reference = _room(rng, box=CHAIR)
    scan = _room(rng)
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["reference_visibility"] == "maps"
    inside = np.all((reference > CHAIR[0]) & (reference < CHAIR[1]), axis=1) & (
        reference[:, 2] > 0.15
    )
    changed = localisation.reference_label[inside] == LABEL_CHANGED
    assert changed.mean() >= 0.9
    removed = [region for region in localisation.regions if region.kind == "removed"]
    assert len(removed) == 1 and removed[0].evidence in {"seen_empty", "surface_moved"}
    assert 0.0 < removed[0].confidence <= 1.0


def test_an_added_object_is_added():
    rng = np.random.default_rng(1)
    reference = _room(rng)
    scan = _room(rng, box=CHAIR)
    localisation = localise_changes(reference, scan)
    added = [region for region in localisation.regions if region.kind == "added"]
    assert len(added) == 1 and added[0].n_points > 300
    # the floor the box now hides, if reported, is that surface moved up to the box's top
    for region in localisation.regions:
        if region.kind == "removed":
            assert region.evidence == "surface_moved" and region.bbox_max[2] < 0.05


def test_coverage_differences_on_continuing_surfaces_are_uncertain_not_changed():
    # the scan's path reached neither a 1.2 x 1 m patch of the floor nor the ceiling's far end
    rng = np.random.default_rng(2)
    reference = _room(rng)
    scan = _room(rng, floor_hole=([3.5, 1.0], [4.7, 2.0]), ceiling_to=4.5)
    localisation = localise_changes(reference, scan)
    assert localisation.regions == []
    assert not np.any(localisation.reference_label == LABEL_CHANGED)
    unobserved = localisation.reference_label == LABEL_UNOBSERVED
    in_hole = (
        (reference[:, 0] > 3.7)
        & (reference[:, 0] < 4.5)
        & (reference[:, 1] > 1.2)
        & (reference[:, 1] < 1.8)
        & (reference[:, 2] < 0.05)
    )
    assert unobserved[in_hole].mean() >= 0.9
    assert len(localisation.uncertain_regions) >= 2
    assert {region.evidence for region in localisation.uncertain_regions} == {"no_coverage"}
    assert localisation.parameters["n_uncertain_regions"] == len(localisation.uncertain_regions)


def test_a_moved_object_is_a_surface_moved():
    rng = np.random.default_rng(3)
    moved = ([4.0, 1.5, 0.0], [4.5, 2.0, 0.9])
    reference = _room(rng, box=CHAIR)
    scan = _room(rng, box=moved)
    localisation = localise_changes(reference, scan)
    assert {region.kind for region in localisation.regions} == {"added", "removed"}
    assert {region.evidence for region in localisation.regions} == {"surface_moved"}
    old_place = np.all((reference > CHAIR[0]) & (reference < CHAIR[1]), axis=1)
    new_place = np.all((scan > moved[0]) & (scan < moved[1]), axis=1)
    assert (localisation.reference_label[old_place & (reference[:, 2] > 0.15)] == 1).mean() > 0.9
    assert (localisation.scan_label[new_place & (scan[:, 2] > 0.15)] == 1).mean() > 0.9


@pytest.mark.parametrize("test", ["coverage", "maps"])
def test_the_coverage_test_stays_available(test):
    rng = np.random.default_rng(4)
    reference = _room(rng, box=CHAIR)
    scan = _room(rng)
    localisation = localise_changes(reference, scan, origin_free_test=test)
    assert localisation.parameters["reference_visibility"] == test

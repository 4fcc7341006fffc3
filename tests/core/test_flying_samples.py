"""Flying samples of a dense fused map are left out of the comparison (``flying_samples``)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

import app.core.localise.flying_samples as flying_module
from app.core.datasets.maps import MapPair, map_pair
from app.core.labels import LABEL_CHANGED, LABEL_UNOBSERVED
from app.core.localise import EpochCloud, localise_changes
from app.core.localise.flying_samples import without_flying_samples
from app.core.registration_result import apply_transform


def _plane(
    rng: np.random.Generator, extent: tuple[float, float, float, float], axis: int, level: float
) -> NDArray[np.float64]:
    """A jittered 1 cm grid on the plane ``axis = level`` over ``extent`` (the other two
    axes' lows and highs), shape (n, 3)."""
    across = [other for other in range(3) if other != axis]
    first, second = np.meshgrid(
        np.arange(extent[0], extent[1], 0.01), np.arange(extent[2], extent[3], 0.01)
    )
    points = np.zeros((first.size, 3))
    points[:, across[0]] = first.ravel() + rng.uniform(-0.003, 0.003, first.size)
    points[:, across[1]] = second.ravel() + rng.uniform(-0.003, 0.003, first.size)
    points[:, axis] = level
    return points


FLYERS = 200
"""Flying samples behind a box's 0.5 m rim: as sparse as the RGB-D rooms' (a median of one other
own point within 4 median spacings, as the drifting rooms' flying pixels the test finds)."""


def _room_with_flyers(seed: int, side: int, flyers: int = FLYERS) -> tuple[NDArray, int]:
    """A dense map of a floor, a wall and a 0.5 m box on it (3 mm noise) and ``flyers``
    flying samples scattered from the box top's rim on ``side`` (+1 or -1 along y) down
    towards the floor behind it; the flying samples last.  Returns (points, surface count)."""
    rng = np.random.default_rng(seed)
    parts = [
        _plane(rng, (0.0, 2.0, 0.0, 2.0), 2, 0.0),
        _plane(rng, (0.0, 2.0, 0.0, 1.0), 1, 2.0),
        _plane(rng, (0.75, 1.25, 0.75, 1.25), 2, 0.5),
    ]
    for axis, level in ((0, 0.75), (0, 1.25), (1, 0.75), (1, 1.25)):
        parts.append(_plane(rng, (0.75, 1.25, 0.0, 0.5), axis, level))
    surface = np.vstack(parts)
    rim = np.column_stack(
        [
            rng.uniform(0.75, 1.25, flyers),
            np.full(flyers, 1.0 + 0.25 * side),
            np.full(flyers, 0.5),
        ]
    )
    behind = rim + np.column_stack(
        [
            rng.normal(0.0, 0.1, flyers),
            side * rng.uniform(0.3, 0.75, flyers),
            -rng.uniform(0.2, 0.5, flyers),
        ]
    )
    flying = rim + rng.uniform(0.1, 0.9, (flyers, 1)) * (behind - rim)
    points = np.vstack([surface, flying]) + rng.normal(0.0, 0.003, (len(surface) + flyers, 3))
    return points, len(surface)


def test_flying_samples_are_found_and_surfaces_kept() -> None:
    points, n_surface = _room_with_flyers(1, side=1)
    other = EpochCloud(points[:n_surface])  # the other epoch: the same room, no flyers
    subset, _, (kept, _) = without_flying_samples(EpochCloud(points), other, 10, 1)
    assert kept is not None
    flying = np.ones(len(points), dtype=bool)
    flying[kept] = False
    assert not flying[:n_surface].any()  # no point of the floor, wall or box
    assert flying[n_surface:].mean() > 0.7
    assert len(subset.points) == len(kept)  # type: ignore[arg-type]


def test_no_flying_samples_on_a_sparse_map_or_with_origins() -> None:
    points, _ = _room_with_flyers(1, side=1)
    sparse = EpochCloud(points[::9])  # 3 cm apart
    with_origin = EpochCloud(points, origin=np.array([1.0, -1.0, 1.5]))
    assert without_flying_samples(sparse, with_origin, 10, 2)[2] == (None, None)


def test_each_epochs_flying_samples_are_no_change() -> None:
    """Each epoch's flying samples in the air behind another rim of the same box: without the
    test, 337 points changed in regions; now most are unobserved, with no region."""
    reference, n_reference = _room_with_flyers(1, side=1)
    scan, n_scan = _room_with_flyers(2, side=-1)
    result = localise_changes(reference, scan)
    changed = np.count_nonzero(result.reference_label == LABEL_CHANGED) + np.count_nonzero(
        result.scan_label == LABEL_CHANGED
    )
    assert changed < FLYERS // 2
    assert result.parameters["flying_samples"][0] > FLYERS // 2
    assert np.all(result.reference_label[:n_reference] != LABEL_UNOBSERVED)
    unobserved = result.reference_label == LABEL_UNOBSERVED
    assert np.all(result.reference_region[unobserved] == -1)
    assert np.all(np.isnan(result.reference_distance[unobserved]))
    for number, region in enumerate(result.regions):  # indices of the whole clouds
        label, region_of = (
            (result.reference_label, result.reference_region)
            if region.kind == "removed"
            else (result.scan_label, result.scan_region)
        )
        assert np.all(region_of[region.point_indices] == number)
        assert np.all(label[region.point_indices] == LABEL_CHANGED)
    assert len(result.reference_label) == len(reference)
    assert len(result.scan_label) == n_scan + FLYERS


def _changed_regions(pair: MapPair, monkeypatch: pytest.MonkeyPatch, test: bool) -> int:
    """Regions of ``pair`` (scan moved by its true transform), with the flying-sample test or
    without it (no point flying)."""
    if not test:
        monkeypatch.setattr(
            flying_module, "flying_samples", lambda points, *_: np.zeros(len(points), bool)
        )
    scan = apply_transform(pair.scan.points, pair.true_transform)
    regions = len(localise_changes(pair.reference.points, scan).regions)
    monkeypatch.undo()
    return regions


def test_a_thin_part_the_other_map_holds_is_no_flying_sample(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Unchanged RGB-D room 104 (no drift): the scan saw a chair leg in 4 samples, the
    reference in 169.  Alone in the air, the scan's 4 looked like flying pixels; taken out, 84
    of the reference's leg were called removed (and 55 scan points added elsewhere: the same
    the other way).  A sample of the other map next to a point keeps it: the test adds no
    region on an unchanged clean room."""
    pair = map_pair("rgbd", change="none", random_state=104)
    assert _changed_regions(pair, monkeypatch, True) <= _changed_regions(pair, monkeypatch, False)


def test_a_sparse_thin_part_is_no_flying_sample() -> None:
    """A chair's four 3 cm legs added in the scan, sampled every 3 cm along them in a 1 cm
    map (RGB-D room 203's turned chair, seen from afar): sparse, and not flat at 10
    neighbours, as a flying scatter; but each sample has its leg's next samples within 4
    median spacings.  The test without that (s23) took 101 of the 240 (203's chair: 13 %
    changed)."""
    rng = np.random.default_rng(3)
    room, _ = _room_with_flyers(1, side=1, flyers=0)
    step, half = 0.03, 0.015
    heights = np.arange(0.02, 0.45, step)
    faces = []
    for x, y in ((0.3, 0.3), (0.3, 0.7), (0.7, 0.3), (0.7, 0.7)):
        for dx, dy in ((-half, 0.0), (half, 0.0), (0.0, -half), (0.0, half)):
            along = heights + rng.uniform(0.0, step, heights.size)
            faces.append(
                np.column_stack(
                    [np.full(heights.size, x + dx), np.full(heights.size, y + dy), along]
                )
            )
    legs = np.vstack(faces) + rng.normal(0.0, 0.003, (len(faces) * heights.size, 3))
    scan = np.vstack([room, legs])
    _, _, (_, kept) = without_flying_samples(EpochCloud(room), EpochCloud(scan), 10, 1)
    assert kept is None or np.isin(np.arange(len(room), len(scan)), kept).all()


def _kept_share(points: NDArray, other: NDArray, rows: slice) -> float:
    """Share of ``points[rows]`` the test keeps, ``other`` the other epoch's map."""
    _, _, (kept, _) = without_flying_samples(EpochCloud(points), EpochCloud(other), 10, 1)
    if kept is None:
        return 1.0
    return float(np.isin(np.arange(len(points))[rows], kept).mean())


@pytest.mark.xfail(
    strict=True,
    reason="s25 rgbd503: a flying pixel off a sparse surface's plane is planar at k by its "
    "neighbours; an off-plane rule (> 2-3 median spacings) found these but also a sparse "
    "solid part's few samples next to a surface (clean RGB-D room 104: 103 -> 205 false)",
)
def test_a_flying_pixel_off_a_sparse_surface_is_a_flying_sample() -> None:
    """Flying pixels 3.5-6 cm in front of a far board sampled every 6 cm in a 1 cm map: each
    isolated, its 10 neighbours the board's samples over ~10 cm, so planar at 10 neighbours
    (surface variation ~0.02-0.07, as 4 of the 6 scan flying pixels that kept drifting RGB-D
    room 503's turned chair unchanged).  It lies off its neighbours' plane, the board's
    samples on it; the test keeps 14 of the 40 (an off-plane rule, withdrawn, kept none)."""
    rng = np.random.default_rng(5)
    room, _ = _room_with_flyers(5, side=1, flyers=0)
    across, up = np.meshgrid(np.arange(0.2, 1.0, 0.06), np.arange(0.6, 1.4, 0.06))
    board = np.column_stack([np.full(across.size, 1.9), across.ravel(), up.ravel()])
    board += rng.normal(0.0, 0.002, board.shape)
    flyers = np.column_stack(
        [1.9 - rng.uniform(0.035, 0.06, 40), rng.uniform(0.3, 0.9, 40), rng.uniform(0.7, 1.3, 40)]
    )
    points = np.vstack([room, board, flyers])
    surface = np.vstack([room, board])
    assert _kept_share(points, surface, slice(len(surface), None)) < 0.1
    assert _kept_share(points, surface, slice(0, len(surface))) == 1.0


def test_flying_pixels_of_both_epochs_do_not_keep_each_other() -> None:
    """Both epochs' cameras saw the same silhouette, so each map has flying pixels in the same
    air, a few next to the other's (drifting RGB-D room 503: such scan pixels kept points of
    the turned chair unchanged).  A sample of the other epoch that is itself a flying
    candidate is no surface both saw: with each flying sample behind the box's rim 0.5-1 cm
    from its twin of the other epoch, the twins kept all of each other (s24); now 63 % are
    taken out (the candidates of one pass), and no surface point."""
    rng = np.random.default_rng(7)
    reference, n_surface = _room_with_flyers(7, side=1)
    offset = rng.normal(size=(FLYERS, 3))
    offset *= rng.uniform(0.005, 0.01, (FLYERS, 1)) / np.linalg.norm(offset, axis=1, keepdims=True)
    scan = reference.copy()
    scan[n_surface:] += offset
    assert _kept_share(reference, scan, slice(n_surface, None)) < 0.5  # s24: 1.0
    assert _kept_share(scan, reference, slice(n_surface, None)) < 0.5
    assert _kept_share(reference, scan, slice(0, n_surface)) == 1.0


def test_a_flying_pixel_the_other_map_holds_on_a_line_of_sight_is_a_flying_sample() -> None:
    """The other map's surface where this map has flying pixels (a turned chair's old back in
    the fan behind a box's rim: drifting RGB-D rooms 503 / 303, where 2 + 9 such scan pixels
    kept 45 / 308 of the chair's reference points unchanged).  A sample of the other map within
    one median spacing kept each of them (s24: a thin part both maps saw); but each lies on a
    line from the floor behind past the rim to where a camera could stand, both maps empty
    along it: taken out (on main none of them), and no surface point."""
    rng = np.random.default_rng(11)
    points, n_surface = _room_with_flyers(11, side=1)
    across, up = np.meshgrid(np.arange(0.5, 1.5, 0.01), np.arange(0.0, 0.5, 0.01))
    back = np.column_stack([across.ravel(), np.full(across.size, 1.5), up.ravel()])
    back += rng.normal(0.0, 0.002, back.shape)
    other = np.vstack([points[:n_surface], back])
    flyers = points[n_surface:]
    held = np.abs(flyers[:, 1] - 1.5) < 0.012  # most within OTHER_NEAR of the back's samples
    assert held.sum() >= 10
    _, _, (kept, _) = without_flying_samples(EpochCloud(points), EpochCloud(other), 10, 1)
    assert kept is not None
    taken = ~np.isin(np.arange(len(points)), kept)
    assert not taken[:n_surface].any()
    assert taken[n_surface:][held].sum() >= 8  # main: 4 of 12 (those the back does not hold)


def test_a_flat_flying_pixel_on_lines_of_sight_is_a_flying_sample() -> None:
    """Drifting RGB-D room 503 (a chair turned in place): 8 flying pixels of the reference,
    18-55 cm from where their rays met a surface, lie within 10 cm of the scan's turned chair
    and held its points (27 of its 78 scored points unchanged, 63 % found).  Alone in the air,
    the 10 neighbours of some are a far surface's samples: flat at k, so no scatter, and no
    sample of the scan lies within a median spacing of them, but one within 6 (they hold its
    points within the change distance).  Main takes 5 of the 8 (s28 took all 8 with every flat
    isolated sample tried, and lost drift 403's chair: s29 tries only those holding a sample)."""
    pair = map_pair("rgbd", change="rotated", random_state=503, realism="drift")
    scan = apply_transform(pair.scan.points, pair.true_transform)
    reference = pair.reference.points
    _, _, (kept, _) = without_flying_samples(EpochCloud(reference), EpochCloud(scan), 10, 1)
    assert kept is not None
    chair = scan[(pair.scan_change == 0) & pair.scan_changed & pair.scan_scored]
    offset = np.linalg.norm(reference - pair.reference_exact, axis=1)
    near = np.linalg.norm(reference[:, None, :] - chair[None], axis=2).min(axis=1) < 0.1
    flying = np.flatnonzero(near & (offset > 0.05))
    assert flying.size == 8
    assert not np.isin(flying, kept).any()

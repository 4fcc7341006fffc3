"""The 3D view draws a job's uncertain regions apart from its changes (issue 29), no browser.

Rules checked: the ``uncertain_regions`` a job row stores (evidence ``no_coverage``) reach the
scene data as boxes of their own, in the scene's local frame, never among the regions (not
counted, not paired into moved objects, not relabelled); malformed entries and jobs stored
before they existed give none; each is drawn as a grey dashed outline (gaps on every edge,
unlike a change's solid box), hidden with its toggle or outside the height clip; its button
names its evidence and that it is not counted.
"""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import viser

from app.viewer.loading import job_uncertain_regions
from app.viewer.regions_display import box_edges, pair_moved
from app.viewer.scene import build_scene_data
from app.viewer.uncertain_display import (
    UNCERTAIN_COLOUR,
    dashed_box_edges,
    draw_uncertain_regions,
    uncertain_label,
)

OFFSET = np.array([500_000.0, 4_200_000.0, 30.0])


def box(kind: str, low: list[float], high: list[float], n_points: int, **extra: object) -> dict:
    low_array, high_array = np.add(low, OFFSET), np.add(high, OFFSET)
    return {
        "kind": kind,
        "n_points": n_points,
        "centroid": ((low_array + high_array) / 2).tolist(),
        "bbox_min": low_array.tolist(),
        "bbox_max": high_array.tolist(),
        "mean_distance": 0.3,
        "max_distance": 0.6,
        **extra,
    }


CHAIR = {"id": "r1", **box("removed", [1, 1, 0], [1.6, 1.6, 1], 800, evidence="seen_empty")}
FLOOR_PATCH = box("added", [2.0, 1.0, 0.0], [3.0, 2.0, 0.02], 240, evidence="no_coverage")
"""A floor patch only the scan's path reached, next to the chair: added-sized, close by."""
CEILING_PATCH = box("removed", [0.0, 0.0, 2.5], [1.0, 1.0, 2.6], 90, confidence=0.4)


def job_row(uncertain: object) -> SimpleNamespace:
    return SimpleNamespace(uncertain_regions=uncertain)


def scene(uncertain: list[dict]):
    rng = np.random.default_rng(1)
    points = rng.uniform((0, 0, 0), (4, 3, 2.6), (2000, 3)) + OFFSET
    return build_scene_data(points, points, regions=[CHAIR], uncertain_regions=uncertain)


def test_uncertain_regions_reach_the_scene_apart_from_the_changes() -> None:
    malformed = ["junk", {"kind": "added", "n_points": 3}, {**FLOOR_PATCH, "bbox_max": [1, 2]}]
    stored = job_uncertain_regions(job_row([FLOOR_PATCH, *malformed, CEILING_PATCH]))

    data = scene(stored)

    assert [region.kind for region in data.regions] == ["removed"]
    assert [(box.kind, box.evidence) for box in data.uncertain] == [
        ("added", "no_coverage"),
        ("removed", "no_coverage"),
    ]
    floor = data.uncertain[0]
    np.testing.assert_allclose(
        np.add(floor.center_local, data.origin),
        [2.5 + OFFSET[0], 1.5 + OFFSET[1], OFFSET[2] + 0.01],
    )
    assert pair_moved(data.regions, within=10.0) == ()  # the floor patch is no moved chair
    record = data.to_json_dict()
    assert len(record["regions"]) == 1 and len(record["uncertain_regions"]) == 2
    assert uncertain_label(floor) == "U1 added · 240 pts · not covered · not counted"
    assert uncertain_label(data.uncertain[1]).endswith("not covered 40 % · not counted")
    assert job_uncertain_regions(job_row(None)) == []  # a job stored before they existed
    assert scene([]).uncertain == ()


def test_each_is_drawn_as_a_grey_dashed_outline_behind_its_toggle() -> None:
    data = scene(job_uncertain_regions(job_row([FLOOR_PATCH, CEILING_PATCH])))
    floor, ceiling = data.uncertain
    dashes = dashed_box_edges(floor.center_local, floor.dimensions)
    solid = box_edges(floor.center_local, floor.dimensions)
    drawn = np.linalg.norm(dashes[:, 1] - dashes[:, 0], axis=1).sum()
    outline = np.linalg.norm(solid[:, 1] - solid[:, 0], axis=1).sum()
    assert len(dashes) > len(solid) and 0.3 * outline < drawn < 0.9 * outline
    # every dash lies on the box's outline
    low = np.subtract(floor.center_local, np.divide(floor.dimensions, 2))
    high = np.add(floor.center_local, np.divide(floor.dimensions, 2))
    ends = dashes.reshape(-1, 3)
    assert ((ends >= low - 1e-4) & (ends <= high + 1e-4)).all()

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        below_ceiling = lambda region: region.center_local[2] < ceiling.center_local[2]  # noqa: E731
        drawn_boxes = draw_uncertain_regions(
            server.scene, data.uncertain, visible=True, inside_clip=below_ceiling
        )
        hidden = draw_uncertain_regions(server.scene, data.uncertain, visible=False)
        assert [handle.name for _box, handle in drawn_boxes] == ["/uncertain/0", "/uncertain/1"]
        assert [handle.visible for _box, handle in drawn_boxes] == [True, False]
        assert not any(handle.visible for _box, handle in hidden)
        colours = np.asarray(drawn_boxes[0][1].colors).reshape(-1, 3)
        assert {tuple(colour) for colour in colours} == {UNCERTAIN_COLOUR}
        assert np.asarray(drawn_boxes[0][1].points).shape == dashes.shape
    finally:
        server.stop()
        time.sleep(0.1)

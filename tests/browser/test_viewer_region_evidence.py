"""The 3D view says why each region is a change (issue 29): its button names the evidence and
the confidence the job stored; regions stored before evidence existed read as seen empty."""

from __future__ import annotations

import numpy as np

from app.viewer.scene import region_boxes


def _region(**extra: object) -> dict[str, object]:
    return {
        "id": "r1",
        "kind": "removed",
        "n_points": 754,
        "centroid": [1.0, 2.0, 0.5],
        "bbox_min": [0.7, 1.7, 0.1],
        "bbox_max": [1.3, 2.3, 0.9],
        "mean_distance": 0.4,
        "max_distance": 0.8,
        **extra,
    }


def test_a_region_button_names_its_evidence_and_confidence():
    (moved,) = region_boxes([_region(evidence="surface_moved", confidence=0.84)], np.zeros(3))
    assert moved.label == "#1 removed · 754 pts · surface moved 84 %"
    assert moved.to_json_dict()["evidence"] == "surface_moved"
    (older,) = region_boxes([_region()], np.zeros(3))
    assert older.label == "#1 removed · 754 pts · seen empty"
    assert older.confidence is None

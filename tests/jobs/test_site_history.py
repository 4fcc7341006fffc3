"""The site-history warning's typed form stores the JSON the old dict did, key for key."""

from __future__ import annotations

import json

from app.jobs.alerts.site_history import RegionCountWarning


def test_a_region_count_warning_stores_the_json_of_the_old_dict() -> None:
    warning = RegionCountWarning(n_regions=139, limit=7.0, median=2.0, history_jobs=20)
    measured = {"value": 139, "limit": 7.0, "median": 2.0, "history_jobs": 20}
    stored_before = {  # written out as the dict of store_results before the typed form
        "code": "region_count_above_history",
        "message": "139 regions, far above this site's usual 2 (the median of its last 20 "
        "comparisons).",
        **measured,
        "detail": {
            **measured,
            "explanation": "so many regions more often come from a bad alignment or a scan of "
            "another place than from real change",
        },
        "how_to_fix": {"action": "check_site_history"},
    }
    assert json.dumps(warning.to_json_dict()) == json.dumps(stored_before)


def test_a_half_region_median_is_written_as_it_is() -> None:
    warning = RegionCountWarning(n_regions=20, limit=7.5, median=2.5, history_jobs=4)
    assert "usual 2.5 (the median of its last 4 comparisons)" in warning.message
    assert warning.to_json_dict()["detail"]["median"] == 2.5

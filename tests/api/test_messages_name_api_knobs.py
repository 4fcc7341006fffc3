"""Messages read over the API name the API's knobs (issue 31): a quality warning is one
sentence with its details and its fix in separate fields, the fix in the API's parameters
(never the CLI's flags), and the point limit is named as the setting SCANDIFF_MAX_POINTS."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from app.core.quality import LOW_FITNESS
from app.testing.files import ply_bytes
from app.testing.results import registration_report, sensor_origin_entries
from app.testing.scenes import room_points
from tests.helpers.http import site_with_reference, upload
from tests.helpers.jobs import finish_job
from tests.helpers.server import ApiServer, fresh_api

N_POINTS = 2000


def test_job_warnings_are_one_sentence_with_the_fix_in_api_parameters(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, reference = site_with_reference(writer)
    response = upload(writer, site["id"], ply_bytes(room_points(N_POINTS, seed=4)))
    assert response.status_code == 202, response.text
    job = response.json()["job"]
    finish_job(
        api,
        job["id"],
        reference["n_points"],
        N_POINTS,
        registration=registration_report(
            fitness=LOW_FITNESS / 2,
            rotation_degrees=4.1,
            translation_m=0.9,
            max_correspondence_distance=0.3,
        ),
        sensor_origins=sensor_origin_entries(
            {
                "reference": [],
                "scan": [
                    {
                        "source": "trajectory",
                        "poses": 30,
                        "time_span": [0.0, 9.5],
                        "points_outside": 150,
                    }
                ],
            }
        ),
    )
    warnings = writer.get(f"/api/v1/jobs/{job['id']}").json()["warnings"]
    by_code = {warning["code"]: warning for warning in warnings}
    assert set(by_code) >= {
        "low_registration_fitness",
        "large_rotation",
        "large_translation",
        "sensor_origin_unknown",
        "trajectory_time_span",
    }
    for warning in warnings:
        message = warning["message"]
        assert message.endswith(".") and "; " not in message and len(message) < 160, message
        assert "--" not in str(warning), "a CLI flag in an API message"
        assert "moving sensor's frame" not in str(warning)
        assert warning["detail"]["explanation"]
        assert warning["how_to_fix"]["text"]
    assert "sensor_origin=x,y,z" in by_code["sensor_origin_unknown"]["how_to_fix"]["text"]
    assert "sensor_origin" in by_code["sensor_origin_unknown"]["how_to_fix"]["parameters"]
    assert '"align": false' in by_code["large_rotation"]["how_to_fix"]["text"]
    assert by_code["large_rotation"]["detail"]["unit"] == "degrees"
    assert by_code["trajectory_time_span"]["how_to_fix"]["parameters"] == ["trajectory"]
    assert by_code["trajectory_time_span"]["side"] == "scan"


@pytest.fixture(scope="module")
def small_limit_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app accepting clouds of at most 500 points."""
    yield from fresh_api(tmp_path_factory, "small-limit-data", max_points=500)


def test_a_cloud_over_the_point_limit_names_the_setting(small_limit_api: ApiServer) -> None:
    writer = small_limit_api.client(small_limit_api.token("writer"))
    site = writer.post("/api/v1/sites", json={"name": "big"}).json()
    response = upload(writer, site["id"], ply_bytes(room_points(N_POINTS, seed=1)), reference=True)
    assert response.status_code == 400, response.text
    detail = response.json()["detail"]
    assert "SCANDIFF_MAX_POINTS" in detail
    assert "max_points" not in detail.replace("SCANDIFF_MAX_POINTS", "")

"""Where a job says its sensor origins came from: an origin given at upload is ``"given"``
(it used to be reported as ``"file"``), one from the file stays ``"file"``.

Real HTTP uploads, then the worker's own code (``execute_job``, the real comparison) on the
module's migrated SQLite file, then the job read back over HTTP.
"""

from __future__ import annotations

import json

import httpx
import numpy as np

from app.jobs.execution import execute_job, given_at_upload_only
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.http import site_with_reference, upload_accepted
from tests.helpers.server import ApiServer


def room_centre(points: np.ndarray) -> list[float]:
    """A sensor position inside the room: the middle of its floor plan, 1.5 m up."""
    low, high = points.min(axis=0), points.max(axis=0)
    return [float((low[0] + high[0]) / 2), float((low[1] + high[1]) / 2), float(low[2] + 1.5)]


def test_an_origin_given_at_upload_is_reported_as_given(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    points = room_points(3000, seed=2, with_box=True)
    origin = room_centre(points)
    accepted = upload_accepted(
        writer,
        site["id"],
        "scan.ply",
        ply_bytes(points),
        sensor_origin=",".join(str(value) for value in origin),
    )
    job_id = accepted["job"]["id"]

    assert execute_job(job_id, api.settings) == "succeeded"

    job = writer.get(f"/api/v1/jobs/{job_id}").json()
    scan_origins = job["sensor_origins"]["scan"]
    assert [entry["source"] for entry in scan_origins] == ["given"], json.dumps(scan_origins)
    assert np.allclose(scan_origins[0]["origin"], origin, atol=1e-6)
    assert job["calibration"]["visibility"]["scan"]["origins"] == "given"
    assert all(entry["source"] != "given" for entry in job["sensor_origins"]["reference"])
    assert all("file sensor origin" not in warning["message"] for warning in job["warnings"])


def test_an_origin_is_given_at_upload_only_when_the_file_has_another() -> None:
    assert given_at_upload_only(None, [1.0, 2.0, 3.0])
    assert given_at_upload_only(np.array([1.0, 2.0, 3.5]), [1.0, 2.0, 3.0])
    assert given_at_upload_only(np.array([1.0, 2.0, 3.0]), [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    assert not given_at_upload_only(np.array([1.0, 2.0, 3.0]), [1.0, 2.0, 3.0])  # the file's own
    assert not given_at_upload_only(np.array([1.0, 2.0, 3.0]), None)

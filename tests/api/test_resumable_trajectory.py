"""A robot that uploads its map by tus attaches its trajectory (issue 29), over real HTTP.

Rules checked:

* ``PUT /uploads/{id}/trajectory`` while the upload is unfinished holds the trajectory with
  it; the last PATCH stores the scan with it, so the comparison job the upload queues loads it
  (no race with a trajectory added to the scan later);
* a trajectory that cannot be parsed is a 422 at once and nothing is held: the upload
  completes as a scan without a trajectory;
* a held trajectory that does not cover the points' times fails the upload at its last bytes
  (422) and nothing is stored;
* once the upload is complete, the trajectory goes to the scan (409 naming the way), and
  ``PUT /scans/{id}/trajectory`` then a re-run of the job uses it.
"""

from __future__ import annotations

from typing import Any

import httpx
import numpy as np
import pytest

from app.jobs.execution import execute_job
from app.jobs.hooks import job_hooks
from app.testing import fake_pipeline
from tests.helpers.http import assert_error, create_site
from tests.helpers.resumable import new_upload, patch
from tests.helpers.server import ApiServer
from tests.helpers.trajectory_uploads import GOOD, timed_ply, tum


def upload_by_tus(
    client: httpx.Client, site_id: str, content: bytes, trajectory: bytes | None, **metadata: str
) -> tuple[str, httpx.Response | None, httpx.Response]:
    """Create a tus upload, send half, PUT the trajectory (if any), send the rest; (location,
    the PUT's answer, the last PATCH's answer)."""
    location = new_upload(client, len(content), site=site_id, filename="map.ply", **metadata)
    half = len(content) // 2
    assert patch(client, location, 0, content[:half]).status_code == 204
    held = None
    if trajectory is not None:
        held = client.put(
            f"{location}/trajectory", content=trajectory, params={"filename": "path.tum"}
        )
    return location, held, patch(client, location, half, content[half:])


def loaded_trajectories(api: ApiServer, job_id: str, monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The trajectories the job's comparison is given (reference, scan)."""
    seen: list[Any] = []

    def capture(reference, scan, **kwargs):
        seen.extend([reference.trajectory, scan.trajectory])
        return fake_pipeline.fake_compare(reference, scan, **kwargs)

    monkeypatch.setattr(job_hooks, "compare", capture)
    assert execute_job(job_id, api.settings) == "succeeded"
    return seen


def test_a_trajectory_held_with_a_tus_upload_is_stored_with_its_scan_and_used_by_its_job(
    api: ApiServer, writer: httpx.Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    site = create_site(writer)
    _, held_reference, reference = upload_by_tus(
        writer, site["id"], timed_ply(1), GOOD, reference="true"
    )
    assert held_reference is not None and held_reference.status_code == 200, held_reference.text
    assert held_reference.json()["poses"] == 25
    assert reference.status_code == 201, reference.text
    _, held, response = upload_by_tus(writer, site["id"], timed_ply(2), GOOD)
    assert held is not None and held.status_code == 200, held.text
    assert response.status_code == 202, response.text

    stored = [path.name for path in api.stored_files()]
    for scan in (reference.json()["scan"], response.json()["scan"]):
        assert f"{scan['id']}.ply.trajectory.npz" in stored
    seen = loaded_trajectories(api, response.json()["job"]["id"], monkeypatch)
    assert [len(trajectory) for trajectory in seen] == [25, 25]


def test_a_bad_trajectory_for_a_tus_upload_is_422_and_nothing_is_held_or_stored(
    api: ApiServer, writer: httpx.Client
) -> None:
    site = create_site(writer)
    before = set(api.stored_files())
    _, held, response = upload_by_tus(
        writer,
        site["id"],
        timed_ply(),
        tum(np.linspace(99, 111, 10), (0, 0, 0.5, 1.0)),
        reference="true",
    )
    assert held is not None
    assert "give unit quaternions" in assert_error(held, 422, "invalid_input")
    assert response.status_code == 201, response.text
    new = {path.name for path in set(api.stored_files()) - before}
    assert new == {f"{response.json()['scan']['id']}.ply"}

    before = api.stored_files()
    _, late, refused = upload_by_tus(
        writer, site["id"], timed_ply(), tum(np.linspace(500, 600, 10)), reference="true"
    )
    assert late is not None and late.status_code == 200, late.text  # times unknown until the end
    assert "do not cover" in assert_error(refused, 422, "invalid_input")
    assert api.stored_files() == before
    assert len(writer.get(f"/api/v1/sites/{site['id']}/scans").json()["items"]) == 1


def test_after_a_tus_upload_completes_its_trajectory_goes_to_the_scan_and_a_rerun_uses_it(
    api: ApiServer, writer: httpx.Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    site = create_site(writer)
    upload_by_tus(writer, site["id"], timed_ply(1), GOOD, reference="true")
    location, _, response = upload_by_tus(writer, site["id"], timed_ply(2), None)
    assert response.status_code == 202, response.text
    too_late = writer.put(f"{location}/trajectory", content=GOOD)
    assert "PUT /api/v1/scans/" in assert_error(too_late, 409)

    scan_id = writer.get(location).json()["result"]["scan"]["id"]
    bad = writer.put(f"/api/v1/scans/{scan_id}/trajectory", content=tum(np.linspace(5, 6, 4)))
    assert "do not cover" in assert_error(bad, 422, "invalid_input")
    added = writer.put(f"/api/v1/scans/{scan_id}/trajectory", content=GOOD)
    assert added.status_code == 200, added.text
    rerun = writer.post(f"/api/v1/jobs/{response.json()['job']['id']}/rerun")
    assert rerun.status_code == 202, rerun.text

    seen = loaded_trajectories(api, rerun.json()["id"], monkeypatch)
    assert [len(trajectory) for trajectory in seen] == [25, 25]

"""Trajectories over real HTTP: sent with a scan (multipart part ``trajectory``) or added later.

Rules checked:

* a scan with per-point times and its TUM trajectory is accepted; the trajectory is stored
  beside the scan's file; a comparison job loads both scans' trajectories;
* ``PUT /scans/{id}/trajectory`` adds one to a stored scan (raw body, or KITTI poses with a
  ``trajectory_times`` part), and answers its summary;
* times on one side only are no error: a scan whose points have times but no trajectory is
  stored as any scan (its times unused), and KITTI poses without times are kept for a scan
  without per-point times (each point takes its nearest pose in line of sight);
* an E57 scan's ``timeStamp`` values are its per-point times: a trajectory that does not cover
  them is refused, one that does is kept;
* bad input is a 422 that says what to fix and stores nothing: times that do not cover the
  points' times, non-finite or non-unit quaternions, an unknown format, pose times without a
  trajectory, KITTI poses without times for a scan with per-point times.
"""

from __future__ import annotations

from typing import Any

import httpx
import numpy as np
import pytest

from app.jobs.execution import execute_job
from app.jobs.hooks import job_hooks
from app.testing import fake_pipeline
from app.testing.e57_times import e57_with_times_bytes
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.http import assert_error, create_site
from tests.helpers.server import ApiServer
from tests.helpers.trajectory_uploads import GOOD, N_POINTS, POINT_TIMES, timed_ply, tum


def kitti(count: int) -> bytes:
    return "\n".join(f"1 0 0 {0.1 * i} 0 1 0 2 0 0 1 1.2" for i in range(count)).encode()


def send(
    client: httpx.Client,
    site_id: str,
    scan: bytes,
    parts: dict[str, tuple[str, bytes]],
    filename: str = "scan.ply",
    **params: Any,
) -> httpx.Response:
    files = {"file": (filename, scan, "application/octet-stream")}
    files.update({name: (filename, data, "text/plain") for name, (filename, data) in parts.items()})
    return client.post(f"/api/v1/sites/{site_id}/scans", params=params, files=files)


@pytest.fixture
def site(writer: httpx.Client) -> dict:
    return create_site(writer)


def test_a_scan_and_its_trajectory_are_stored_and_loaded_by_its_job(
    api: ApiServer, writer: httpx.Client, site: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    reference = send(
        writer, site["id"], timed_ply(1), {"trajectory": ("ref.tum", GOOD)}, reference="true"
    )
    assert reference.status_code == 201, reference.text
    response = send(writer, site["id"], timed_ply(2), {"trajectory": ("scan.txt", GOOD)})
    assert response.status_code == 202, response.text
    stored = [path.name for path in api.stored_files()]
    for scan in (reference.json()["scan"], response.json()["scan"]):
        assert f"{scan['id']}.ply.trajectory.npz" in stored

    seen: list[Any] = []

    def capture(reference, scan, **kwargs):
        seen.extend([reference.trajectory, scan.trajectory])
        return fake_pipeline.fake_compare(reference, scan, **kwargs)

    monkeypatch.setattr(job_hooks, "compare", capture)
    assert execute_job(response.json()["job"]["id"], api.settings) == "succeeded"

    assert [len(trajectory) for trajectory in seen] == [25, 25]
    np.testing.assert_allclose(seen[1].times, np.linspace(99.0, 111.0, 25))


def test_a_trajectory_is_added_to_a_stored_scan(writer: httpx.Client, site: dict) -> None:
    scan = send(writer, site["id"], timed_ply(), {}, reference="true").json()["scan"]

    raw = writer.put(
        f"/api/v1/scans/{scan['id']}/trajectory", content=GOOD, params={"filename": "p.tum"}
    )
    times_file = "\n".join(repr(float(t)) for t in np.linspace(99, 111, 8)).encode()
    kitti_with_times = writer.put(
        f"/api/v1/scans/{scan['id']}/trajectory",
        files={
            "trajectory": ("poses.txt", kitti(8), "text/plain"),
            "trajectory_times": ("times.txt", times_file, "text/plain"),
        },
    )

    assert raw.status_code == 200, raw.text
    assert raw.json()["poses"] == 25 and raw.json()["time_span"] == [99.0, 111.0]
    assert raw.json()["points_outside"] == 0 and raw.json()["point_times"] is True
    assert kitti_with_times.status_code == 200, kitti_with_times.text
    assert kitti_with_times.json()["poses"] == 8


def test_times_on_one_side_only_are_accepted(
    api: ApiServer, writer: httpx.Client, site: dict
) -> None:
    timed_alone = send(writer, site["id"], timed_ply(), {}, reference="true")
    untimed = ply_bytes(room_points(N_POINTS, 3))
    poses_alone = send(writer, site["id"], untimed, {"trajectory": ("poses.txt", kitti(8))})

    assert timed_alone.status_code == 201, timed_alone.text
    assert poses_alone.status_code == 202, poses_alone.text
    stored = {path.name for path in api.stored_files()}
    assert f"{timed_alone.json()['scan']['id']}.ply.trajectory.npz" not in stored
    assert f"{poses_alone.json()['scan']['id']}.ply.trajectory.npz" in stored
    added = writer.put(
        f"/api/v1/scans/{poses_alone.json()['scan']['id']}/trajectory", content=kitti(8)
    )
    assert added.status_code == 200, added.text
    assert added.json()["time_span"] is None and added.json()["point_times"] is False


def test_an_e57_scans_time_stamps_are_checked_against_its_trajectory(
    api: ApiServer, writer: httpx.Client, site: dict
) -> None:
    e57 = e57_with_times_bytes(room_points(N_POINTS, 4), POINT_TIMES)
    before = api.stored_files()

    late = send(
        writer, site["id"], e57, {"trajectory": ("t.tum", tum(np.linspace(500, 600, 10)))},
        filename="scan.e57", reference="true",
    )  # fmt: skip
    assert "do not cover" in assert_error(late, 422, "invalid_input")
    assert api.stored_files() == before
    accepted = send(
        writer, site["id"], e57, {"trajectory": ("t.tum", GOOD)}, filename="scan.e57",
        reference="true",
    )  # fmt: skip
    assert accepted.status_code == 201, accepted.text
    added = writer.put(f"/api/v1/scans/{accepted.json()['scan']['id']}/trajectory", content=GOOD)
    assert added.json()["point_times"] is True and added.json()["points_outside"] == 0


@pytest.mark.parametrize(
    ("parts", "params", "message"),
    [
        ({"trajectory": ("t.tum", tum(np.linspace(500, 600, 10)))}, {}, "do not cover"),
        (
            {"trajectory": ("t.tum", tum(np.linspace(99, 111, 10), (0, 0, 0.5, 1.0)))},
            {},
            "not 1: give unit quaternions",
        ),
        (
            {"trajectory": ("t.tum", tum(np.linspace(99, 111, 10), (0, 0, float("nan"), 1)))},
            {},
            "non-finite",
        ),
        ({"trajectory": ("t.bin", b"\x00\x01\x02 not a trajectory")}, {}, "expected TUM"),
        (
            {"trajectory": ("t.tum", GOOD)},
            {"trajectory_format": "ply"},
            "unknown trajectory format",
        ),
        ({"trajectory_times": ("times.txt", b"1\n2\n")}, {}, "without a trajectory"),
        ({}, {"trajectory_rate": "10"}, "without a trajectory"),
        ({"trajectory": ("poses.txt", kitti(8))}, {}, "trajectory has none"),
    ],
    ids=[
        "times-not-covered",
        "non-unit-quaternion",
        "nan-quaternion",
        "unknown-format",
        "format-named-unknown",
        "times-without-trajectory",
        "rate-without-trajectory",
        "kitti-without-times",
    ],
)
def test_bad_trajectories_are_422_and_store_nothing(
    api: ApiServer,
    writer: httpx.Client,
    site: dict,
    parts: dict,
    params: dict,
    message: str,
) -> None:
    before = api.stored_files()

    response = send(writer, site["id"], timed_ply(), parts, reference="true", **params)

    assert message in assert_error(response, 422, "invalid_input")
    assert api.stored_files() == before
    assert writer.get(f"/api/v1/sites/{site['id']}/scans").json()["items"] == []


def test_a_bad_trajectory_added_later_is_422_and_keeps_none(
    api: ApiServer, writer: httpx.Client, site: dict
) -> None:
    scan = send(writer, site["id"], timed_ply(), {}, reference="true").json()["scan"]
    before = api.stored_files()

    path = f"/api/v1/scans/{scan['id']}/trajectory"
    late = writer.put(path, content=tum(np.linspace(500, 600, 10)))
    empty = writer.put(path, content=b"")
    long = writer.put(path, content=tum(np.linspace(99, 111, 10), (0, 0, 0.5, 1.0)))
    untimed = writer.put(path, content=kitti(8))
    unknown = writer.put(path, content=GOOD, params={"trajectory_format": "ply"})
    missing = writer.put("/api/v1/scans/nope/trajectory", content=GOOD)

    assert "do not cover" in assert_error(late, 422, "invalid_input")
    assert "empty" in assert_error(empty, 422, "invalid_input")
    assert "give unit quaternions" in assert_error(long, 422, "invalid_input")
    assert "trajectory has none" in assert_error(untimed, 422, "invalid_input")
    assert "unknown trajectory format" in assert_error(unknown, 422, "invalid_input")
    assert_error(missing, 404)
    assert api.stored_files() == before

"""ROS bags uploaded as scans to the real service (``scandiff serve`` with its job consumer).

Rules checked:

* a ROS 1 ``.bag`` is accepted as a site's reference (format ``bag``, the point count and
  bounds of the map :func:`read_point_cloud` builds from it); a bare ROS 2 ``.mcap`` sent
  without a file name is recognised from its content and compared against it by the worker: the
  job succeeds and finds the box removed from the room;
* a truncated bag is a 400 ``malformed_point_cloud`` saying it may be truncated, and leaves no
  scan row and no file.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path

import numpy as np

from app.core.formats import BagOptions, read_point_cloud
from app.testing.bags import BOX_HIGH, BOX_LOW, write_lidar_bag
from app.testing.service import ServiceProcess
from tests.helpers.http import assert_error, create_site, upload


def stored_files(service: ServiceProcess) -> list[Path]:
    return sorted(path for path in (service.data_dir / "scans").rglob("*") if path.is_file())


def test_bags_upload_and_compare_and_a_truncated_bag_is_refused(
    service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    (tmp_path / "reference").mkdir()
    (tmp_path / "scan").mkdir()
    reference_bag = write_lidar_bag(tmp_path / "reference", "bag")
    scan_bag = write_lidar_bag(tmp_path / "scan", "mcap", with_box=False, seed=1)
    reference_map = read_point_cloud(reference_bag.path)
    service = service_factory(workers=1)

    with service.client() as client:
        site = create_site(client)
        content = reference_bag.path.read_bytes()
        response = upload(client, site["id"], content, filename="robot.bag", reference=True)
        assert response.status_code == 201, response.text
        reference = response.json()["scan"]
        assert reference["format"] == "bag"
        assert reference["n_points"] == len(reference_map)
        low, high = reference_map.bounds()
        np.testing.assert_allclose(reference["bbox_min"], low)
        np.testing.assert_allclose(reference["bbox_max"], high)

        files_before = stored_files(service)
        truncated = content[: len(content) // 2]
        for multipart in (False, True):
            refused = upload(client, site["id"], truncated, filename="cut.bag", multipart=multipart)
            detail = assert_error(refused, 400, "malformed_point_cloud")
            assert "cut.bag" in detail and "truncated" in detail
        listed = client.get(f"/api/v1/sites/{site['id']}/scans").json()["items"]
        assert [scan["id"] for scan in listed] == [reference["id"]]
        assert stored_files(service) == files_before

        response = upload(client, site["id"], scan_bag.path.read_bytes(), filename=None)
        assert response.status_code == 202, response.text
        assert response.json()["scan"]["format"] == "mcap"
        job = service.wait_for_job(client, response.json()["job"]["id"], timeout=180)
        assert job["status"] == "succeeded", job
        assert job["changed"] is True
        regions = client.get(f"/api/v1/jobs/{job['id']}/regions", params={"limit": 1000}).json()
        regions = regions["items"]
        removed = [region for region in regions if region["kind"] == "removed"]
        assert removed, regions
        largest = max(removed, key=lambda region: region["n_points"])
        box_centre = (BOX_LOW[0] + BOX_HIGH[0]) / 2
        assert np.linalg.norm(np.array(largest["centroid"])[:2] - box_centre[:2]) < 0.6

        # a bag with two cloud topics: refused naming them until the upload says which, then
        # kept with that choice, which its job reads again (the same map, the same result)
        (tmp_path / "two").mkdir()
        two_topics = write_lidar_bag(
            tmp_path / "two", "mcap", with_box=False, seed=2, extra_cloud_topic=True
        ).path.read_bytes()
        refused = upload(client, site["id"], two_topics, filename="two.mcap")
        detail = assert_error(refused, 400, "malformed_point_cloud")
        assert "cloud_topic" in detail and "/front/points" in detail
        refused = upload(client, site["id"], two_topics, filename="two.mcap", bag="topic=/x")
        assert "cloud_topic" in assert_error(refused, 422, "validation_error")
        accepted = upload(
            client, site["id"], two_topics, filename="two.mcap", bag="cloud_topic=/velodyne_points"
        )
        assert accepted.status_code == 202, accepted.text
        chosen_map = read_point_cloud(
            two_topics, filename="two.mcap", bag_options=BagOptions(cloud_topic="/velodyne_points")
        )
        assert accepted.json()["scan"]["n_points"] == len(chosen_map)
        job = service.wait_for_job(client, accepted.json()["job"]["id"], timeout=180)
        assert job["status"] == "succeeded", job
        labels = client.get(f"/api/v1/jobs/{job['id']}/labels")
        with np.load(io.BytesIO(labels.content)) as archive:
            assert archive["scan_label"].shape == (len(chosen_map),)

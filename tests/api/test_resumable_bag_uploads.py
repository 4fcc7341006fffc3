"""A ROS bag sent as a resumable (tus) upload takes the bag parameters of ``?bag=KEY=VALUE``,
as ``Upload-Metadata`` keys ``bag.KEY`` (issue 29), over real HTTP.

Rules checked: a bag with two cloud topics, created with ``bag.cloud_topic``, becomes the map of
that topic, and the parameters are kept beside the stored bag (the file its jobs read them
from); an unknown key or a value that is not a number is a 422 at creation naming it, and
nothing is created or stored; without the parameter the completed upload is refused naming the
topics, the upload is ``failed`` and nothing is stored.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from app.core.formats import BagOptions, read_point_cloud
from app.kit.scan_files import bag_options_path
from app.testing.bags import write_lidar_bag
from tests.helpers.http import assert_error, create_site
from tests.helpers.resumable import TUS, create_upload, new_upload, patch
from tests.helpers.server import ApiServer


@pytest.fixture(scope="module")
def two_topics(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A ROS 2 ``.mcap`` bag with two cloud topics: ``/velodyne_points``, ``/front/points``."""
    directory = tmp_path_factory.mktemp("two-topics")
    written = write_lidar_bag(  # small enough for the test server's upload limit
        directory,
        "mcap",
        with_box=False,
        seed=2,
        extra_cloud_topic=True,
        n_sweeps=4,
        azimuth_step_deg=8.0,
    )
    return Path(written.path).read_bytes()


def test_bag_parameters_in_the_metadata_choose_the_map_and_are_kept(
    api: ApiServer, two_topics: bytes
) -> None:
    client = api.client(api.token("writer"))
    site = create_site(client)

    location = new_upload(
        client,
        len(two_topics),
        site=site["id"],
        filename="two.mcap",
        reference="true",
        **{"bag.cloud_topic": "/velodyne_points", "bag.voxel_size": "0.05"},
    )
    half = len(two_topics) // 2
    assert patch(client, location, 0, two_topics[:half]).status_code == 204
    response = patch(client, location, half, two_topics[half:])

    assert response.status_code == 201, response.text
    scan = response.json()["scan"]
    chosen = read_point_cloud(
        two_topics, filename="two.mcap", bag_options=BagOptions(cloud_topic="/velodyne_points")
    )
    assert scan["format"] == "mcap" and scan["n_points"] == len(chosen)
    (stored,) = [path for path in api.stored_files() if path.name.endswith(".mcap")]
    kept = json.loads(bag_options_path(stored).read_text())
    assert kept == {"cloud_topic": "/velodyne_points", "voxel_size": "0.05"}


@pytest.mark.parametrize(
    ("metadata", "named"),
    [
        ({"bag.topic": "/velodyne_points"}, "topic"),
        ({"bag.voxel_size": "fine"}, "voxel_size"),
        ({"bag.max_sweeps": "0"}, "max_sweeps"),
        ({"bag": "cloud_topic=/velodyne_points"}, "bag.KEY"),
    ],
    ids=["unknown-key", "not-a-number", "out-of-range", "one-bag-key"],
)
def test_a_bad_bag_parameter_is_422_at_creation_naming_it(
    api: ApiServer, two_topics: bytes, metadata: dict[str, str], named: str
) -> None:
    client = api.client(api.token("writer"))
    site = create_site(client)
    before = api.stored_files()

    response = create_upload(client, len(two_topics), site=site["id"], **metadata)

    assert named in assert_error(response, 422)
    assert "Location" not in response.headers
    assert api.stored_files() == before
    assert not list((api.data_dir / "uploads").glob("*.part"))


def test_without_parameters_an_ambiguous_bag_fails_naming_its_topics(
    api: ApiServer, two_topics: bytes
) -> None:
    client = api.client(api.token("writer"))
    site = create_site(client)
    before = api.stored_files()
    location = new_upload(
        client, len(two_topics), site=site["id"], filename="two.mcap", reference="true"
    )

    response = patch(client, location, 0, two_topics)

    detail = assert_error(response, 400, "malformed_point_cloud")
    assert "cloud_topic" in detail and "/front/points" in detail
    assert client.get(location).json()["state"] == "failed"
    assert client.head(location, headers=TUS).status_code == 410
    assert client.get(f"/api/v1/sites/{site['id']}/scans").json()["items"] == []
    assert api.stored_files() == before

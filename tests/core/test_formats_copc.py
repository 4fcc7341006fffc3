"""COPC files: read whole as LAZ, read by box (only the octree nodes overlapping it), and
refused when their header and octree disagree on the point count."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.errors import PointCloudError
from app.core.formats import detect_format, read_point_cloud, summarise_point_cloud
from app.core.formats.copc import is_copc, read_copc_bounds
from app.testing.files import las_bytes
from tests.helpers.copc import COPC_SCALE, copc_bytes, with_point_count


@pytest.fixture(scope="module")
def cloud() -> np.ndarray:
    """2,000 points in a 10 m cube, at the file's 1 mm resolution."""
    points = np.random.default_rng(30).uniform(0.0, 10.0, size=(2000, 3))
    return np.round(points / COPC_SCALE) * COPC_SCALE


@pytest.fixture(scope="module")
def copc_path(tmp_path_factory, cloud):
    path = tmp_path_factory.mktemp("copc") / "survey.copc.laz"
    path.write_bytes(copc_bytes(cloud))
    return path


def sorted_rows(points: np.ndarray) -> np.ndarray:
    return points[np.lexsort(points.T[::-1])]


def test_a_copc_file_is_read_whole_as_laz(copc_path, cloud) -> None:
    content = copc_path.read_bytes()
    assert is_copc(content)
    assert not is_copc(las_bytes(cloud, compress=True, point_format=6, version="1.4"))
    assert detect_format(copc_path.name, content[:4096]) == "laz"
    whole = read_point_cloud(copc_path)
    np.testing.assert_allclose(sorted_rows(whole.points), sorted_rows(cloud), atol=1e-6)
    summary = summarise_point_cloud(copc_path, "laz", filename=copc_path.name, max_points=10**6)
    assert summary.n_points == len(cloud)


@pytest.mark.parametrize(
    ("low", "high"),
    [
        ((-1.0, -1.0, -1.0), (4.0, 4.0, 4.0)),  # one octant and a bit
        ((2.0, 3.0, 1.0), (8.0, 7.0, 9.0)),  # across all eight octants
        ((20.0, 20.0, 20.0), (30.0, 30.0, 30.0)),  # outside the cloud
    ],
)
def test_read_copc_bounds_returns_exactly_the_points_in_the_box(
    copc_path, cloud, low, high
) -> None:
    found = read_copc_bounds(copc_path, low, high)
    expected = cloud[((cloud >= low) & (cloud <= high)).all(axis=1)]
    assert found.points.dtype == np.float64 and found.points.shape == expected.shape
    np.testing.assert_allclose(sorted_rows(found.points), sorted_rows(expected), atol=1e-6)
    assert all(len(values) == len(expected) for values in found.attributes.values())
    assert "intensity" in found.attributes


def test_read_copc_bounds_decodes_only_the_nodes_overlapping_the_box(
    copc_path, monkeypatch
) -> None:
    import laspy.copc

    decoded_nodes: list[int] = []
    original = laspy.copc.CopcReader._fetch_and_decompress_points_of_nodes

    def counting(self, nodes):
        decoded_nodes.append(len(nodes))
        return original(self, nodes)

    monkeypatch.setattr(laspy.copc.CopcReader, "_fetch_and_decompress_points_of_nodes", counting)
    read_copc_bounds(copc_path, (0.1, 0.1, 0.1), (2.0, 2.0, 2.0))
    one_octant = sum(decoded_nodes)
    decoded_nodes.clear()
    read_copc_bounds(copc_path, (-1.0, -1.0, -1.0), (11.0, 11.0, 11.0))
    assert one_octant == 2 and sum(decoded_nodes) == 9  # the root and one child; all nine


@pytest.mark.parametrize("declared_change", [+25, -25])
def test_a_header_that_disagrees_with_the_octree_is_refused(
    tmp_path, cloud, declared_change
) -> None:
    path = tmp_path / "edited.copc.laz"
    path.write_bytes(with_point_count(copc_bytes(cloud), len(cloud) + declared_change))
    expected = f"declares {len(cloud) + declared_change:,} points but its octree holds"
    with pytest.raises(PointCloudError, match=expected):
        read_point_cloud(path)
    with pytest.raises(PointCloudError, match=expected):
        summarise_point_cloud(path, "laz", filename=path.name, max_points=10**6)
    with pytest.raises(PointCloudError, match=expected):
        read_copc_bounds(path, (0, 0, 0), (1, 1, 1))


def test_read_copc_bounds_refuses_other_files_and_bad_boxes(tmp_path, copc_path, cloud) -> None:
    laz = tmp_path / "plain.laz"
    laz.write_bytes(las_bytes(cloud, compress=True, point_format=6, version="1.4"))
    with pytest.raises(PointCloudError, match="not a COPC file"):
        read_copc_bounds(laz, (0, 0, 0), (1, 1, 1))
    with pytest.raises(PointCloudError, match="low corner"):
        read_copc_bounds(copc_path, (2, 0, 0), (1, 1, 1))
    with pytest.raises(PointCloudError, match="finite"):
        read_copc_bounds(copc_path, (np.nan, 0, 0), (1, 1, 1))
    with pytest.raises(PointCloudError, match="three"):
        read_copc_bounds(copc_path, (0, 0), (1, 1))
    with pytest.raises(PointCloudError):
        read_copc_bounds(copc_path, (-1, -1, -1), (11, 11, 11), max_points=100)

"""Every real third-party file in ../shared/data/real loads with the documented point count."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.core.formats import detect_format, read_point_cloud

pytestmark = pytest.mark.real_data

# From ../shared/data/real/README.md: points and bounding boxes (metres, 2 decimals).
EXPECTED = {
    "kitti_2011_09_26_drive_0002_pointcloudset/frame0.ply": (
        121_071,
        (-79.90, -62.94, -7.06),
        (79.70, 77.23, 2.91),
    ),
    "kitti_2011_09_26_drive_0002_pointcloudset/frame1.ply": (
        120_854,
        (-79.89, -59.44, -7.79),
        (79.68, 78.86, 2.91),
    ),
    "kitti_2011_09_26_drive_0002_pointcloudset/frame2.ply": (
        120_791,
        (-79.96, -54.03, -6.32),
        (79.19, 77.33, 2.91),
    ),
    "lidar_scu_velodyne_budapest/Velo1.pcd": (
        18_090,
        (-26.26, -30.00, -2.65),
        (28.58, 29.99, 3.12),
    ),
    "lidar_scu_velodyne_budapest/Velo2.pcd": (
        33_134,
        (-39.99, -50.00, -2.94),
        (39.98, 49.48, 5.15),
    ),
    "lidar_scu_velodyne_budapest/Velo3.pcd": (
        18_981,
        (-29.03, -29.57, -2.49),
        (29.54, 29.57, 3.28),
    ),
    "lidar_scu_velodyne_budapest/Velo4.pcd": (
        27_508,
        (-39.98, -47.70, -3.84),
        (39.97, 49.92, 4.79),
    ),
    "lidar_scu_velodyne_budapest/Velo5.pcd": (
        31_210,
        (-39.99, -49.97, -2.95),
        (40.00, 50.00, 5.46),
    ),
    # two-epoch maps (counts from the README; bounds read with plyfile)
    "multichange3d_samples/classroom_tls/epoch0.ply": (
        92_597,
        (-5.76, -10.13, -1.53),
        (7.81, 7.02, 1.07),
    ),
    "multichange3d_samples/classroom_tls/epoch1.ply": (
        90_110,
        (-5.75, -10.12, -1.51),
        (7.81, 7.02, 1.07),
    ),
    "multichange3d_samples/bike_parking_mls/epoch0.ply": (
        69_578,
        (27.84, 0.05, -5.15),
        (55.56, 20.12, 1.94),
    ),
    "multichange3d_samples/bike_parking_mls/epoch1.ply": (
        52_048,
        (27.82, 0.05, -4.35),
        (55.35, 20.17, 2.04),
    ),
}


@pytest.mark.parametrize("relative_path", sorted(EXPECTED))
def test_real_file_loads_with_documented_count_and_bounds(real_data_dir: Path, relative_path):
    path = real_data_dir / relative_path
    expected_count, expected_min, expected_max = EXPECTED[relative_path]
    cloud = read_point_cloud(path)
    assert len(cloud) == expected_count
    assert cloud.n_dropped == 0
    low, high = cloud.bounds()
    np.testing.assert_allclose(low, expected_min, atol=0.006)
    np.testing.assert_allclose(high, expected_max, atol=0.006)
    # Content sniffing agrees with the suffix, and bytes without a name read the same.
    assert detect_format(None, path.read_bytes()[:4096]) == path.suffix.lstrip(".")
    np.testing.assert_array_equal(read_point_cloud(path.read_bytes()).points, cloud.points)


def test_budapest_pcd_fields_match_pypcd4(real_data_dir: Path):
    import pypcd4

    path = real_data_dir / "lidar_scu_velodyne_budapest" / "Velo1.pcd"
    cloud = read_point_cloud(path)
    reference = pypcd4.PointCloud.from_path(path)
    assert set(cloud.attributes) == {"rgb", "normal_x", "normal_y", "normal_z", "curvature"}
    assert cloud.attributes["rgb"].dtype == np.uint32
    for name in cloud.attributes:
        np.testing.assert_array_equal(cloud.attributes[name], reference.pc_data[name])
    np.testing.assert_array_equal(cloud.points, reference.numpy(("x", "y", "z")))
    assert cloud.sensor_origin is None  # VIEWPOINT is PCL's default: unknown


def test_every_real_file_is_covered(real_data_dir: Path):
    present = {
        str(path.relative_to(real_data_dir))
        for path in real_data_dir.rglob("*")
        if path.suffix in (".ply", ".pcd", ".las", ".laz", ".xyz", ".csv", ".npy", ".npz")
    }
    assert present == set(EXPECTED)

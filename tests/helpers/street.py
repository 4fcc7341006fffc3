"""A real KITTI street frame with a car-sized box of points added: a change on a real scan,
shared by the viewer's opening test and the origin estimate's tests."""

from __future__ import annotations

import numpy as np

from app.core.datasets.added_objects import box_on_the_ground
from app.core.formats import read_point_cloud
from app.testing.paths import shared_data_dir
from tests.helpers.environment import require

KITTI_FRAME = "real/kitti_2011_09_26_drive_0002_pointcloudset/frame0.ply"
"""The street frame, under ../shared/data."""


def street_with_a_parked_car() -> tuple[np.ndarray, np.ndarray]:
    """A real KITTI street frame, and the same frame with a car-sized box of points added on
    the road 12 m ahead (its six sides sampled on an 81 x 81 grid each: 39k points, a quarter
    of the frame, 1,500-3,400 points a one-metre voxel where the lidar's own hold at most ~980).
    """
    path = shared_data_dir() / KITTI_FRAME
    require(path.exists(), f"the real KITTI frame is missing: {path} (see ../shared/data)")
    street = read_point_cloud(path).points
    car = box_on_the_ground(street, (10.0, 2.1), (14.0, 3.9), 1.5)
    return street, np.vstack([street, car])

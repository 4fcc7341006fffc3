"""Trajectory files: TUM, KITTI poses (with a times file, a rate or neither) and CSV.

Rules checked: each format is detected by content and read into the same poses; comments and
blank lines are skipped; CSV column names are case-insensitive with aliases and any order;
unknown formats name the accepted ones; non-finite values, non-unit quaternions, non-rotation
KITTI blocks, unsorted or repeated times, and times that do not fit the poses are refused with
the line at fault; per-point time fields of PLY/LAS files end up in the ``"time"`` attribute.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.core.formats import read_point_cloud
from app.core.formats.trajectory_files import detect_trajectory_format, read_trajectory
from app.core.trajectory import TrajectoryError
from app.testing.files import las_bytes, pcd_bytes, ply_bytes

RNG = np.random.default_rng(3)
TIMES = 1_700_000_000.0 + np.cumsum(RNG.uniform(0.05, 0.2, 6))
POSITIONS = RNG.uniform(-5, 5, (6, 3))
QUATERNIONS = Rotation.random(6, random_state=4).as_quat()


def tum_text(times=TIMES, positions=POSITIONS, quaternions=QUATERNIONS) -> bytes:
    lines = ["# timestamp tx ty tz qx qy qz qw", ""]
    for time, position, quaternion in zip(times, positions, quaternions, strict=True):
        values = [repr(float(time)), *map(repr, map(float, position))]
        values += [repr(float(value)) for value in quaternion]
        lines.append(" ".join(values))
    return "\n".join(lines).encode()


def kitti_text(positions=POSITIONS, quaternions=QUATERNIONS) -> bytes:
    matrices = np.concatenate(
        [Rotation.from_quat(quaternions).as_matrix(), positions[:, :, None]], axis=2
    )
    return "\n".join(" ".join(repr(float(v)) for v in m.reshape(-1)) for m in matrices).encode()


def test_tum_is_detected_and_read() -> None:
    trajectory = read_trajectory(tum_text(), filename="poses.txt")

    assert detect_trajectory_format(tum_text().decode()) == "tum"
    np.testing.assert_allclose(trajectory.times, TIMES)
    np.testing.assert_allclose(trajectory.positions, POSITIONS)
    np.testing.assert_allclose(trajectory.orientations, QUATERNIONS)
    assert trajectory.has_times


def test_kitti_poses_take_their_times_from_a_times_file_or_a_rate(tmp_path) -> None:
    times_file = tmp_path / "times.txt"
    times_file.write_text("\n".join(repr(float(t)) for t in TIMES))

    with_file = read_trajectory(kitti_text(), times=times_file)
    with_rate = read_trajectory(kitti_text(), rate=10.0)
    without = read_trajectory(kitti_text())

    np.testing.assert_allclose(with_file.times, TIMES)
    np.testing.assert_allclose(with_file.positions, POSITIONS)
    same_rotation = np.abs(np.einsum("md,md->m", with_file.orientations, QUATERNIONS))
    np.testing.assert_allclose(same_rotation, 1.0, atol=1e-9)  # q and -q are one rotation
    np.testing.assert_allclose(with_rate.times, np.arange(6) / 10.0)
    assert with_file.has_times and with_rate.has_times
    assert not without.has_times


@pytest.mark.parametrize(
    "header",
    ["time,x,y,z,qx,qy,qz,qw", "Timestamp,TX,Ty,tz,QX,qy,qz,qw", "#time;x;y;z;qx;qy;qz;qw"],
)
def test_csv_columns_are_found_by_name_whatever_the_case_or_alias(header: str) -> None:
    delimiter = ";" if ";" in header else ","
    rows = [
        delimiter.join(repr(float(v)) for v in (t, *p, *q))
        for t, p, q in zip(TIMES, POSITIONS, QUATERNIONS, strict=True)
    ]
    text = "\n".join([header.lstrip("#") if header.startswith("#") else header, *rows])

    trajectory = read_trajectory(text.encode(), filename="path.csv")

    np.testing.assert_allclose(trajectory.times, TIMES)
    np.testing.assert_allclose(trajectory.positions, POSITIONS)
    np.testing.assert_allclose(trajectory.orientations, QUATERNIONS)


def test_csv_columns_may_come_in_any_order_and_without_quaternions() -> None:
    rows = [
        f"{p[2]:.17g},{t:.17g},{p[0]:.17g},{p[1]:.17g}"
        for t, p in zip(TIMES, POSITIONS, strict=True)
    ]
    trajectory = read_trajectory(("z,time,x,y\n" + "\n".join(rows)).encode())

    np.testing.assert_allclose(trajectory.positions, POSITIONS)
    assert trajectory.orientations is None


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"hello world\nthis is not a trajectory\n", "expected TUM"),
        (b"1 2 3 4 5\n6 7 8 9 10\n", "has 5 numbers"),
        (b"", "holds no poses"),
        (b"\xff\xfe\x00binary", "is not text"),
        (b"time,a,b,c\n1,2,3,4\n", "has no x, y, z column"),
    ],
    ids=["words", "five-numbers", "empty", "binary", "csv-without-xyz"],
)
def test_unknown_or_malformed_files_name_what_is_accepted(content: bytes, message: str) -> None:
    with pytest.raises(TrajectoryError, match=message):
        read_trajectory(content, filename="bad.txt")


def test_bad_values_are_refused_with_the_line_at_fault() -> None:
    not_finite = POSITIONS.copy()
    not_finite[2, 1] = np.nan
    not_unit = QUATERNIONS.copy()
    not_unit[3] *= 1.5
    unsorted = TIMES.copy()
    unsorted[[1, 2]] = unsorted[[2, 1]]
    repeated = TIMES.copy()
    repeated[4] = repeated[3]

    with pytest.raises(TrajectoryError, match=r"line 5 .*non-finite"):
        read_trajectory(tum_text(positions=not_finite))
    with pytest.raises(TrajectoryError, match=r"line 6: the quaternion .* not 1"):
        read_trajectory(tum_text(quaternions=not_unit))
    with pytest.raises(TrajectoryError, match="increase strictly: line 5 goes back"):
        read_trajectory(tum_text(times=unsorted))
    with pytest.raises(TrajectoryError, match="line 7 repeats"):
        read_trajectory(tum_text(times=repeated))


def test_kitti_needs_rotations_and_one_time_a_pose() -> None:
    sheared = kitti_text().decode().splitlines()
    values = sheared[1].split()
    values[1] = str(float(values[1]) + 0.3)
    sheared[1] = " ".join(values)

    with pytest.raises(TrajectoryError, match=r"line 2 .* not a rotation"):
        read_trajectory("\n".join(sheared).encode())
    with pytest.raises(TrajectoryError, match="5 times for 6 KITTI poses"):
        read_trajectory(kitti_text(), times=np.array(TIMES[:5]))
    with pytest.raises(TrajectoryError, match="either a times file or a rate"):
        read_trajectory(kitti_text(), times=TIMES, rate=10.0)
    with pytest.raises(TrajectoryError, match="only for KITTI poses"):
        read_trajectory(tum_text(), rate=10.0)


def test_per_point_times_of_ply_and_las_files_become_the_time_attribute() -> None:
    points = RNG.uniform(0, 10, (200, 3))
    times = np.linspace(5.0, 6.0, 200)

    ply = read_point_cloud(ply_bytes(points, extra={"timestamp": times}), filename="a.ply")
    ply_t = read_point_cloud(ply_bytes(points, extra={"t": times.astype("f4")}), filename="b.ply")
    pcd = read_point_cloud(pcd_bytes(points, extra={"time": times}), filename="e.pcd")
    las = read_point_cloud(
        las_bytes(points, point_format=1, scale=0.001, gps_time=times), filename="c.las"
    )
    without = read_point_cloud(ply_bytes(points), filename="d.ply")

    for cloud in (ply, ply_t, pcd, las):
        assert cloud.attributes["time"].dtype == np.float64
        np.testing.assert_allclose(cloud.attributes["time"], times, rtol=1e-6)
    assert "time" not in without.attributes

"""Small COPC files for tests, written with copc-lib (laspy reads COPC but cannot write it)."""

from __future__ import annotations

import struct
import tempfile
from pathlib import Path

import copclib
import numpy as np
from numpy.typing import NDArray

from app.core.formats.copc import POINT_COUNT_OFFSET

COPC_SCALE = 0.001


def copc_bytes(points: NDArray[np.float64]) -> bytes:
    """A COPC file of (n, 3) ``points``: a root node holding every 10th point and its eight
    children holding the rest by octant (1 mm resolution)."""
    low, high = points.min(axis=0), points.max(axis=0)
    centre = (low + high) / 2.0
    half_size = float((high - low).max()) / 2.0 + COPC_SCALE
    config = copclib.CopcConfigWriter(
        6, copclib.Vector3(COPC_SCALE, COPC_SCALE, COPC_SCALE), copclib.Vector3(*np.floor(low))
    )
    info = config.copc_info
    info.center_x, info.center_y, info.center_z = (float(value) for value in centre)
    info.halfsize = half_size
    info.spacing = half_size / 8.0
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "cloud.copc.laz"
        writer = copclib.FileWriter(str(path), config)
        header = writer.copc_config.las_header
        header.min = copclib.Vector3(*low)
        header.max = copclib.Vector3(*high)

        def add_node(key: copclib.VoxelKey, rows: NDArray[np.int64]) -> None:
            node_points = copclib.Points(header)
            for x, y, z in points[rows]:
                point = node_points.CreatePoint()
                point.x, point.y, point.z = float(x), float(y), float(z)
                node_points.AddPoint(point)
            writer.AddNode(key, node_points)

        rows = np.arange(len(points))
        root = rows % 10 == 0
        add_node(copclib.VoxelKey(0, 0, 0, 0), rows[root])
        octant = (points[~root] >= centre).astype(int)
        for index in range(8):
            corner = ((index >> 2) & 1, (index >> 1) & 1, index & 1)
            selected = rows[~root][(octant == corner).all(axis=1)]
            if len(selected):
                add_node(copclib.VoxelKey(1, *corner), selected)
        writer.Close()
        return path.read_bytes()


def with_point_count(content: bytes, n_points: int) -> bytes:
    """A LAS 1.4 / COPC file whose header declares ``n_points`` (64-bit count) instead."""
    edited = bytearray(content)
    struct.pack_into("<Q", edited, POINT_COUNT_OFFSET, n_points)
    return bytes(edited)

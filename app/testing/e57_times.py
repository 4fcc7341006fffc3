"""E57 files with per-point times (``timeStamp``), written by libE57Format itself.

pye57's ``write_scan_raw`` writes no ``timeStamp`` field, so the scan's node is built here with
pye57's bindings of libE57Format (``pye57.libe57``), as ``write_scan_raw`` builds it: cartesian
coordinates as float32 nodes, the times as float64 ones, optionally ``isTimeStampInvalid``.
"""

from __future__ import annotations

import tempfile
import uuid
from pathlib import Path

import numpy as np
import pye57
from numpy.typing import NDArray
from pye57 import libe57


def e57_with_times_bytes(
    points: NDArray[np.float64],
    times: NDArray[np.float64],
    time_invalid: NDArray[np.bool_] | None = None,
) -> bytes:
    """One scan of (n, 3) ``points`` (identity pose) whose points carry ``times`` (n,) seconds;
    ``time_invalid`` flags points whose time is not valid (``isTimeStampInvalid``)."""
    points = np.asarray(points, dtype=np.float64)
    columns: dict[str, NDArray] = {
        "cartesianX": points[:, 0].copy(),
        "cartesianY": points[:, 1].copy(),
        "cartesianZ": points[:, 2].copy(),
        "timeStamp": np.asarray(times, dtype=np.float64).copy(),
    }
    if time_invalid is not None:
        columns["isTimeStampInvalid"] = np.asarray(time_invalid, dtype=np.int8)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "timed.e57"
        with pye57.E57(str(path), mode="w") as writer:
            image = writer.image_file
            scan = libe57.StructureNode(image)
            scan.set("guid", libe57.StringNode(image, f"{{{uuid.uuid4()}}}"))
            scan.set("name", libe57.StringNode(image, "timed scan"))
            prototype = libe57.StructureNode(image)
            low, high = points.min(axis=0), points.max(axis=0)
            for axis, name in enumerate(("cartesianX", "cartesianY", "cartesianZ")):
                prototype.set(
                    name,
                    libe57.FloatNode(
                        image, float(low[axis]), libe57.E57_SINGLE, float(low[axis]),
                        float(high[axis]),
                    ),
                )  # fmt: skip
            first, last = float(columns["timeStamp"].min()), float(columns["timeStamp"].max())
            prototype.set(
                "timeStamp", libe57.FloatNode(image, first, libe57.E57_DOUBLE, first, last)
            )
            if time_invalid is not None:
                prototype.set("isTimeStampInvalid", libe57.IntegerNode(image, 0, 0, 1))
            points_node = libe57.CompressedVectorNode(
                image, prototype, libe57.VectorNode(image, True)
            )
            scan.set("points", points_node)
            writer.data3d.append(scan)
            buffers = libe57.VectorSourceDestBuffer()
            for name, values in columns.items():
                buffers.append(
                    libe57.SourceDestBuffer(image, name, values, len(values), True, True)
                )
            stream = points_node.writer(buffers)
            stream.write(len(points))
            stream.close()
        return path.read_bytes()

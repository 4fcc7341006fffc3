"""viser's websocket protocol as a test client speaks it: the subprotocol, a camera message, frames.

A viser client announces ``viser-v<version>``; the server sends frames of
``[8 B msgpack size][8 B compressed size][zstd msgpack][padding][binary buffers]`` holding
``{"messages": [...], "binaryBufferLengths": [...]}`` where numpy arrays are placeholders
``{"__binary_index": i, "dtype": ...}``.  A client's own scene (the 3D view's layers and boxes)
is only sent after the client reports its camera, as the browser does.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import msgspec.msgpack
import numpy as np
import viser
import zstandard
from viser import _messages

VISER_SUBPROTOCOL = f"viser-v{viser.__version__}"


def camera_message() -> bytes:
    """A ``ViewerCameraMessage`` as the browser's client sends it on connecting."""
    message = _messages.ViewerCameraMessage(
        wxyz=(1.0, 0.0, 0.0, 0.0),
        position=(0.0, 0.0, 10.0),
        fov=1.0,
        near=0.01,
        far=1000.0,
        image_height=480,
        image_width=640,
        look_at=(0.0, 0.0, 0.0),
        up_direction=(0.0, 0.0, 1.0),
    )
    return msgspec.msgpack.encode(message.as_serializable_dict())


def _with_arrays(value: Any, buffers: list[np.ndarray]) -> Any:
    """``value`` with binary placeholders replaced by their arrays."""
    if isinstance(value, dict):
        if "__binary_index" in value and "dtype" in value:
            return buffers[value["__binary_index"]].view(np.dtype(value["dtype"]))
        return {key: _with_arrays(item, buffers) for key, item in value.items()}
    if isinstance(value, list):
        return [_with_arrays(item, buffers) for item in value]
    return value


def decode_frame(frame: bytes) -> list[dict[str, Any]]:
    """The messages of one binary frame from a viser server (arrays as numpy arrays)."""
    inner_size = int.from_bytes(frame[:8], "little")
    compressed_size = int.from_bytes(frame[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(
        frame[16 : 16 + compressed_size], max_output_size=inner_size
    )
    payload = msgspec.msgpack.decode(inner)
    offset = 16 + compressed_size
    buffers = []
    for length in payload["binaryBufferLengths"]:
        offset += (8 - offset % 8) % 8
        buffers.append(np.frombuffer(frame, dtype=np.uint8, count=length, offset=offset))
        offset += length
    return [_with_arrays(message, buffers) for message in payload["messages"]]


def receive_messages(
    connection: Any,
    until: Callable[[list[dict[str, Any]]], bool],
    timeout: float = 30.0,
) -> list[dict[str, Any]]:
    """Messages from a ``websockets.sync`` connection until ``until(messages)`` holds."""
    messages: list[dict[str, Any]] = []
    deadline = time.monotonic() + timeout
    while not until(messages):
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            types = sorted({message["type"] for message in messages})
            raise TimeoutError(f"viser sent {len(messages)} messages ({types}) but not enough")
        frame = connection.recv(timeout=remaining)
        assert isinstance(frame, bytes), f"viser sent text: {frame!r}"
        messages.extend(decode_frame(frame))
    return messages


def point_clouds(messages: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """The point clouds among ``messages``: scene name -> (n, 3) float32 positions."""
    clouds = {}
    for message in messages:
        if message["type"] == "PointCloudMessage":
            points = message["props"]["points"]
            clouds[message["name"]] = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    return clouds

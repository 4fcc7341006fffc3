"""The ``sensor_origin`` of an upload: one station's ``x,y,z`` or a JSON list of stations.

One origin is kept as ``[x, y, z]``; several (a cloud merged from several scanner stations) as
``[[x, y, z], ...]``, in the order of the file's per-point station index when it has one
(``station_index``, ``station`` or ``scan_index`` fields; an E57 file's scans).  Both are
stored as given on the scan and used by its comparisons.
"""

from __future__ import annotations

import json
import math
from typing import Any, NoReturn

from app.services.errors import ValidationFailedError

MAX_STATIONS = 1024
"""Most origins one upload may list."""

SensorOrigin = list[float] | list[list[float]]
"""One origin ``[x, y, z]`` or one per station ``[[x, y, z], ...]``."""

_HOW = (
    "give 'x,y,z' for one station, or a JSON list of stations '[[x,y,z],[x,y,z],...]', in the "
    "file's frame (e.g. 0,0,0 for a scan in its sensor's frame)"
)


def parse_sensor_origin(text: str | None) -> SensorOrigin | None:
    """``"x,y,z"``, ``"[x,y,z]"`` or ``"[[x,y,z], ...]"`` as finite floats; 422 otherwise."""
    if text is None or text.strip() == "":
        return None
    stripped = text.strip()
    if stripped.startswith("["):
        try:
            value: Any = json.loads(stripped)
        except (json.JSONDecodeError, RecursionError):
            _refuse(f"sensor_origin is not valid JSON ({text[:80]!r})")
    else:
        value = stripped.split(",")
    if isinstance(value, list) and value and all(isinstance(item, list) for item in value):
        if len(value) > MAX_STATIONS:
            _refuse(f"sensor_origin lists {len(value)} stations; at most {MAX_STATIONS}")
        origins = [_triple(item, f"station {index}'s origin") for index, item in enumerate(value)]
        return origins[0] if len(origins) == 1 else origins
    return _triple(value, "sensor_origin")


def check_stations_match(origin: SensorOrigin | None, n_stations: int | None) -> None:
    """422 when the file's per-point station index names more stations than origins given."""
    if origin is None or n_stations is None:
        return
    given = len(origin) if isinstance(origin[0], list) else 1
    if given < n_stations:
        raise ValidationFailedError(
            f"the file's per-point station index names {n_stations} stations (0 .. "
            f"{n_stations - 1}) but sensor_origin gives {given} origin(s): give one origin per "
            "station, in the order of the index, as a JSON list '[[x,y,z],...]', or leave "
            "sensor_origin out to use the file's own",
            code="invalid_sensor_origin",
        )


def _triple(value: Any, name: str) -> list[float]:
    """Three finite floats from a list of numbers or numeric strings."""
    numbers: list[float] = []
    if isinstance(value, list):
        for item in value:
            if isinstance(item, bool) or not isinstance(item, int | float | str):
                break
            try:
                numbers.append(float(item))
            except ValueError:
                break
    if len(numbers) != 3 or len(numbers) != len(value):
        _refuse(f"{name} must be three numbers x,y,z, got {json.dumps(value)[:80]}")
    if not all(math.isfinite(number) for number in numbers):
        _refuse(f"{name} must be three finite numbers, got {numbers}")
    return numbers


def _refuse(reason: str) -> NoReturn:
    raise ValidationFailedError(f"{reason}; {_HOW}", code="invalid_sensor_origin")

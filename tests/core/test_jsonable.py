"""json_safe: what the CLI prints and the worker stores is plain, portable JSON."""

from __future__ import annotations

import json

import numpy as np

from app.core.jsonable import json_safe


def test_numpy_values_become_plain_json_and_non_finite_numbers_null():
    value = {
        "transform": np.eye(2),
        "fitness": np.float32(0.5),
        "count": np.int64(3),
        "flag": np.bool_(True),
        "rmse": float("inf"),
        "nested": ({"nan": np.float64("nan")}, [1, 2.5]),
    }
    converted = json_safe(value)
    assert converted == {
        "transform": [[1.0, 0.0], [0.0, 1.0]],
        "fitness": 0.5,
        "count": 3,
        "flag": True,
        "rmse": None,
        "nested": [{"nan": None}, [1, 2.5]],
    }
    assert type(converted["count"]) is int and type(converted["flag"]) is bool
    json.dumps(converted, allow_nan=False)  # strict JSON

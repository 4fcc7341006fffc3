"""Plain-JSON conversion of results: the CLI's ``--json``, the worker's database rows."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np


def json_safe(value: Any) -> Any:
    """``value`` with numpy scalars/arrays turned into Python types and NaN/inf into None.

    Parameters
    ----------
    value : any
        Nested mappings, lists, tuples, numpy arrays of any shape, scalars.

    Returns
    -------
    any
        The same structure made only of dict, list, str, int, float (finite), bool and None.
    """
    if isinstance(value, Mapping):
        return {str(key): json_safe(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(item) for item in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value

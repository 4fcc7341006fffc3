"""The core's one parameter validator: a :class:`ParamSpec` table and :func:`validate_parameters`.

Detectors (:mod:`app.core.detectors.base`), localisation (:mod:`app.core.localise.settings`)
and the pipeline's registration stage (:mod:`app.core.pipeline`) each describe their keyword
parameters as a ``{name: ParamSpec}`` table and check what a caller gave with
:func:`validate_parameters`; every bad name or value is an :class:`InputError` naming it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.core.errors import InputError

__all__ = ["ParamSpec", "validate_parameters"]

KINDS = ("any", "int", "float", "choice", "voxel", "positive", "positive_int")


@dataclass(frozen=True)
class ParamSpec:
    """How one keyword parameter is validated.

    Attributes
    ----------
    kind : {"any", "int", "float", "choice", "voxel", "positive", "positive_int"}
        ``any`` accepts every value unchanged (only the name is checked).  ``int`` and
        ``float`` accept Python and numpy numbers within ``[low, high]``; ``voxel`` accepts
        ``"auto"`` or a float >= 0 (0 switches voxelisation off); ``choice`` one of
        ``choices``.  ``positive`` accepts a finite Python number > 0 (at most ``high``) and
        returns a float; ``positive_int`` a positive number that is an integer >= ``low``.
    low, high : float or None
        Inclusive bounds for numbers.
    choices : tuple of str
        Allowed values for ``choice``.
    optional : bool
        None is accepted and kept (e.g. "calibrate it from the data").
    """

    kind: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    optional: bool = False

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {list(KINDS)}, got {self.kind!r}")

    def check(self, name: str, value: Any) -> Any:
        """Return ``value`` normalised to a JSON type, or raise :class:`InputError`."""
        if self.kind == "any" or (self.optional and value is None):
            return value
        if self.kind in ("positive", "positive_int"):
            return self._check_positive(name, value)
        if self.kind == "choice":
            if value not in self.choices:
                raise InputError(f"{name} must be one of {list(self.choices)}, got {value!r}")
            return str(value)
        if self.kind == "voxel" and value == "auto":
            return "auto"
        if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
            raise InputError(f"{name} must be a number, got {value!r}")
        if self.kind == "int":
            if int(value) != value:
                raise InputError(f"{name} must be an integer, got {value!r}")
            value = int(value)
        else:
            value = float(value)
            if not math.isfinite(value):
                raise InputError(f"{name} must be finite, got {value!r}")
        low = 0.0 if self.kind == "voxel" else self.low
        if low is not None and value < low:
            raise InputError(f"{name} must be >= {low:g}, got {value!r}")
        if self.high is not None and value > self.high:
            raise InputError(f"{name} must be <= {self.high:g}, got {value!r}")
        return value

    def _check_positive(self, name: str, value: Any) -> float | int:
        """``positive`` and ``positive_int``: Python numbers only (bools are not numbers)."""
        if isinstance(value, bool) or not (
            isinstance(value, int | float) and math.isfinite(value) and value > 0
        ):
            raise InputError(f"{name} must be a positive number, got {value!r}")
        number = float(value)
        if self.kind == "positive_int":
            low = 1.0 if self.low is None else self.low
            if number != int(number) or number < low:
                raise InputError(f"{name} must be an integer >= {low:g}, got {value!r}")
            return int(number)
        if self.high is not None and number > self.high:
            raise InputError(f"{name} must be in (0, {self.high:g}], got {value}")
        return number


def validate_parameters(
    specs: Mapping[str, ParamSpec],
    given: Mapping[str, Any],
    *,
    stage: str = "",
    owner: str = "",
    defaults: Mapping[str, Any] | None = None,
    also_valid: Iterable[str] = (),
) -> dict[str, Any]:
    """Check keyword parameters against their table and return them normalised.

    Parameters
    ----------
    specs : mapping of str to ParamSpec
        Every accepted name, in the order the result lists them.
    given : mapping of str to object
        What the caller passed.
    stage, owner : str
        Name whose parameters these are in the message about unknown names:
        ``"unknown {stage} parameter(s) [...] for {owner}; valid: [...]"`` (each part only
        when given).
    defaults : mapping, optional
        Every name of ``specs`` with its default: the result then holds every parameter,
        ``given`` over ``defaults``, defaults checked too.  Without it, only ``given``.
    also_valid : iterable of str
        Names accepted elsewhere by the same caller, listed as valid in that message.

    Returns
    -------
    dict
        Name to normalised value (see :meth:`ParamSpec.check`).

    Raises
    ------
    InputError
        An unknown name (all of them listed, with the valid ones) or the first bad value.
    """
    unknown = sorted(set(given) - set(specs))
    if unknown:
        stage_words = f"{stage} " if stage else ""
        owner_words = f" for {owner}" if owner else ""
        raise InputError(
            f"unknown {stage_words}parameter(s) {unknown}{owner_words}; "
            f"valid: {sorted([*specs, *also_valid])}"
        )
    if defaults is None:
        return {name: specs[name].check(name, value) for name, value in given.items()}
    values = {**defaults, **given}
    return {name: spec.check(name, values[name]) for name, spec in specs.items()}

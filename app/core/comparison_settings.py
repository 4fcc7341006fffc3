"""A comparison's parameters: validated once, split by stage, and the decision rules.

:func:`parse_comparison_params` is what both :func:`app.core.pipeline.compare` and the service
(before it queues a job) call, so a parameter the worker would refuse is refused at once.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from app.core.detectors import make_detector
from app.core.detectors.base import ChangeDetector
from app.core.errors import InputError
from app.core.localise.settings import as_origins
from app.core.origins.station_recovery import as_recover_setting
from app.core.parameters import ParamSpec, validate_parameters
from app.core.registration import register_scan

DECISION_RULES = ("regions", "either", "detector")
"""How ``changed`` is decided:

``"regions"`` (default)
    localisation found at least one region of changed points: points farther from the other
    cloud's local surface than a threshold calibrated from the measured noise and local point
    spacing, seen by the other sensor (not unobserved), in a connected cluster above the size
    floor that spurious edge clusters never reach.  It is the default because the global
    detectors' threshold models resampling noise, not the change of viewpoint between two
    rescans (``bench/scenes.py``; figures in ``docs/performance.md``).
``"either"``
    the global score exceeds its calibrated threshold, or a region was found.
``"detector"``
    the paper's rule: the global EMD score against its calibrated threshold only.

Whatever the rule, the global score, its threshold and the detector's own verdict are
reported (``calibration["decision"]``).
"""


@dataclass(frozen=True)
class ComparisonSettings:
    """A comparison's parameters, split by stage and validated."""

    detector: ChangeDetector
    align: bool
    registration: dict[str, Any]
    localisation: dict[str, Any]
    reference_origin: Any
    scan_origin: Any
    decision: str
    estimate_origins: bool = True
    recover_stations: bool | str = "auto"


INTERNAL_REGISTRATION_ARGUMENTS = frozenset({"reference_memory"})
"""Arguments of :func:`register_scan` that are not user parameters (the geometry cache's
reference facts, passed by the pipeline)."""

REGISTRATION_SPECS: dict[str, ParamSpec] = {
    name: ParamSpec("any")
    for name, parameter in inspect.signature(register_scan).parameters.items()
    if parameter.kind == parameter.KEYWORD_ONLY and name not in INTERNAL_REGISTRATION_ARGUMENTS
}
"""The registration stage's keyword parameters: those :func:`register_scan` takes (values are
checked by the registration itself), less the ones the pipeline passes itself."""


def parse_comparison_params(
    method: str,
    variant: str,
    params: Mapping[str, Any] | None,
    *,
    random_state: int = 0,
    align: bool = True,
) -> ComparisonSettings:
    """Validate and split a comparison's ``params`` (see :func:`compare`).

    Parameters stored with an earlier result (``result.params``) replay it exactly: their
    ``random_state`` and ``align`` take precedence over the keyword arguments.

    Raises
    ------
    InputError
        Unknown method, variant or parameter, or a value of the wrong type.
    """
    if params is not None and not isinstance(params, Mapping):
        raise InputError("params must be an object of keyword parameters")
    remaining = dict(params or {})
    random_state = remaining.pop("random_state", random_state)
    if isinstance(random_state, bool) or not isinstance(random_state, int):
        raise InputError(f"random_state must be an integer, got {random_state!r}")
    align = remaining.pop("align", align)
    if not isinstance(align, bool):
        raise InputError(f"align must be true or false, got {align!r}")
    stored_variant = remaining.pop("variant", variant)
    if stored_variant != variant:
        raise InputError(
            f"params say variant {stored_variant!r} but variant {variant!r} was requested"
        )
    stage_params: dict[str, dict[str, Any]] = {}
    for stage in ("registration", "localisation"):
        value = remaining.pop(stage, None) or {}
        if not isinstance(value, Mapping):
            raise InputError(f"{stage} must be an object of keyword parameters, got {value!r}")
        stage_params[stage] = dict(value)
    validate_parameters(REGISTRATION_SPECS, stage_params["registration"], stage="registration")
    decision = remaining.pop("decision", DECISION_RULES[0])
    if decision not in DECISION_RULES:
        raise InputError(f"decision must be one of {', '.join(DECISION_RULES)}, got {decision!r}")
    reference_origin = remaining.pop("reference_origin", None)
    scan_origin = remaining.pop("scan_origin", None)
    estimate_origins = remaining.pop("estimate_origins", True)
    if not isinstance(estimate_origins, bool):
        raise InputError(f"estimate_origins must be true or false, got {estimate_origins!r}")
    recover = as_recover_setting(remaining.pop("recover_stations", "auto"))
    for origin, name in ((reference_origin, "reference_origin"), (scan_origin, "scan_origin")):
        as_origins(origin, name)  # validates: 3 numbers or a list of them
    try:
        detector = make_detector(method, variant, random_state=random_state, **remaining)
    except TypeError as exc:
        raise InputError(f"invalid parameters for {method}/{variant}: {exc}") from exc
    return ComparisonSettings(
        detector=detector,
        align=align,
        registration=stage_params["registration"],
        localisation=stage_params["localisation"],
        reference_origin=reference_origin,
        scan_origin=scan_origin,
        decision=decision,
        estimate_origins=estimate_origins,
        recover_stations=recover,
    )

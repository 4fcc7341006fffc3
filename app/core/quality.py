"""Quality warnings on a comparison: what makes a result less trustworthy than it looks.

A comparison of two scans of different places, or one the alignment had to turn a lot, can
still "succeed" with many regions.  :func:`quality_warnings` says so, from the result alone:

``low_registration_fitness``
    fewer than :data:`LOW_FITNESS` of the scan's (downsampled) points lie near the reference
    after alignment.
``large_rotation`` / ``large_translation``
    the alignment turned the scan by more than :data:`LARGE_ROTATION_DEGREES` or moved its
    centre by more than :data:`LARGE_TRANSLATION_METRES`.
``low_overlap``
    less than :data:`LOW_OVERLAP_FRACTION` of a cloud's points were observed by the other
    scan (the rest is ``unobserved``: no evidence either way).
``sensor_origin_unknown``
    no sensor origin is known for a cloud (none given, none in the file, none estimated):
    occlusion cannot be told from removal.
``sensor_origin``
    an origin was given but the data contradict it (the origins' own warnings).
``trajectory_time_span``
    some of a cloud's points have times outside its trajectory's span (fewer than half: more
    is refused as bad input): they take the trajectory's end poses, so their sensor positions
    are guesses.

The site's history (a region count far above the site's usual) needs the database; the
service adds it.  Every warning is a :class:`QualityWarning`, stored as
``{"code", "message", "detail", "how_to_fix", ...}`` (:meth:`QualityWarning.to_json_dict`):
``message`` is one sentence with units; ``detail`` holds the measured ``value``, the ``limit``
it crossed, ``unit``, ``side`` where there is one and an ``explanation`` (what it means for the
result); ``how_to_fix`` is ``{"action"}``, one of :data:`FIX_ACTIONS`.  The core names no
interface's knobs: the API and the CLI add ``how_to_fix["text"]`` naming their own parameter,
setting or flag (``app.services.messages``, ``app.cli.compare``).  ``value``, ``limit``,
``unit`` and ``side`` are also kept at the top level, as before.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from app.core.comparison.reports import FIX_ACTIONS as FIX_ACTIONS
from app.core.comparison.reports import QualityWarning
from app.core.labels import LABEL_UNOBSERVED

if TYPE_CHECKING:
    from app.core.comparison.protocol import Comparison

LOW_FITNESS = 0.6
"""Registration fitness below which the alignment (or the pairing of the scans) is suspect.
Rescans of one place align at 0.9 and more (``docs/performance.md``); two different street
frames reached 0.39."""

LARGE_ROTATION_DEGREES = 2.0
"""An alignment turning the scan by more than this (degrees) is reported: files in one world
frame rarely need it, and a wrong alignment often looks like that."""

LARGE_TRANSLATION_METRES = 0.5
"""An alignment moving the scan's centre by more than this (metres) is reported."""

LOW_OVERLAP_FRACTION = 0.5
"""A cloud of which less than this fraction was observed by the other scan: most of it is
``unobserved``, so the decision rests on a small part of the place."""


def registration_warnings(
    registration: Mapping[str, Any],
    *,
    low_fitness: float = LOW_FITNESS,
    large_rotation_degrees: float = LARGE_ROTATION_DEGREES,
    large_translation_metres: float = LARGE_TRANSLATION_METRES,
) -> list[QualityWarning]:
    """Warnings about the alignment, from a result's ``registration`` report.

    Parameters
    ----------
    registration : mapping
        ``fitness`` (fraction in [0, 1]), ``rotation_degrees``, ``translation_m`` (how far the
        alignment moved the scan's centre, metres), ``max_correspondence_distance`` (metres)
        and ``enabled`` (False: ``--no-align``); missing keys are not checked.
    low_fitness, large_rotation_degrees, large_translation_metres : float
        The limits (defaults: the module's constants).

    Returns
    -------
    list of QualityWarning
    """
    warnings: list[QualityWarning] = []
    aligned = registration.get("enabled", True) is not False
    fitness = _finite(registration.get("fitness"))
    if fitness is not None and fitness < low_fitness:
        distance = _finite(registration.get("max_correspondence_distance"))
        within = f" within {distance:.3g} m of the reference" if distance is not None else ""
        after = " after alignment" if aligned else " (not aligned)"
        warnings.append(
            QualityWarning(
                "low_registration_fitness",
                f"Only {fitness:.0%} of the scan's points lie{within}{after} "
                f"(registration fitness {fitness:.2f}, below {low_fitness:g}).",
                "the scans may be of different places or badly aligned, so regions may be false",
                "check_pairing",
                value=fitness,
                limit=low_fitness,
            )
        )
    if not aligned:
        return warnings
    rotation = _finite(registration.get("rotation_degrees"))
    if rotation is not None and rotation > large_rotation_degrees:
        warnings.append(
            QualityWarning(
                "large_rotation",
                f"The alignment rotated the scan by {rotation:.1f} degrees (more than "
                f"{large_rotation_degrees:g} degrees).",
                "scans of one place in one frame rarely need such a turn; a wrong match often "
                "looks like this",
                "check_alignment",
                value=rotation,
                limit=large_rotation_degrees,
                unit="degrees",
            )
        )
    translation = _finite(registration.get("translation_m"))
    if translation is not None and translation > large_translation_metres:
        warnings.append(
            QualityWarning(
                "large_translation",
                f"The alignment moved the scan's centre by {translation:.2f} m (more than "
                f"{large_translation_metres:g} m).",
                "scans of one place in one frame rarely need such a shift; a wrong match often "
                "looks like this",
                "check_alignment",
                value=translation,
                limit=large_translation_metres,
                unit="m",
            )
        )
    return warnings


def overlap_warnings(
    reference_label: NDArray[np.integer],
    scan_label: NDArray[np.integer],
    *,
    low_overlap: float = LOW_OVERLAP_FRACTION,
) -> list[QualityWarning]:
    """A warning when too little of either cloud was observed by the other scan.

    Parameters
    ----------
    reference_label, scan_label : ndarray, shape (n,) and (m,), int
        Per-point labels (-1 unobserved or dropped, 0 unchanged, 1 changed).
    low_overlap : float
        The limit (default :data:`LOW_OVERLAP_FRACTION`).

    Returns
    -------
    list of QualityWarning
        At most one warning, about the less observed cloud.
    """
    observed = {
        side: float(np.count_nonzero(labels != LABEL_UNOBSERVED) / len(labels))
        for side, labels in (("reference", reference_label), ("scan", scan_label))
        if len(labels)
    }
    if not observed:
        return []
    side = min(observed, key=lambda name: observed[name])
    fraction = observed[side]
    if fraction >= low_overlap:
        return []
    other = "scan" if side == "reference" else "reference"
    return [
        QualityWarning(
            "low_overlap",
            f"Only {fraction:.0%} of the {side}'s points were observed by the {other} (less "
            f"than {low_overlap:.0%}).",
            "the rest is unobserved, so the decision rests on a small part of the place",
            "widen_coverage",
            value=fraction,
            limit=low_overlap,
            side=side,
        )
    ]


def origin_warnings(
    sensor_origins: Mapping[str, Sequence[Mapping[str, Any]]] | None,
    origin_messages: Sequence[str] = (),
) -> list[QualityWarning]:
    """Warnings about the sensor origins: unknown ones, and those the data contradicted.

    Parameters
    ----------
    sensor_origins : mapping or None
        ``{"reference": [...], "scan": [...]}``, each a list of ``{origin, source,
        confidence}`` (empty: no origin known).  A side not reported is not checked.
    origin_messages : sequence of str
        The origins' own warnings (``ComparisonResult.warnings``).

    Returns
    -------
    list of QualityWarning
    """
    warnings = [
        QualityWarning("sensor_origin", _sentence(str(text)), str(text), "check_sensor_origin")
        for text in origin_messages
    ]
    for side in ("reference", "scan"):
        for entry in (sensor_origins or {}).get(side) or ():
            if not isinstance(entry, Mapping) or entry.get("source") != "trajectory":
                continue
            outside = entry.get("points_outside")
            if isinstance(outside, int) and outside > 0:
                warnings.append(_time_span_warning(side, outside, entry.get("time_span")))
        if sensor_origins is not None and side in sensor_origins and not sensor_origins[side]:
            warnings.append(
                QualityWarning(
                    "sensor_origin_unknown",
                    f"The {side}'s sensor origin is unknown (none given, none in the file, "
                    "none estimated with confidence).",
                    "points hidden from one sensor cannot be told from removed ones, so some "
                    "regions may be shadows",
                    "give_sensor_origin",
                    side=side,
                )
            )
    return warnings


def _time_span_warning(side: str, outside: int, span: Any) -> QualityWarning:
    """``trajectory_time_span``: ``outside`` points of ``side`` lie outside its trajectory's
    time span ``[first, last]``."""
    within = ""
    if isinstance(span, Sequence) and len(span) == 2:
        within = f" ({float(span[0]):.3f}..{float(span[1]):.3f} s)"
    return QualityWarning(
        "trajectory_time_span",
        f"{outside:,} of the {side}'s points have times outside its trajectory's time "
        f"span{within}.",
        "their sensor positions are the trajectory's end poses, not where the sensor was: "
        "regions near them may be shadows",
        "check_trajectory",
        value=outside,
        unit="points",
        side=side,
    )


def quality_warnings(result: Comparison) -> list[QualityWarning]:
    """Every warning :mod:`app.core.quality` can tell from a comparison result (its
    ``registration``, labels, ``sensor_origins`` and the origins' ``warnings``).

    A result computes them once (``result.quality_warnings``); each is stored as its
    :meth:`QualityWarning.to_json_dict`.
    """
    warnings = registration_warnings(result.registration.to_json_dict())
    warnings += overlap_warnings(np.asarray(result.reference_label), np.asarray(result.scan_label))
    warnings += origin_warnings(result.sensor_origins_json(), list(result.warnings or []))
    return warnings


def _sentence(text: str) -> str:
    """The first sentence of ``text`` (up to its first ``; `` or ``: ``), capitalised, with a
    full stop."""
    head = text.strip()
    for separator in ("; ", ": "):
        head = head.split(separator, 1)[0]
    head = head.rstrip(" .")
    return (head[:1].upper() + head[1:] + ".") if head else text


def _finite(value: Any) -> float | None:
    """``value`` as a finite float, else None."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
        return None
    number = float(value)
    return number if math.isfinite(number) else None

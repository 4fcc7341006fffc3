"""Why a comparison decided what it decided, as data and as one line of text.

The decision rule is :data:`app.core.comparison_settings.DECISION_RULES`: by default
(``"regions"``) a scan is *changed* when localisation kept at least one region of changed
points of at least ``min_region_points`` points, whatever the global detector's score.  A
reader who sees "score 0.037, threshold 0.042: changed" is misled unless the page says so; the
explanation says which evidence decided and what the other evidence said::

    changed: 1 region of 1,282 points (>= 200 each), largest 0.82 x 0.82 x 1.00 m; the
    detector's score 0.037 is below its threshold 0.0424 (the regions decide)

:func:`explain_decision` works from plain values (a stored job's columns, or a result);
:func:`explain_comparison` from a :class:`~app.core.pipeline.ComparisonResult`.  Both give an
:class:`Explanation`, stored as its :meth:`Explanation.to_json_dict`; a result computes its own
once (``result.explanation``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from app.core.comparison.reports import Explanation, LargestRegion

if TYPE_CHECKING:
    from app.core.comparison.protocol import Comparison

RULE_DECIDES = {
    "regions": "the regions decide",
    "detector": "the detector decides",
    "either": "changed if the regions or the detector say so",
}
"""How each decision rule is named in the one-line text."""


def _number(value: float | None) -> str:
    """Three significant digits, or "unknown"."""
    if value is None or not math.isfinite(value):
        return "unknown"
    return f"{value:.3g}"


def _region_size(region: Any) -> tuple[float, ...]:
    """Bounding-box extents of a region (metres), shape (3,)."""
    low = _field(region, "bbox_min")
    high = _field(region, "bbox_max")
    return tuple(
        round(float(top) - float(bottom), 3) for bottom, top in zip(low, high, strict=True)
    )


def _field(item: Any, name: str) -> Any:
    """``item[name]`` of a mapping, else ``item.name`` (a region row or summary)."""
    return item[name] if isinstance(item, Mapping) else getattr(item, name)


def explain_decision(
    *,
    changed: bool,
    rule: str,
    score: float | None,
    threshold: float | None,
    detector_changed: bool | None,
    regions: Sequence[Any],
    min_region_points: int | None = None,
    dropped_clusters: int | None = None,
    site_test: Mapping[str, Any] | None = None,
) -> Explanation:
    """The structured explanation of one decision and its one-line ``text``.

    Parameters
    ----------
    changed : bool
        The decision.
    rule : {"regions", "detector", "either"}
        The decision rule in effect (``calibration["decision"]["rule"]``).
    score, threshold : float or None
        The global detector's score and calibrated threshold.
    detector_changed : bool or None
        The detector's own verdict (None: unknown, then ``score > threshold``).
    regions : sequence of RegionSummary, Region rows or mappings
        Each with ``kind``, ``n_points``, ``bbox_min`` and ``bbox_max`` (3 numbers, metres).
    min_region_points : int, optional
        The size floor a cluster of changed points had to reach to be a region.
    dropped_clusters : int, optional
        Clusters of changed points dropped for being below that floor.
    site_test : mapping, optional
        The decision test that used the site's learned threshold
        (:func:`app.core.site_calibration.decide`: ``statistic``, ``value``, ``threshold``,
        ``fires``), when one did; the text then says the site's threshold decided.

    Returns
    -------
    Explanation
        ``decision`` ("changed"/"unchanged"), ``rule``, ``decided_by``, ``n_regions``,
        ``n_region_points``, ``min_region_points``, ``dropped_clusters``, ``largest_region``
        (``index``, ``kind``, ``n_points``, ``size_m``: 3 extents in metres; None without
        regions), ``score``, ``threshold``, ``detector_changed``, ``agrees`` (whether the
        regions and the detector say the same), ``site_test`` and ``text``.
    """
    if detector_changed is None and score is not None and threshold is not None:
        detector_changed = bool(score > threshold)
    n_regions = len(regions)
    n_region_points = int(sum(int(_field(region, "n_points")) for region in regions))
    largest = None
    if regions:
        index = max(range(n_regions), key=lambda number: int(_field(regions[number], "n_points")))
        largest = LargestRegion(
            index=index,
            kind=str(_field(regions[index], "kind")),
            n_points=int(_field(regions[index], "n_points")),
            size_m=_region_size(regions[index]),
        )
    decided_by = {"regions": "regions", "detector": "detector"}.get(rule)
    if rule == "either":
        decided_by = (
            " and ".join(
                name
                for name, said in (("regions", n_regions > 0), ("detector", bool(detector_changed)))
                if said
            )
            or "regions and detector"
        )
    return Explanation(
        decision="changed" if changed else "unchanged",
        rule=rule,
        decided_by=decided_by or rule,
        n_regions=n_regions,
        n_region_points=n_region_points,
        min_region_points=min_region_points,
        dropped_clusters=dropped_clusters,
        largest_region=largest,
        score=score,
        threshold=threshold,
        detector_changed=detector_changed,
        agrees=detector_changed is None or bool(detector_changed) == (n_regions > 0),
        site_test=dict(site_test) if site_test else None,
        text=_text(
            changed, rule, score, threshold, detector_changed, n_regions, n_region_points,
            min_region_points, dropped_clusters, largest,
        ) + _site_text(site_test),
    )  # fmt: skip


STATISTIC_NAMES = {
    "largest_region_extent_m": ("the largest region's extent", " m"),
    "score": ("the detector's score", ""),
}
"""How a site-calibrated statistic is named in the text, and its unit."""


def _site_text(site_test: Mapping[str, Any] | None) -> str:
    """ "; the site's learned threshold: ..." when a learned threshold took part, else ""."""
    if not site_test:
        return ""
    name, unit = STATISTIC_NAMES.get(str(site_test.get("statistic")), ("the statistic", ""))
    value, limit = site_test.get("value"), site_test.get("threshold")
    relation = "above" if site_test.get("fires") else "not above"
    return (
        f"; {name} {_number(value)}{unit} is {relation} the site's learned threshold "
        f"{_number(limit)}{unit} (from reviews)"
    )


def _text(
    changed: bool,
    rule: str,
    score: float | None,
    threshold: float | None,
    detector_changed: bool | None,
    n_regions: int,
    n_region_points: int,
    min_region_points: int | None,
    dropped_clusters: int | None,
    largest: LargestRegion | None,
) -> str:
    """The one line: the decision, the regions' evidence, the detector's, the rule."""
    floor = f" (>= {min_region_points:,} each)" if min_region_points else ""
    if n_regions:
        noun = "region" if n_regions == 1 else "regions"
        regions_part = f"{n_regions:,} {noun} of {n_region_points:,} points{floor}"
        if largest is not None:
            size = " x ".join(f"{extent:.2f}" for extent in largest.size_m)
            regions_part += f", largest {size} m" if n_regions > 1 else f", {size} m"
    else:
        regions_part = f"no region of changed points{floor}"
        if dropped_clusters:
            noun = "cluster" if dropped_clusters == 1 else "clusters"
            regions_part += f" ({dropped_clusters:,} smaller {noun} dropped)"
    if score is None or threshold is None:
        detector_part = "the detector's score is unknown"
    else:
        relation = "above" if detector_changed else "below"
        detector_part = (
            f"the detector's score {_number(score)} is {relation} its threshold "
            f"{_number(threshold)}"
        )
    decision = "changed" if changed else "no change"
    if rule == "detector":
        rule_part = RULE_DECIDES[rule]
        return f"{decision}: {detector_part}; localisation found {regions_part} ({rule_part})"
    return f"{decision}: {regions_part}; {detector_part} ({RULE_DECIDES.get(rule, rule)})"


def explain_comparison(result: Comparison) -> Explanation:
    """:func:`explain_decision` of a :class:`~app.core.pipeline.ComparisonResult`.

    Reads ``changed``, ``score``, ``threshold``, ``regions``, ``calibration.decision`` and
    ``localisation``.
    """
    decision = result.calibration.decision
    localisation = result.localisation or {}
    min_points = localisation.get("min_region_points")
    dropped = localisation.get("n_dropped_clusters")
    return explain_decision(
        changed=bool(result.changed),
        rule=str(decision.rule),
        score=None if result.score is None else float(result.score),
        threshold=None if result.threshold is None else float(result.threshold),
        detector_changed=decision.detector_changed,
        regions=list(result.regions),
        min_region_points=None if min_points is None else int(min_points),
        dropped_clusters=None if dropped is None else int(dropped),
        site_test=next(
            (test.to_json_dict() for test in decision.tests if test.source == "site"), None
        ),
    )

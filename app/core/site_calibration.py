"""Per-site thresholds learned from reviewed jobs, and the decision that applies them.

A comparison decides ``changed`` by a rule
(:data:`app.core.comparison_settings.DECISION_RULES`); each rule is one or two *tests* of a
statistic against a threshold:

``"regions"``
    ``largest_region_extent_m > 0``: a region of changed points survived the localiser's size
    floor (``min_region_points``); the statistic is the bounding-box diagonal in metres of the
    largest region, the one with the most points (the region the explanation calls largest,
    :func:`app.core.explanation.explain_decision`), 0 when no region survived.
``"detector"``
    ``score > threshold``: the detector's global score against its calibrated threshold.
``"either"``
    either test fires.

A site whose reviewers keep marking the same kind of alarm as false learns its own bar.
The region statistic is a size in metres, not a point count: the same object yields 30 to
110 points depending on where the sensor stood, but a bounding box within 0.65-0.87 m
(``bench/calibration.py``'s moving bin), so a bar learned on it separates a recurring small
nuisance from a larger real change much better.

The stated rule (split conformal)
---------------------------------
Let ``s_1 .. s_n`` be a statistic on the site's ``n`` *reviewed-null* jobs: jobs with the
verdict ``false_alarm``, or ``confirmed`` on a job that decided ``unchanged``.  With
``alpha`` the site's target false-alarm rate and ``k = ceil((n + 1) (1 - alpha))``, the learned
threshold is ``q = s_(k)``, the ``k``-th smallest value (``n >= k`` is needed, so at least
``ceil(1 / alpha) - 1`` samples; the service also asks for a minimum count).  If the next
job's statistic ``s`` is exchangeable with ``s_1 .. s_n`` (the same nuisance again, nothing
else), ``P(s > q) <= alpha``: a split-conformal upper prediction bound.  The job then fires
only when ``s > q`` (and the default test fires too: a learned threshold only raises the bar).

What it does not promise: reviewed jobs are chosen by people (mostly raised alarms), so they
are not a random sample of the site's null jobs; the bound is then conservative (higher than
needed), which costs sensitivity, not false alarms.  A real change smaller than the learned
nuisance (a region no larger than the largest learned false-alarm region) no longer fires.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

SITE_RULE = "split-conformal upper bound of reviewed-null jobs"
STATISTICS = ("largest_region_extent_m", "score")
"""The statistics a site learns a threshold for: what ``"regions"`` and ``"detector"`` test."""
MAX_SOURCE_IDS = 50
"""At most this many source job ids are listed in a calibration (the newest); ``n_samples``
always says how many there were."""


@dataclass(frozen=True)
class ReviewedSample:
    """One reviewed-null job of a site: its id and the statistics it produced."""

    job_id: str
    score: float
    largest_region_extent_m: float


def largest_extent(regions: Iterable[Any]) -> float:
    """The bounding-box diagonal (metres) of the largest region: the one with the most points.

    "Largest region" means the region with the most points everywhere (the explanation's
    ``largest_region``, the dashboard); the first of equals, as in the job's region order.

    Parameters
    ----------
    regions : iterable
        Objects (or mappings) with ``n_points``, ``bbox_min`` and ``bbox_max`` (3 numbers each).

    Returns
    -------
    float
        0.0 when there is no region.
    """

    def field(region: Any, name: str) -> Any:
        return region[name] if isinstance(region, Mapping) else getattr(region, name)

    largest = None
    for region in regions:
        if largest is None or int(field(region, "n_points")) > int(field(largest, "n_points")):
            largest = region
    if largest is None:
        return 0.0
    low = np.asarray(field(largest, "bbox_min"), float)
    high = np.asarray(field(largest, "bbox_max"), float)
    return float(np.linalg.norm(high - low))


def conformal_rank(n_samples: int, false_alarm_rate: float) -> int:
    """``k = ceil((n + 1) (1 - alpha))``, the rank of the conformal upper bound (1-based).

    Parameters
    ----------
    n_samples : int
        Number of calibration values ``n``.
    false_alarm_rate : float
        Target rate ``alpha`` in (0, 1).

    Returns
    -------
    int
        The rank; greater than ``n_samples`` when there are too few values for that rate.
    """
    if not 0.0 < false_alarm_rate < 1.0:
        raise ValueError(f"false_alarm_rate must be in (0, 1), got {false_alarm_rate}")
    # the small epsilon keeps e.g. (19 + 1) * 0.95 = 19.000000000000004 at rank 19
    return math.ceil((n_samples + 1) * (1.0 - false_alarm_rate) - 1e-9)


def minimum_samples(false_alarm_rate: float) -> int:
    """The fewest values that give a finite bound at ``false_alarm_rate``: ``ceil(1/alpha) - 1``."""
    n_samples = 1
    while conformal_rank(n_samples, false_alarm_rate) > n_samples:
        n_samples += 1
    return n_samples


def conformal_upper_bound(values: ArrayLike, false_alarm_rate: float) -> float:
    """The split-conformal upper bound of one more exchangeable value.

    Parameters
    ----------
    values : array_like, shape (n,)
        Calibration values (finite).
    false_alarm_rate : float
        Target rate ``alpha``: a new exchangeable value exceeds the bound with probability at
        most ``alpha``.

    Returns
    -------
    float
        The ``k``-th smallest value, ``k = ceil((n + 1) (1 - alpha))``; ``inf`` when ``k > n``
        (too few values for that rate).
    """
    array = np.sort(np.asarray(values, dtype=np.float64).ravel())
    if not np.isfinite(array).all():
        raise ValueError("calibration values must be finite")
    rank = conformal_rank(len(array), false_alarm_rate)
    if rank > len(array):
        return math.inf
    return float(array[rank - 1])


def learn_site_calibration(
    samples: Sequence[ReviewedSample],
    *,
    method: str,
    variant: str,
    false_alarm_rate: float,
    min_samples: int,
) -> dict[str, Any]:
    """A site's calibration from its reviewed-null jobs of one detector (JSON-ready).

    ``status`` is ``"learned"`` with ``thresholds`` (one per statistic of :data:`STATISTICS`)
    once there are ``max(min_samples, minimum_samples(alpha))`` samples, else ``"learning"``.
    Source job ids are listed newest last, at most :data:`MAX_SOURCE_IDS` of them.
    """
    needed = max(int(min_samples), minimum_samples(false_alarm_rate))
    n_samples = len(samples)
    calibration: dict[str, Any] = {
        "rule": SITE_RULE,
        "method": method,
        "variant": variant,
        "false_alarm_rate": float(false_alarm_rate),
        "min_samples": needed,
        "n_samples": n_samples,
        "source_job_ids": [sample.job_id for sample in samples][-MAX_SOURCE_IDS:],
    }
    if n_samples < needed:
        calibration["status"] = "learning"
        calibration["thresholds"] = None
        return calibration
    rank = conformal_rank(n_samples, false_alarm_rate)
    calibration["status"] = "learned"
    calibration["rank"] = rank
    calibration["quantile"] = rank / n_samples
    calibration["thresholds"] = {
        "largest_region_extent_m": conformal_upper_bound(
            [sample.largest_region_extent_m for sample in samples], false_alarm_rate
        ),
        "score": conformal_upper_bound([sample.score for sample in samples], false_alarm_rate),
    }
    return calibration


@dataclass(frozen=True)
class DecisionInputs:
    """What a comparison measured, for :func:`decide`."""

    rule: str
    method: str
    variant: str
    score: float
    detector_threshold: float
    n_regions: int
    largest_region_extent_m: float
    min_region_points: int


def _site_applies(inputs: DecisionInputs, site: Mapping[str, Any] | None) -> str | None:
    """Why the site's calibration does not apply to this comparison (None: it applies)."""
    if not site:
        return "the site has no reviewed jobs yet"
    if site.get("status") != "learned":
        return (
            f"the site has {site.get('n_samples', 0)} reviewed-null jobs; "
            f"{site.get('min_samples')} are needed"
        )
    if (site.get("method"), site.get("variant")) != (inputs.method, inputs.variant):
        return (
            f"learned for {site.get('method')}/{site.get('variant')}, "
            f"not {inputs.method}/{inputs.variant}"
        )
    return None


def decide(
    inputs: DecisionInputs, site_calibration: Mapping[str, Any] | None
) -> tuple[bool, list[dict[str, Any]], dict[str, Any]]:
    """``changed``, the decisive tests and the site calibration's provenance.

    Each test is ``{"statistic", "value", "comparison", "threshold", "source", "fires"}``
    (the region test adds ``n_regions`` and ``min_region_points``); ``source`` is
    ``"default"`` or ``"site"`` (a learned threshold above the default one).
    ``changed`` is any test firing for ``"either"``, the one test otherwise.
    """
    reason = _site_applies(inputs, site_calibration)
    learned = (site_calibration or {}).get("thresholds") if reason is None else None
    tests: list[dict[str, Any]] = []
    if inputs.rule in ("regions", "either"):
        test = {
            "statistic": "largest_region_extent_m",
            "value": float(inputs.largest_region_extent_m) if inputs.n_regions else 0.0,
            "comparison": ">",
            "threshold": 0.0,
            "source": "default",
            "n_regions": int(inputs.n_regions),
            "min_region_points": int(inputs.min_region_points),
            "fires": inputs.n_regions > 0,
        }
        site_value = (learned or {}).get("largest_region_extent_m")
        if site_value is not None and site_value > 0.0:
            test.update(threshold=float(site_value), source="site")
            test["fires"] = bool(test["value"] > test["threshold"])
        tests.append(test)
    if inputs.rule in ("detector", "either"):
        test = {
            "statistic": "score",
            "value": float(inputs.score),
            "comparison": ">",
            "threshold": float(inputs.detector_threshold),
            "source": "default",
        }
        site_value = (learned or {}).get("score")
        if site_value is not None and site_value > inputs.detector_threshold:
            test.update(threshold=float(site_value), source="site")
        test["fires"] = bool(test["value"] > test["threshold"])
        tests.append(test)
    changed = any(test["fires"] for test in tests)
    provenance = dict(site_calibration or {})
    provenance["applied"] = reason is None
    if reason is not None:
        provenance["reason"] = reason
    return changed, tests, provenance

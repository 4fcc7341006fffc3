"""Review verdicts and the score timeline in a real headless Chromium, against the real service.

The verdict buttons of the job page (false alarm with a note, then "make this scan the
reference" after a confirmation) change the job and the site over the API; the site's timeline
plots what decides each job with its threshold, the verdicts on it, one chart per detector and
jobs created in the same instant side by side.  The time axis and the empty state are checked
on timelines drawn from synthetic jobs in the page (spans of minutes and of days, equal
timestamps), from the SVG elements, not pixels.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest

from app.core.datasets.site import SiteVisit, site_visit
from app.testing.files import ply_bytes
from tests.helpers.browser import ReviewService, save_screenshot
from tests.helpers.browser import by_css as visible
from tests.helpers.browser import wait_for_page as wait_until
from tests.helpers.http import upload

pytestmark = pytest.mark.timeout(300)

N_POINTS = 12_000


def attribute_of_all(driver: Any, selector: str, name: str) -> list[str]:
    """``name`` of every element matching ``selector`` (SVG elements included)."""
    return driver.execute_script(
        "return [...document.querySelectorAll(arguments[0])]"
        ".map(e => e.getAttribute(arguments[1]))",
        selector,
        name,
    )


def sign_in(driver: Any, service: ReviewService) -> None:
    """Sign in with the admin token through the form."""
    driver.get(service.base_url + "/")
    visible(driver, "#token").send_keys(service.process.admin_token)
    visible(driver, "#sign-in-button").click()
    wait_until(lambda: driver.get_cookie("scandiff_session"), 10, "signing in set no cookie")


def upload_visit(client: Any, site_id: str, visit: SiteVisit, **query: Any) -> dict:
    """Upload one synthetic visit with its sensor origin; the answer."""
    origin = ",".join(f"{value:.6f}" for value in visit.sensor_origin)
    answer = upload(
        client,
        site_id,
        ply_bytes(visit.points),
        filename="visit.ply",
        sensor_origin=origin,
        **query,
    )
    assert answer.status_code in (201, 202), answer.text
    return answer.json()


@pytest.fixture(scope="module")
def site_history(review_service: ReviewService) -> dict[str, Any]:
    """A PCA site with a reference and two finished rescans in which the bin moved."""
    service = review_service
    with service.client() as client:
        answer = client.post(
            "/api/v1/sites",
            json={
                "name": "Loading bay",
                "detector": {"method": "pca", "variant": "improved", "params": {}},
            },
        )
        assert answer.status_code == 201, answer.text
        site = answer.json()
        reference = site_visit(bin_spot=5, n_points=N_POINTS, sensor_shift=0.0, random_state=1)
        reference_scan = upload_visit(client, site["id"], reference, reference="true")["scan"]
        jobs = []
        for seed, spot in ((2, 0), (3, 1)):
            visit = site_visit(bin_spot=spot, n_points=N_POINTS, random_state=seed)
            job_id = upload_visit(client, site["id"], visit)["job"]["id"]
            jobs.append(service.process.wait_for_job(client, job_id, timeout=120))
    assert all(job["status"] == "succeeded" for job in jobs), jobs
    return {"site": site, "reference": reference_scan, "jobs": jobs}


def test_verdict_buttons_on_the_job_page(
    review_service: ReviewService, site_history: dict[str, Any], chrome_factory
) -> None:
    from selenium.webdriver.common.by import By

    service = review_service
    job = site_history["jobs"][0]
    driver = chrome_factory()
    sign_in(driver, service)
    driver.get(f"{service.base_url}/#/jobs/{job['id']}")
    explained = visible(driver, "#decision-explained").text
    # in sentences, naming the Why line's largest region (the most points)
    largest = job["explanation"]["largest_region"]
    named = f"region {largest['index'] + 1}: {largest['kind']}, {largest['n_points']:,} points"
    assert f"the largest region ({named})" in explained, explained
    assert "→" not in explained and "fires" not in explained, explained
    assert visible(driver, "#current-verdict").get_attribute("data-verdict") == ""

    visible(driver, "#verdict-note").send_keys("the bin again")
    visible(driver, "#verdict-false_alarm").click()
    wait_until(
        lambda: visible(driver, "#current-verdict").get_attribute("data-verdict") == "false_alarm",
        20,
        "the false alarm verdict was not shown",
    )
    assert "the bin again" in visible(driver, "#current-verdict").text
    with service.client() as client:
        verdict = client.get(f"/api/v1/jobs/{job['id']}").json()["verdict"]
    assert (verdict["verdict"], verdict["note"]) == ("false_alarm", "the bin again")

    # "make this scan the reference" asks first, then promotes the job's scan
    assert not driver.find_element(By.ID, "new-reference-confirm").is_displayed()
    visible(driver, "#verdict-new-reference-ask").click()
    visible(driver, "#verdict-new_reference").click()
    wait_until(
        lambda: (
            visible(driver, "#current-verdict").get_attribute("data-verdict") == "new_reference"
        ),
        20,
        "the new reference verdict was not shown",
    )
    with service.client() as client:
        site = client.get(f"/api/v1/sites/{job['site_id']}").json()
    assert site["reference_scan_id"] == job["scan_id"]
    visible(driver, "#review summary").click()
    wait_until(
        lambda: (
            attribute_of_all(driver, "#verdict-history li", "data-verdict")
            == ["new_reference", "false_alarm"]  # newest first
        ),
        10,
        "the verdict history does not list both verdicts",
    )
    save_screenshot(driver, "verdicts-job-page")


def test_site_timeline_plots_the_decision_threshold_verdicts_and_detectors(
    review_service: ReviewService, site_history: dict[str, Any], chrome_factory
) -> None:
    service = review_service
    site = site_history["site"]
    first, second = site_history["jobs"]
    pair = {"reference_scan_id": site_history["reference"]["id"], "scan_id": second["scan_id"]}
    with service.client() as client:
        answer = client.post(f"/api/v1/jobs/{second['id']}/verdict", json={"verdict": "confirmed"})
        assert answer.status_code == 200, answer.text
        # two comparisons queued in the same instant (sent together: one after the other, a
        # loaded machine can put seconds between them), and one with another detector
        with ThreadPoolExecutor(2) as senders:
            created = list(
                senders.map(lambda _: client.post("/api/v1/jobs", json=pair).json(), range(2))
            )
        created.append(client.post("/api/v1/jobs", json={**pair, "method": "gmm"}).json())
        finished = [service.process.wait_for_job(client, job["id"], timeout=180) for job in created]
    assert all(job["status"] == "succeeded" for job in finished), finished
    all_jobs = [first, second, *finished]

    driver = chrome_factory()
    sign_in(driver, service)
    driver.get(f"{service.base_url}/#/sites/{site['id']}")
    chart = visible(driver, "svg.decisive-chart")
    assert chart.get_attribute("data-statistic") == "largest_region_extent_m"
    wait_until(
        lambda: (
            sorted(attribute_of_all(driver, "svg.decisive-chart .dot[data-job-id]", "data-job-id"))
            == sorted(job["id"] for job in all_jobs)
        ),
        20,
        "the decisive chart does not have one dot per finished job",
    )
    marks = dict(
        zip(
            attribute_of_all(driver, ".verdict-mark[data-job-id]", "data-job-id"),
            attribute_of_all(driver, ".verdict-mark[data-job-id]", "data-verdict"),
            strict=True,
        )
    )
    assert marks == {first["id"]: "new_reference", second["id"]: "confirmed"}
    assert attribute_of_all(driver, "svg.decisive-chart line.threshold-line", "class")
    detectors = attribute_of_all(driver, "svg.detector-chart", "data-detector")
    assert sorted(detectors) == ["gmm · improved", "pca · improved"]
    # the two jobs of the same instant: one group, side by side
    positions = {
        job_id: (float(x), group)
        for job_id, x, group in zip(
            attribute_of_all(driver, "svg.decisive-chart .dot[data-job-id]", "data-job-id"),
            attribute_of_all(driver, "svg.decisive-chart .dot[data-job-id]", "cx"),
            attribute_of_all(driver, "svg.decisive-chart .dot[data-job-id]", "data-group"),
            strict=True,
        )
    }
    (x_a, group_a), (x_b, group_b) = (positions[job["id"]] for job in finished[:2])
    assert group_a == group_b and abs(x_a - x_b) >= 4
    ticks = attribute_of_all(driver, "svg.decisive-chart .time-tick", "data-time")
    assert len(ticks) == len(set(ticks)) >= 2
    save_screenshot(driver, "verdicts-site-timeline")


DRAW_SYNTHETIC = """
const done = arguments[arguments.length - 1];
import('/static/timeline.js').then((timeline) => {
  const draw = (jobs) => {
    const box = document.createElement('div');
    box.style.width = '800px';
    document.body.append(box);
    timeline.drawTimeline(box, jobs, () => {});
    const texts = (selector) => [...box.querySelectorAll(selector)].map((e) => e.textContent);
    const dots = [...box.querySelectorAll('svg.decisive-chart .dot[data-job-id]')];
    return {
      first: box.firstElementChild.tagName.toLowerCase(),
      height: box.getBoundingClientRect().height,
      svgs: box.querySelectorAll('svg').length,
      ticks: [...box.querySelectorAll('svg.decisive-chart .time-tick')].map((t) => t.textContent),
      main: texts('svg.decisive-chart .tick-main'),
      dates: texts('svg.decisive-chart .tick-date'),
      cx: dots.map((d) => Number(d.getAttribute('cx'))),
      groups: dots.map((d) => d.getAttribute('data-group-size')),
      detectors: [...box.querySelectorAll('svg.detector-chart')].map((s) => s.dataset.detector),
      notes: texts('.timeline-note'),
    };
  };
  const job = (index, createdAt, extra = {}) => ({
    id: `job${index}`, status: 'succeeded', created_at: createdAt, score: 0.1 + index / 100,
    threshold: 0.2, changed: index % 2 === 0, method: 'pca', variant: 'improved',
    calibration: {decision: {tests: [{statistic: 'largest_region_extent_m', value: index / 10,
      comparison: '>', threshold: 0, source: 'default', fires: index > 0}]}},
    ...extra,
  });
  const base = Date.parse('2026-03-02T02:10:00Z');
  const iso = (offset) => new Date(base + offset).toISOString();
  done({
    empty: draw([]),
    days: draw([0, 1, 2, 3, 4].map((day) => job(day, iso(day * 86400000)))),
    minutes: draw([0, 1, 2, 3, 4].map((minute) => job(minute, iso(minute * 120000)))),
    same: draw([0, 1, 2].map((index) => job(index, iso(0)))),
    mixed: draw([
      job(0, iso(0)),
      job(1, iso(3600000), {method: 'gmm'}),
      job(2, iso(7200000), {calibration: null}),
    ]),
  });
}).catch((error) => done({error: String(error)}));
"""


def test_timeline_axis_grouping_series_and_empty_state(
    review_service: ReviewService, chrome_factory
) -> None:
    driver = chrome_factory()
    driver.get(review_service.base_url + "/")
    visible(driver, "#token")
    driver.set_script_timeout(30)
    drawn = driver.execute_async_script(DRAW_SYNTHETIC)
    assert "error" not in drawn, drawn

    empty = drawn["empty"]  # a line of text, not a 400 px empty chart
    assert (empty["first"], empty["svgs"]) == ("p", 0) and empty["height"] < 60

    for span in ("days", "minutes"):
        ticks = drawn[span]["ticks"]
        assert len(ticks) >= 3 and len(set(ticks)) == len(ticks), (span, ticks)
        assert not any("AM" in tick or "PM" in tick for tick in ticks), ticks
    # five jobs at 02:10 on five days: dates, no repeated time of day
    assert all("Mar" in tick and ":" not in tick for tick in drawn["days"]["main"])
    # jobs a few minutes apart: times, and the date once (at the first tick)
    assert len(drawn["minutes"]["dates"]) == 1 and "Mar" in drawn["minutes"]["dates"][0]
    assert all(":" in tick for tick in drawn["minutes"]["main"])

    same = drawn["same"]  # three jobs of the same instant: one group, spread out
    assert same["groups"] == ["3", "3", "3"] and len(set(same["cx"])) == 3

    mixed = drawn["mixed"]  # one chart per detector; a job without the statistic is explained
    assert sorted(mixed["detectors"]) == ["gmm · improved", "pca · improved"]
    assert len(mixed["cx"]) == 2 and "1 job without" in mixed["notes"][0]


def test_verdict_buttons_in_the_3d_view(
    review_service: ReviewService, site_history: dict[str, Any], chrome_factory
) -> None:
    service = review_service
    job = site_history["jobs"][1]
    driver = chrome_factory()
    sign_in(driver, service)
    driver.get(f"{service.base_url}/jobs/{job['id']}/view")
    explained = visible(driver, "#view-review #decision-explained").text
    assert "the largest region (region " in explained
    visible(driver, "#view-review #verdict-note").send_keys("seen in 3D: the bin")
    visible(driver, "#view-review #verdict-false_alarm").click()
    wait_until(
        lambda: (
            visible(driver, "#view-review #current-verdict").get_attribute("data-verdict")
            == "false_alarm"
        ),
        20,
        "the 3D view's review panel did not show the false alarm",
    )
    with service.client() as client:
        verdict = client.get(f"/api/v1/jobs/{job['id']}").json()["verdict"]
    assert (verdict["verdict"], verdict["note"]) == ("false_alarm", "seen in 3D: the bin")
    assert verdict["set_by"]["role"] == "admin"
    # (a visitor with only a view link, told where to sign in to review: test_view_review_tools)

"""A job's stored results as the API describes and serves them: OpenAPI names every field of
the registration, calibration (decision, visibility), sensor origins, warnings and explanation,
and a response is exactly the JSON stored (no field added as null, keys in stored order)."""

from __future__ import annotations

import json

import httpx

from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.http import site_with_reference, upload_accepted
from tests.helpers.jobs import finish_job, load_job
from tests.helpers.server import ApiServer

DESCRIBED = {
    "registration": {"transform", "fitness", "rmse", "enabled", "translation_m"},
    "calibration": {"compared_points", "site", "visibility", "decision"},
    "explanation": {"decision", "rule", "decided_by", "largest_region", "agrees", "text"},
}
"""Fields of JobRead, and fields OpenAPI must name for each."""


def _resolve(schema: dict, components: dict) -> dict:
    """``schema`` with a ``$ref`` (also one inside ``anyOf``) followed."""
    for option in schema.get("anyOf", [schema]):
        if "$ref" in option:
            return components[option["$ref"].rsplit("/", 1)[-1]]
        if option.get("type") == "array" and "$ref" in option.get("items", {}):
            return components[option["items"]["$ref"].rsplit("/", 1)[-1]]
    return schema


def test_openapi_names_every_field_of_a_jobs_results(writer: httpx.Client) -> None:
    components = writer.get("/openapi.json").json()["components"]["schemas"]
    job = components.get("JobRead-Output") or components["JobRead"]
    for field, names in DESCRIBED.items():
        described = _resolve(job["properties"][field], components)
        assert names <= set(described.get("properties", {})), (field, described)
    calibration = _resolve(job["properties"]["calibration"], components)
    decision = _resolve(calibration["properties"]["decision"], components)
    assert {"rule", "detector_changed", "tests"} <= set(decision["properties"])
    warning = _resolve(job["properties"]["warnings"], components)
    assert {"code", "message", "detail", "how_to_fix"} <= set(warning["properties"])
    origins = job["properties"]["sensor_origins"]["anyOf"][0]["additionalProperties"]
    origin = _resolve(origins, components)
    assert {"origin", "source", "confidence"} <= set(origin["properties"])


def test_a_job_answers_exactly_the_json_it_stored(api: ApiServer, writer: httpx.Client) -> None:
    site, reference = site_with_reference(writer)
    accepted = upload_accepted(writer, site["id"], "scan.ply", ply_bytes(room_points(500, seed=4)))
    job_id = accepted["job"]["id"]
    registration = {"rmse": 0.01, "transform": [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}
    calibration = {"detector_figure": 3, "decision": {"tests": [], "rule": "regions"}}
    finish_job(
        api,
        job_id,
        reference["n_points"],
        accepted["scan"]["n_points"],
        registration=registration,
        calibration=calibration,
        sensor_origins={"scan": [{"source": "file", "origin": [1, 2, 3], "extra": True}]},
    )

    answer = writer.get(f"/api/v1/jobs/{job_id}").json()
    stored = load_job(api.settings, job_id)

    for field in ("registration", "calibration", "sensor_origins", "explanation"):
        assert json.dumps(answer[field]) == json.dumps(getattr(stored, field)), field
    assert answer["registration"] == registration  # integers stay integers, nothing added
    assert [warning["code"] for warning in answer["warnings"]] == [
        warning["code"] for warning in stored.warnings
    ]

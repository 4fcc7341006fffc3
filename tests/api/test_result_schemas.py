"""A job's stored results as the API describes and serves them: OpenAPI names every field of
the registration, calibration (decision, visibility), sensor origins, warnings and explanation,
and a response is exactly the JSON stored (no field added as null, keys in stored order)."""

from __future__ import annotations

import json

import httpx

from app.core.comparison.reports import QualityWarning
from app.jobs.alerts.site_history import RegionCountWarning
from app.testing.files import ply_bytes
from app.testing.results import calibration_report, registration_report, sensor_origin_entries
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
    # every key either kind of warning stores (the core's and the site history's) is named
    stored = [
        QualityWarning("low_overlap", "m", "e", "widen_coverage", 0.2, 0.5, "", "scan"),
        RegionCountWarning(n_regions=12, limit=7.0, median=2.0, history_jobs=3),
    ]
    detail = _resolve(warning["properties"]["detail"], components)
    how_to_fix = _resolve(warning["properties"]["how_to_fix"], components)
    for one in stored:
        stored_json = one.to_json_dict()
        assert set(stored_json) <= set(warning["properties"]), one.code
        assert set(stored_json["detail"]) <= set(detail["properties"]), one.code
        assert set(stored_json["how_to_fix"]) <= set(how_to_fix["properties"]), one.code
    origins = job["properties"]["sensor_origins"]["anyOf"][0]["additionalProperties"]
    origin = _resolve(origins, components)
    assert {"origin", "source", "confidence"} <= set(origin["properties"])


def _free_form(schema: dict, components: dict, path: str, seen: set[str]) -> list[str]:
    """Where under ``schema`` a JSON object (or any value) is left undescribed: an object
    without named properties and with untyped additional ones, or a schema saying nothing."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        if name in seen:
            return []
        return _free_form(components[name], components, f"{path}<{name}>", seen | {name})
    options = schema.get("anyOf") or schema.get("oneOf") or schema.get("allOf")
    if options:
        return [spot for option in options for spot in _free_form(option, components, path, seen)]
    kind = schema.get("type")
    if kind is None and "const" not in schema and "enum" not in schema:
        return [path]  # any value at all
    found = []
    if kind == "object":
        extra = schema.get("additionalProperties", True)
        if not schema.get("properties") and not isinstance(extra, dict):
            found.append(path)
        if isinstance(extra, dict) and extra:
            found += _free_form(extra, components, f"{path}.*", seen)
        for name, field in schema.get("properties", {}).items():
            found += _free_form(field, components, f"{path}.{name}", seen)
    if kind == "array" and "items" in schema:
        found += _free_form(schema["items"], components, f"{path}[]", seen)
    return found


def test_openapi_describes_every_object_of_a_job(writer: httpx.Client) -> None:
    """No field of JobRead, however deep, is a free-form object (on the old code: params,
    effective_params, timings and a trajectory's summary were)."""
    components = writer.get("/openapi.json").json()["components"]["schemas"]
    job = components.get("JobRead-Output") or components["JobRead"]
    assert _free_form(job, components, "JobRead", set()) == []


def test_a_job_answers_exactly_the_json_it_stored(api: ApiServer, writer: httpx.Client) -> None:
    site, reference = site_with_reference(writer)
    accepted = upload_accepted(writer, site["id"], "scan.ply", ply_bytes(room_points(500, seed=4)))
    job_id = accepted["job"]["id"]
    registration = registration_report(transform=[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])
    calibration = calibration_report({"detector_figure": 3})
    finish_job(
        api,
        job_id,
        reference["n_points"],
        accepted["scan"]["n_points"],
        registration=registration,
        calibration=calibration,
        sensor_origins=sensor_origin_entries(
            {"scan": [{"source": "file", "origin": [1, 2, 3], "confidence": 1}]}
        ),
        params={"voxel_size": "auto", "registration": {"min_fitness": 0}, "detector_own": 2},
    )

    answer = writer.get(f"/api/v1/jobs/{job_id}").json()
    stored = load_job(api.settings, job_id)

    fields = ("registration", "calibration", "sensor_origins", "explanation", "effective_params")
    for field in fields:
        assert json.dumps(answer[field]) == json.dumps(getattr(stored, field)), field
    assert answer["registration"] == registration.to_json_dict()  # integers stay, nothing added
    assert json.dumps(answer["timings"]) == json.dumps(stored.timings)
    assert json.dumps(answer["params"]) == json.dumps(stored.params)
    assert [warning["code"] for warning in answer["warnings"]] == [
        warning["code"] for warning in stored.warnings
    ]

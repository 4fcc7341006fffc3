"""Quality warnings as the API shows them: how to fix each, in the API's own knobs.

The core (:mod:`app.core.quality`) says what is wrong in one sentence and which fix applies
(``how_to_fix["action"]``), naming no interface.  Here each fix gets the words of the API: the
upload's query parameter, the job's ``params`` key, the service setting (``SCANDIFF_*``) that
changes the outcome.  The CLI does the same with its flags (``app.cli.compare``).
"""

from __future__ import annotations

from typing import Any

API_FIXES: dict[str, tuple[str, list[str]]] = {
    "check_pairing": (
        "check that the scan was uploaded to the right site; to compare without aligning, "
        'rerun with "align": false in the job\'s params (POST /api/v1/jobs/{job_id}/rerun)',
        ["params.align"],
    ),
    "check_alignment": (
        "check that the alignment found the right match; to compare without aligning, rerun "
        'with "align": false in the job\'s params (POST /api/v1/jobs/{job_id}/rerun)',
        ["params.align"],
    ),
    "widen_coverage": ("rescan so that both scans cover the same part of the place", []),
    "give_sensor_origin": (
        "give the sensor position: ?sensor_origin=x,y,z (metres, the file's frame) when "
        'uploading the scan, or "reference_origin"/"scan_origin" in the job\'s params',
        ["sensor_origin", "params.reference_origin", "params.scan_origin"],
    ),
    "check_sensor_origin": (
        "check the sensor position given with ?sensor_origin= on upload or "
        '"reference_origin"/"scan_origin" in the job\'s params',
        ["sensor_origin", "params.reference_origin", "params.scan_origin"],
    ),
    "check_trajectory": (
        "check that the trajectory sent with the scan (the multipart part trajectory, or PUT "
        "/api/v1/scans/{scan_id}/trajectory) was recorded with it, on the same clock, and "
        "covers the whole recording",
        ["trajectory"],
    ),
    "check_site_history": (
        "check the job's registration and that both scans are of this site before trusting "
        "its regions",
        [],
    ),
}
"""For each ``how_to_fix["action"]``: the API's advice and the parameters it names."""

ACTION_OF_CODE = {
    "low_registration_fitness": "check_pairing",
    "large_rotation": "check_alignment",
    "large_translation": "check_alignment",
    "low_overlap": "widen_coverage",
    "sensor_origin_unknown": "give_sensor_origin",
    "sensor_origin": "check_sensor_origin",
    "trajectory_time_span": "check_trajectory",
    "region_count_above_history": "check_site_history",
}
"""The fix of each warning code (for warnings stored before they carried ``how_to_fix``)."""

SETTING_OF_LIMIT = {"max_points": "SCANDIFF_MAX_POINTS"}
"""The service setting behind each limit the core names (``PointCloudError.limit_name``)."""


def api_warning(warning: dict[str, Any]) -> dict[str, Any]:
    """``warning`` with ``how_to_fix`` saying what to change in the API's terms."""
    rendered = dict(warning)
    fix = dict(rendered.get("how_to_fix") or {})
    action = fix.get("action") or ACTION_OF_CODE.get(str(rendered.get("code")))
    if action in API_FIXES:
        text, parameters = API_FIXES[action]
        fix.update(action=action, text=text, parameters=parameters)
        rendered["how_to_fix"] = fix
    return rendered


def api_warnings(warnings: list[dict[str, Any]] | None) -> list[dict[str, Any]] | None:
    """Every warning of a job as the API shows it (None stays None)."""
    if warnings is None:
        return None
    return [api_warning(warning) if isinstance(warning, dict) else warning for warning in warnings]


def api_limit_message(message: str, limit_name: str | None) -> str:
    """A core error message about a limit, naming the service setting that raises it."""
    setting = SETTING_OF_LIMIT.get(limit_name or "")
    return f"{message} (the service's limit, setting {setting})" if setting else message

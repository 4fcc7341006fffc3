"""What this server reads and runs, for clients that build their forms from it (the dashboard)."""

from __future__ import annotations

from app.services.schemas import CapabilitiesRead, DetectorConfig
from app.services.sites import DEFAULT_METHOD, DEFAULT_VARIANT


def capabilities() -> CapabilitiesRead:
    """The upload formats the core reads and the detectors it runs."""
    from app.core.detectors import METHODS, VARIANTS  # the core's own lists, never copied
    from app.core.formats import SUPPORTED_FORMATS

    return CapabilitiesRead(
        upload_formats=list(SUPPORTED_FORMATS),
        upload_extensions=[f".{name}" for name in SUPPORTED_FORMATS],
        detector_methods=list(METHODS),
        detector_variants=list(VARIANTS),
        default_detector=DetectorConfig(method=DEFAULT_METHOD, variant=DEFAULT_VARIANT),
    )

"""A job's cache of its reference's k-NN geometry: where it lives, its key, its bytes in the quota.

The cache of a reference scan ``scans/<site>/<scan>.<format>`` is ``scans/<site>/<scan>.geometry``
(removed with the site's scans).  Its key (:func:`app.core.cache.geometry.cache_key`) is the scan's
id and SHA-256, the code version and the job's localisation parameters; a file for another key,
or damaged, is rebuilt by the comparison (:class:`app.core.cache.geometry.GeometryCache`).  Its
size is stored on the scan (``scan.geometry_cache_bytes``), which the stored-bytes quota counts;
a cache that would take the organisation over its cap is deleted instead (the comparison then
runs the search again next time, as without a cache).
"""

from __future__ import annotations

import logging

from app.config import Settings
from app.core.cache.geometry import GeometryCache, cache_key
from app.db import usage
from app.db.models import Scan
from app.db.session import transaction
from app.jobs.leases import ClaimedJob

logger = logging.getLogger("scandiff.jobs")

CACHE_SUFFIX = ".geometry"


def geometry_cache_of(job: ClaimedJob) -> GeometryCache | None:
    """The cache of ``job``'s reference, or None when the job has no stored reference."""
    if job.reference_path is None or job.reference_scan_id is None:
        return None
    localisation = job.params.get("localisation")
    try:
        key = cache_key(
            f"{job.reference_scan_id}:{job.reference_sha256}",
            localisation if isinstance(localisation, dict) else None,
        )
    except ValueError:  # a bad parameter: the comparison reports it
        return None
    return GeometryCache(job.reference_path.with_suffix(CACHE_SUFFIX), key)


def record_geometry_cache(job: ClaimedJob, settings: Settings, cache: GeometryCache) -> int:
    """Store the cache's size on the reference scan (0 when there is no file); its bytes.

    A file that would take the organisation over ``max_stored_bytes_per_organisation`` is
    deleted and counts 0.  The organisation row is locked first, as uploads lock it for their
    quota check, so the two never both pass on the same usage.
    """
    size = cache.path.stat().st_size if cache.path.is_file() else 0
    with transaction(settings.sqlalchemy_url) as session:
        scan = session.get(Scan, job.reference_scan_id)
        if scan is None:  # deleted meanwhile
            cache.path.unlink(missing_ok=True)
            return 0
        if scan.geometry_cache_bytes == size:
            return size
        cap = settings.max_stored_bytes_per_organisation
        if cap is not None and size > scan.geometry_cache_bytes:
            usage.lock_organisation(session, scan.organisation_id)
            used = usage.stored_bytes(session, scan.organisation_id)
            if used - scan.geometry_cache_bytes + size > cap:
                logger.info(
                    "reference geometry not cached: over the organisation's storage cap",
                    extra={"job_id": job.id, "stage": "geometry-cache"},
                )
                cache.path.unlink(missing_ok=True)
                size = 0
        scan.geometry_cache_bytes = size
    return size

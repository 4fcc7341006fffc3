"""Sites: a place scanned over time, with its detector settings and current reference scan."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sqlalchemy import delete, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.clock import as_utc, utc_now
from app.config import Settings
from app.core.comparison_settings import parse_comparison_params  # never in a transaction
from app.core.detectors import canonical_method
from app.core.errors import InputError
from app.db.models import Job, JobStatus, JobVerdict, ReferenceHistory, Region, Scan, Site
from app.services import storage
from app.services.auth import Principal
from app.services.errors import ConflictError, ValidationFailedError
from app.services.paging import newest_first_page
from app.services.schemas import DEFAULT_DETECTOR_VARIANT, SiteCreate, SiteUpdate
from app.services.scoping import get_owned, scoped
from app.services.site_calibration import recompute_site_calibration
from app.services.transaction import after_commit

DEFAULT_METHOD = "gmm"
DEFAULT_VARIANT = DEFAULT_DETECTOR_VARIANT


def validate_detector(method: str, variant: str, params: dict[str, Any]) -> str:
    """Check that ``compare`` would accept these settings; the canonical method name (the
    paper's ``pe``, ``PE-EMD``... are aliases); 422 with the core's message otherwise."""
    try:
        method = canonical_method(method)
        parse_comparison_params(method, variant, params)
    except InputError as exc:
        raise ValidationFailedError(str(exc), code="invalid_detector") from exc
    return method


def resolve_detector(
    site: Site, method: str | None, variant: str | None, params: dict[str, Any] | None = None
) -> tuple[str, str, dict[str, Any]]:
    """The detector of a job: overrides, else the site's; validated.

    Without explicit ``params`` the site's parameters are kept only when method and variant
    are the site's (another detector takes its own defaults).
    """
    chosen_method = canonical_method_or_422(method) if method else site.detector_method
    chosen_variant = variant or site.detector_variant
    if params is None:
        same_detector = (chosen_method, chosen_variant) == (
            site.detector_method,
            site.detector_variant,
        )
        params = dict(site.detector_params or {}) if same_detector else {}
    chosen_method = validate_detector(chosen_method, chosen_variant, params)
    return chosen_method, chosen_variant, params


def canonical_method_or_422(method: str) -> str:
    """The canonical name of a detector method or alias; 422 naming the valid ones."""
    try:
        return canonical_method(method)
    except InputError as exc:
        raise ValidationFailedError(str(exc), code="invalid_detector") from exc


def get_site(session: Session, principal: Principal, site_id: str) -> Site:
    """The principal's site ``site_id``; 404 when it does not exist or is another's."""
    return get_owned(session, principal, Site, site_id)


def list_sites(
    session: Session, principal: Principal, limit: int, cursor: str | None
) -> tuple[Sequence[Site], str | None]:
    """The principal's sites, newest first, one page."""
    return newest_first_page(session, scoped(select(Site), principal), Site, limit, cursor)


def _flush_unique_name(session: Session, name: str) -> None:
    try:
        with session.begin_nested():
            session.flush()
    except IntegrityError as exc:
        raise ConflictError(f"a site named {name!r} already exists", code="site_exists") from exc


def create_site(session: Session, principal: Principal, payload: SiteCreate) -> Site:
    """Create a site (detector validated; default GMM-EMD improved)."""
    detector = payload.detector
    method = detector.method if detector else DEFAULT_METHOD
    variant = detector.variant if detector else DEFAULT_VARIANT
    params = dict(detector.params) if detector else {}
    method = validate_detector(method, variant, params)
    site = Site(
        organisation_id=principal.organisation_id,
        name=payload.name,
        description=payload.description,
        detector_method=method,
        detector_variant=variant,
        detector_params=params,
    )
    session.add(site)
    _flush_unique_name(session, payload.name)
    return site


def update_site(
    session: Session, settings: Settings, principal: Principal, site_id: str, payload: SiteUpdate
) -> Site:
    """Change a site's name, description or detector (only the fields given; a new detector
    recomputes the site's calibration from that detector's reviewed jobs)."""
    site = get_site(session, principal, site_id)
    fields = payload.model_fields_set
    if "name" in fields:
        if payload.name is None:
            raise ValidationFailedError("name cannot be null")
        site.name = payload.name
    if "description" in fields:
        site.description = payload.description
    if "detector" in fields:
        if payload.detector is None:
            raise ValidationFailedError("detector cannot be null")
        params = dict(payload.detector.params)
        site.detector_method = validate_detector(
            payload.detector.method, payload.detector.variant, params
        )
        site.detector_variant = payload.detector.variant
        site.detector_params = params
        recompute_site_calibration(session, settings, site)
    _flush_unique_name(session, site.name)
    return site


def _refuse_running_jobs(session: Session, site: Site) -> None:
    """409 when a worker holds a live lease on a job of the site (its results would be lost).

    The site's unfinished jobs are locked (PostgreSQL; SQLite write transactions are
    exclusive), so a worker cannot claim a queued one before it is deleted with the site; a
    worker that later picks up a deleted job's id skips it.
    """
    now = utc_now()
    unfinished = session.execute(
        select(Job.id, Job.status, Job.lease_expires_at)
        .where(Job.site_id == site.id, Job.status.in_(JobStatus.unfinished()))
        .with_for_update()
    ).all()
    running = [
        job_id
        for job_id, status, lease_expires_at in unfinished
        if status == JobStatus.RUNNING
        and lease_expires_at is not None
        and as_utc(lease_expires_at) >= now
    ]
    if running:
        raise ConflictError(
            f"site {site.id} has {len(running)} running job(s) (e.g. job {running[0]}); "
            f"deleting it now would throw their work away. Wait until they finish "
            f"(GET /api/v1/jobs/{running[0]}) and delete again; queued jobs are deleted "
            f"with the site.",
            code="site_has_running_jobs",
        )


def delete_site(session: Session, settings: Settings, principal: Principal, site_id: str) -> None:
    """Delete a site with its scans, jobs and regions; their files go once the rows are gone.

    Refused (409) while one of its jobs is running; its queued jobs are deleted with it.
    """
    site = get_site(session, principal, site_id)
    _refuse_running_jobs(session, site)
    job_ids = list(session.scalars(select(Job.id).where(Job.site_id == site.id)))
    if job_ids:
        session.execute(delete(Region).where(Region.job_id.in_(job_ids)))
    session.execute(delete(Job).where(Job.site_id == site.id))
    session.execute(delete(JobVerdict).where(JobVerdict.site_id == site.id))
    session.execute(delete(ReferenceHistory).where(ReferenceHistory.site_id == site.id))
    session.execute(delete(Scan).where(Scan.site_id == site.id))
    session.delete(site)
    session.flush()

    def remove_files() -> None:
        storage.remove_tree(settings.data_layout.site_scans_dir(site_id))
        for job_id in job_ids:
            storage.remove_tree(settings.data_layout.job_results_dir(job_id))

    after_commit(session, remove_files)


def set_reference(session: Session, site: Site, scan: Scan) -> None:
    """Make ``scan`` the site's reference and record it in the reference history."""
    site.reference_scan_id = scan.id
    session.add(ReferenceHistory(site_id=site.id, scan_id=scan.id))
    session.flush()


def promote_reference(session: Session, principal: Principal, site_id: str, scan_id: str) -> Site:
    """Make an existing scan of the site its reference."""
    site = get_site(session, principal, site_id)
    scan = get_owned(session, principal, Scan, scan_id)
    if scan.site_id != site.id:
        raise ValidationFailedError(
            f"scan {scan_id} belongs to another site; a reference must be a scan of this site",
            code="scan_of_another_site",
        )
    set_reference(session, site, scan)
    return site

"""Issue 18: a job keeps its reference's k-NN geometry for the site's next scans, in the quota.

Real pipeline, real Alembic-migrated SQLite, jobs executed in-process (as a worker runs them).
"""

from __future__ import annotations

import numpy as np

from app.config import Settings
from app.db.models import Job, Scan, Site
from app.db.session import transaction
from app.jobs.execution import execute_job
from app.jobs.geometry import CACHE_SUFFIX
from app.services.auth import Principal
from app.services.quotas import stored_bytes as quota_stored_bytes
from tests.helpers.jobs import create_job, load_job, new_job

N_POINTS = 6000


def reference_of(settings: Settings, job_id: str) -> Scan:
    with transaction(settings.sqlalchemy_url) as session:
        job = session.get(Job, job_id)
        scan = session.get(Scan, job.reference_scan_id)
        session.expunge(scan)
        return scan


def same_comparison_again(settings: Settings, job_id: str, **columns: object) -> str:
    """A new queued job of the same site, reference and scan; its id."""
    with transaction(settings.sqlalchemy_url) as session:
        job = session.get(Job, job_id)
        site = session.get(Site, job.site_id)
        again = new_job(site, job.reference_scan_id, job.scan_id, status="queued", **columns)
        session.add(again)
        session.flush()
        return again.id


def stored_bytes(settings: Settings, organisation_id: str) -> int:
    """Scan and cache bytes of the organisation, as the quota sums them."""
    principal = Principal(organisation_id=organisation_id, role="reader", token_id="-")
    with transaction(settings.sqlalchemy_url) as session:
        return quota_stored_bytes(session, principal)


def labels_of(settings: Settings, job_id: str) -> dict[str, np.ndarray]:
    job = load_job(settings, job_id)
    with np.load(settings.data_dir / job.labels_path) as labels:
        return {name: labels[name] for name in labels.files}


def test_the_cache_is_written_reused_rebuilt_when_corrupt_and_counted(job_settings: Settings):
    first = create_job(job_settings, n_points=N_POINTS)
    assert execute_job(first, job_settings) == "succeeded"
    reference = reference_of(job_settings, first)
    cache_path = (job_settings.data_dir / reference.storage_path).with_suffix(CACHE_SUFFIX)
    assert cache_path.is_file()
    assert reference.geometry_cache_bytes == cache_path.stat().st_size > 0
    # counted with the organisation's stored bytes (what the quota and /organisation sum)
    scans_only = stored_bytes(job_settings, reference.organisation_id) - cache_path.stat().st_size
    assert scans_only > 0
    written = cache_path.read_bytes()
    expected = labels_of(job_settings, first)

    second = same_comparison_again(job_settings, first)
    cache_path.touch()  # a reuse must not rewrite it
    before = cache_path.stat().st_mtime_ns
    assert execute_job(second, job_settings) == "succeeded"
    assert cache_path.stat().st_mtime_ns == before
    for name, values in labels_of(job_settings, second).items():
        np.testing.assert_array_equal(values, expected[name])

    damaged = bytearray(written)
    damaged[len(damaged) // 2] ^= 0xFF
    cache_path.write_bytes(bytes(damaged))
    third = same_comparison_again(job_settings, first)
    assert execute_job(third, job_settings) == "succeeded"
    assert cache_path.read_bytes() == written  # rebuilt, not trusted
    for name, values in labels_of(job_settings, third).items():
        np.testing.assert_array_equal(values, expected[name])

    cache_path.unlink()
    fourth = same_comparison_again(job_settings, first)
    assert execute_job(fourth, job_settings) == "succeeded"
    assert cache_path.read_bytes() == written  # missing: rebuilt


def test_other_localisation_parameters_are_another_key(job_settings: Settings):
    first = create_job(job_settings, n_points=N_POINTS)
    assert execute_job(first, job_settings) == "succeeded"
    reference = reference_of(job_settings, first)
    cache_path = (job_settings.data_dir / reference.storage_path).with_suffix(CACHE_SUFFIX)
    default_k = cache_path.read_bytes()
    other = same_comparison_again(job_settings, first, params={"localisation": {"n_neighbors": 12}})
    assert execute_job(other, job_settings) == "succeeded"
    assert cache_path.read_bytes() != default_k  # not used for k = 12: rebuilt for it
    assert reference_of(job_settings, first).geometry_cache_bytes == cache_path.stat().st_size


def test_a_cache_over_the_storage_cap_is_dropped_and_not_counted(job_settings: Settings):
    first = create_job(job_settings, n_points=N_POINTS)
    reference = reference_of(job_settings, first)
    scans = stored_bytes(job_settings, reference.organisation_id)
    capped = job_settings.model_copy(update={"max_stored_bytes_per_organisation": scans + 1000})
    assert execute_job(first, capped) == "succeeded"
    cache_path = (job_settings.data_dir / reference.storage_path).with_suffix(CACHE_SUFFIX)
    assert not cache_path.exists()
    assert reference_of(job_settings, first).geometry_cache_bytes == 0
    assert stored_bytes(job_settings, reference.organisation_id) == scans

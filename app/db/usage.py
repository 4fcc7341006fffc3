"""What an organisation stores, and the lock that serialises its quota checks.

Shared by the services' quota checks (:mod:`app.services.quotas`: uploads, jobs) and the job
workers' reference geometry caches (:mod:`app.jobs.geometry`), which must take the same lock and
count the same bytes, so an upload and a cache never both pass the storage cap on one usage.
"""

from __future__ import annotations

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.clock import utc_now
from app.db.models import Organisation, ResumableUpload, Scan


def lock_organisation(session: Session, organisation_id: str) -> None:
    """Serialise quota checks of one organisation until the transaction ends.

    ``SELECT ... FOR NO KEY UPDATE`` of the organisation row on PostgreSQL: it serialises quota
    checks but, unlike ``FOR UPDATE``, does not clash with the ``FOR KEY SHARE`` lock that inserting
    a row referencing the organisation takes (an upload inserts its idempotency record first: with
    ``FOR UPDATE`` two concurrent uploads deadlocked; tests/reliability/test_scaled_out.py).
    SQLite has no row locks and needs none (its write transactions are ``BEGIN IMMEDIATE``).
    """
    session.execute(
        select(Organisation.id)
        .where(Organisation.id == organisation_id)
        .with_for_update(key_share=True)
    )


def stored_bytes(session: Session, organisation_id: str) -> int:
    """Bytes of the organisation's scan files, their cached reference geometry and what its
    resumable uploads accepted so far (until they complete, expire or are terminated)."""
    stored = func.coalesce(func.sum(Scan.size_bytes + Scan.geometry_cache_bytes), 0)
    total = session.scalar(select(stored).where(Scan.organisation_id == organisation_id))
    receiving = select(func.coalesce(func.sum(ResumableUpload.offset), 0)).where(
        ResumableUpload.organisation_id == organisation_id,
        ResumableUpload.state == "active",
        ResumableUpload.expires_at > utc_now(),
    )
    reserved = session.scalar(receiving)
    return int(total or 0) + int(reserved or 0)

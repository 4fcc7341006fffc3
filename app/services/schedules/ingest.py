"""A file a schedule fetched becomes a scan of its site, by the checks of an upload.

The steps of :func:`app.services.scans.upload_scan`, without an HTTP body: the storage quota
with the exact size (507), then :func:`app.services.scans.store_scan_file` (the core reader
parses and checks the cloud, a malformed file is refused with the core's message, the file is
renamed into place), and a short transaction locks the organisation, checks the quota again
and inserts the scan.  Any refusal leaves no row
and no file.  No job is created here: the schedule's run creates its comparisons.
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from app.config import Settings
from app.db.models import Scan
from app.services import quotas, scans, storage
from app.services.auth import Principal
from app.services.storage import ReceivedFile


def store_received_scan(
    session: Session,
    settings: Settings,
    principal: Principal,
    site_id: str,
    received: ReceivedFile,
    filename: str | None,
) -> Scan:
    """Parse ``received`` and insert it as a scan of ``site_id`` in ``session``'s transaction.

    Call with no transaction open (parsing is slow); the temporary file is removed in all cases.
    """
    try:
        scans.check_stored_bytes_before_parsing(session, settings, principal, received.size_bytes)
        scan = scans.store_scan_file(
            session,
            settings,
            principal,
            site_id=site_id,
            received=received,
            filename=storage.sanitise_filename(filename),
        )
        quotas.lock_organisation(session, principal)
        quotas.check_stored_bytes(session, settings, principal, received.size_bytes)
        session.add(scan)
        session.flush()
        return scan
    finally:
        storage.remove_file(received.path)

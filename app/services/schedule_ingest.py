"""A file a schedule fetched becomes a scan of its site, by the checks of an upload.

The same steps as :func:`app.services.scans.upload_scan`, without an HTTP body: the storage
quota with the exact size (507), the core reader parses and checks the cloud (a malformed file
is refused with the core's message), the file is renamed into place, and a short transaction
locks the organisation, checks the quota again and inserts the scan.  Any refusal leaves no row
and no file.  No job is created here: the schedule's run creates its comparisons.
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from app.config import Settings
from app.db.models import Scan, new_id
from app.services import quotas, scans, storage
from app.services.auth import Principal
from app.services.storage import ReceivedFile
from app.services.transaction import after_rollback, end_read_transaction


def check_room(session: Session, settings: Settings, principal: Principal, size: int) -> None:
    """The storage quota for ``size`` more bytes, before the file is parsed (a read)."""
    quotas.check_stored_bytes(session, settings, principal, size)
    end_read_transaction(session)


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
        check_room(session, settings, principal, received.size_bytes)
        clean_name = storage.sanitise_filename(filename)
        parsed = scans.parse_upload(received.path, clean_name, received.head, settings.max_points)
        scan_id = new_id()
        storage_path = settings.data_layout.scan_storage_path(site_id, scan_id, parsed.format)
        final_path = settings.data_layout.resolve(storage_path)
        storage.install_file(received.path, final_path)
        after_rollback(session, lambda: storage.remove_file(final_path))
        quotas.lock_organisation(session, principal)
        quotas.check_stored_bytes(session, settings, principal, received.size_bytes)
        scan = scans.scan_row(
            principal,
            scan_id=scan_id,
            site_id=site_id,
            filename=clean_name,
            storage_path=storage_path,
            received=received,
            parsed=parsed,
        )
        session.add(scan)
        session.flush()
        return scan
    finally:
        storage.remove_file(received.path)

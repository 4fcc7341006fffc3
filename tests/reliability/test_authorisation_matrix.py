"""Issue 5 (6): who can read what — every endpoint x every kind of caller, 0 leaks.

Organisation A owns a site, its reference, a scan, two jobs (one succeeded, one queued), a
webhook, a schedule and a resumable upload in progress (tus 1.0.0, its first bytes received).
Every operation of ``/openapi.json`` (the test fails when a new one is not in the matrix) is
called, with the headers and body that make it otherwise valid (tus: ``Tus-Resumable``,
``Upload-Metadata`` naming A's site, ``Upload-Offset`` at the upload's offset), by A's writer,
admin and reader, by B's writer, admin and reader, by B's dashboard session cookie, with no
token, an unknown token, a revoked token of A, a non-Bearer scheme and a view link used as a
token; then A's writer calls it again with guessed ids (random, B's, and junk).  Pass: only A's
path succeeds (readers only read); other organisations get 404 (403 for their readers' writes);
A's data is unchanged after every refused call (the upload's row, offset and received bytes
too); no refused answer and no answer to B contains A's names, descriptions, file names,
checksums or bytes, in its body or its headers; A's objects answer 404 to guessed ids.  The 3D
view page is checked with view links: valid, expired, forged, for another job, made by a
revoked token.  Every log record written meanwhile is searched for every token, view link and
session cookie used.
"""

from __future__ import annotations

import base64
import logging
import time
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import httpx
import pytest
from sqlalchemy import func, select, update

from app.api.logs import JsonFormatter
from app.api.session_auth import SESSION_COOKIE, make_view_link, secret_key
from app.clock import utc_now
from app.db.models import ApiToken, Job, ResumableUpload, Scan
from app.db.session import transaction
from app.services.auth import hash_token
from app.services.resumable_uploads import upload_path
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from app.viewer.access import VIEW_COOKIE
from tests.helpers.figures import record_figure
from tests.helpers.http import create_site, unique_name, upload
from tests.helpers.jobs import finish_job
from tests.helpers.resumable import OCTETS, TUS, metadata_header, new_upload, patch
from tests.helpers.server import ApiServer

TUM_PATH = b"0.0 0.5 0.5 1.2 0 0 0 1\n1.0 1.5 0.5 1.2 0 0 0 1\n2.0 2.5 0.5 1.2 0 0 0 1\n"
"""A three-pose trajectory (TUM) through the room, for PUT /scans/{id}/trajectory."""

PUBLIC_OPERATIONS = {
    ("GET", "/api/v1/health"),
    ("POST", "/api/v1/session"),  # trades a token (in the body) for a cookie
    ("DELETE", "/api/v1/session"),  # clears the caller's own cookie
}


@dataclass
class Objects:
    """A's objects, as the ids a request is built from."""

    site_id: str
    reference_scan_id: str
    scan_id: str
    job_id: str
    queued_job_id: str
    webhook_id: str = ""
    spare_site_ids: list[str] = field(default_factory=list)
    schedule_id: str = ""
    spare_schedule_ids: list[str] = field(default_factory=list)
    spare_webhook_ids: list[str] = field(default_factory=list)
    upload_id: str = ""
    upload_offset: int = 0  # the upload's offset: a PATCH must send it to be otherwise valid
    spare_upload_ids: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Operation:
    """One API operation and how to call it on ``Objects``."""

    method: str
    path: str
    min_role: str  # "reader", "writer" or "admin"
    owner_status: int
    scoped: bool = True  # addresses A's objects (other organisations must get 404)
    json: Callable[[Objects], dict[str, Any]] | None = None
    params: dict[str, str] | None = None
    headers: Callable[[Objects], dict[str, str]] | None = None
    content: Callable[[Objects], bytes] | None = None
    upload: bool = False
    destroys: bool = False

    def url(self, ids: Objects, *, owner: bool) -> str:
        site_id, schedule_id, webhook_id = ids.site_id, ids.schedule_id, ids.webhook_id
        upload_id = ids.upload_id
        if self.destroys and owner and "{schedule_id}" in self.path:
            schedule_id = ids.spare_schedule_ids.pop()
        elif self.destroys and owner and "{webhook_id}" in self.path:
            webhook_id = ids.spare_webhook_ids.pop()
        elif self.destroys and owner and "{upload_id}" in self.path:
            upload_id = ids.spare_upload_ids.pop()
        elif self.destroys and owner:
            site_id = ids.spare_site_ids.pop()
        return self.path.format(
            site_id=site_id,
            scan_id=ids.scan_id,
            job_id=ids.job_id,
            schedule_id=schedule_id,
            webhook_id=webhook_id,
            upload_id=upload_id,
        )


SCAN_CONTENT = ply_bytes(room_points(1500, seed=21))
NIGHTLY = {"cron": "0 2 * * *", "timezone": "Europe/Lisbon"}
WEBHOOK_URL = "https://93.184.215.14/hooks/matrix"
UPLOAD_CHUNK_BYTES = 512
"""What one PATCH of the matrix appends to A's upload (of ``SCAN_CONTENT``: it never completes)."""


def new_upload_headers(ids: Objects) -> dict[str, str]:
    """A tus creation of a scan of ``ids.site_id`` (A's unless the ids are guessed)."""
    return {
        **TUS,
        "Upload-Length": str(len(SCAN_CONTENT)),
        "Upload-Metadata": metadata_header(site=ids.site_id, filename="matrix.ply"),
    }


def next_chunk_headers(ids: Objects) -> dict[str, str]:
    """A tus PATCH at the upload's offset (only the caller's rights can refuse it)."""
    return {**OCTETS, "Upload-Offset": str(ids.upload_offset)}


def next_chunk(ids: Objects) -> bytes:
    """The bytes of ``SCAN_CONTENT`` that follow the upload's offset."""
    return SCAN_CONTENT[ids.upload_offset : ids.upload_offset + UPLOAD_CHUNK_BYTES]


OPERATIONS = [
    Operation(
        "POST",
        "/api/v1/sites",
        "writer",
        201,
        scoped=False,
        json=lambda ids: {"name": unique_name("matrix-site")},
    ),
    Operation("GET", "/api/v1/sites", "reader", 200, scoped=False),
    Operation("GET", "/api/v1/session", "reader", 200, scoped=False),
    Operation("GET", "/api/v1/organisation", "reader", 200, scoped=False),
    Operation("GET", "/api/v1/capabilities", "reader", 200, scoped=False),
    Operation("GET", "/api/v1/sites/{site_id}", "reader", 200),
    Operation(
        "PATCH",
        "/api/v1/sites/{site_id}",
        "writer",
        200,
        json=lambda ids: {"description": "changed by the matrix"},
    ),
    Operation("DELETE", "/api/v1/sites/{site_id}", "writer", 204, destroys=True),
    Operation(
        "POST",
        "/api/v1/sites/{site_id}/reference",
        "writer",
        200,
        json=lambda ids: {"scan_id": ids.reference_scan_id},
    ),
    Operation("POST", "/api/v1/sites/{site_id}/scans", "writer", 202, upload=True),
    Operation("GET", "/api/v1/sites/{site_id}/scans", "reader", 200),
    Operation("GET", "/api/v1/sites/{site_id}/jobs", "reader", 200),
    Operation("GET", "/api/v1/scans/{scan_id}", "reader", 200),
    Operation("GET", "/api/v1/scans/{scan_id}/file", "reader", 200),
    Operation(
        "PUT",
        "/api/v1/scans/{scan_id}/trajectory",
        "writer",
        200,
        params={"filename": "path.tum"},
        content=lambda ids: TUM_PATH,
    ),
    Operation(
        "POST",
        "/api/v1/jobs",
        "writer",
        202,
        json=lambda ids: {"reference_scan_id": ids.reference_scan_id, "scan_id": ids.scan_id},
    ),
    Operation("GET", "/api/v1/jobs", "reader", 200, scoped=False),
    Operation("GET", "/api/v1/jobs/awaiting-review/counts", "reader", 200, scoped=False),
    Operation("GET", "/api/v1/jobs/{job_id}", "reader", 200),
    Operation("POST", "/api/v1/jobs/{job_id}/rerun", "writer", 202, json=lambda ids: {}),
    Operation(
        "POST",
        "/api/v1/jobs/{job_id}/verdict",
        "writer",
        200,
        json=lambda ids: {"verdict": "confirmed"},
    ),
    Operation("GET", "/api/v1/jobs/{job_id}/verdicts", "reader", 200),
    Operation("GET", "/api/v1/jobs/{job_id}/regions", "reader", 200),
    Operation("GET", "/api/v1/jobs/{job_id}/labels", "reader", 200, params={"format": "npz"}),
    Operation("POST", "/api/v1/jobs/{job_id}/view-link", "reader", 200),
    Operation("GET", "/api/v1/jobs/{job_id}/view/scene", "reader", 200),
    Operation("POST", "/api/v1/sites/{site_id}/schedules", "writer", 201, json=lambda ids: NIGHTLY),
    Operation("GET", "/api/v1/sites/{site_id}/schedules", "reader", 200),
    Operation("GET", "/api/v1/schedules/{schedule_id}", "reader", 200),
    Operation(
        "PATCH",
        "/api/v1/schedules/{schedule_id}",
        "writer",
        200,
        json=lambda ids: {"enabled": True},
    ),
    Operation("POST", "/api/v1/schedules/{schedule_id}/run", "writer", 201),
    Operation("GET", "/api/v1/schedules/{schedule_id}/runs", "reader", 200),
    Operation("DELETE", "/api/v1/schedules/{schedule_id}", "writer", 204, destroys=True),
    Operation(
        "POST",
        "/api/v1/webhooks",
        "admin",
        201,
        scoped=False,
        json=lambda ids: {"url": WEBHOOK_URL},
    ),
    Operation("GET", "/api/v1/webhooks", "reader", 200, scoped=False),
    Operation("GET", "/api/v1/webhooks/{webhook_id}", "reader", 200),
    Operation("DELETE", "/api/v1/webhooks/{webhook_id}", "admin", 204, destroys=True),
    Operation("GET", "/api/v1/webhooks/{webhook_id}/deliveries", "reader", 200),
    Operation("POST", "/api/v1/webhooks/{webhook_id}/test", "admin", 202),
    Operation("OPTIONS", "/api/v1/uploads", "reader", 204, scoped=False),
    # scoped: the site named in Upload-Metadata is A's (other organisations must get 404)
    Operation("POST", "/api/v1/uploads", "writer", 201, headers=new_upload_headers),
    Operation("HEAD", "/api/v1/uploads/{upload_id}", "reader", 200, headers=lambda ids: TUS),
    Operation("GET", "/api/v1/uploads/{upload_id}", "reader", 200),
    Operation(
        "PUT",
        "/api/v1/uploads/{upload_id}/trajectory",
        "writer",
        200,
        params={"filename": "path.tum"},
        content=lambda ids: TUM_PATH,
    ),
    Operation(
        "PATCH",
        "/api/v1/uploads/{upload_id}",
        "writer",
        204,
        headers=next_chunk_headers,
        content=next_chunk,
    ),
    Operation(
        "DELETE",
        "/api/v1/uploads/{upload_id}",
        "writer",
        204,
        headers=lambda ids: TUS,
        destroys=True,
    ),
]


@dataclass(frozen=True)
class Caller:
    """Who calls: whose organisation, which role, how authenticated."""

    name: str
    organisation: str | None  # "A", "B" or None (not authenticated)
    role: str | None
    headers: dict[str, str] = field(default_factory=dict)
    cookies: dict[str, str] = field(default_factory=dict)


def off_by_one(object_id: str) -> str:
    """``object_id`` with its last character changed (never the id itself)."""
    return object_id[:-1] + ("1" if object_id.endswith("0") else "0")


def expected_status(operation: Operation, caller: Caller) -> int:
    """What the caller must get from the operation on A's objects."""
    if caller.organisation is None:
        return 401
    may = (
        caller.role == "admin"
        or (caller.role == "writer" and operation.min_role != "admin")
        or operation.min_role == "reader"
    )
    if not may:
        return 403
    if caller.organisation == "A" or not operation.scoped:
        return operation.owner_status
    return 404


def client_for(service: ApiServer, caller: Caller) -> httpx.Client:
    """An HTTP client sending the caller's credentials."""
    client = httpx.Client(
        base_url=service.base_url, headers=caller.headers, cookies=caller.cookies, timeout=30.0
    )
    service.clients.append(client)
    return client


def call(
    client: httpx.Client, operation: Operation, ids: Objects, caller: Caller
) -> httpx.Response:
    """Send the operation as ``caller`` (``client`` carries the caller's credentials)."""
    owner_success = caller.organisation == "A" and expected_status(operation, caller) < 400
    target = operation.url(ids, owner=owner_success)
    if operation.upload:
        return client.post(
            target,
            params={"filename": "matrix.ply"},
            content=SCAN_CONTENT,
            headers={"Content-Type": "application/octet-stream"},
        )
    response = client.request(
        operation.method,
        target,
        json=operation.json(ids) if operation.json else None,
        params=operation.params,
        headers=operation.headers(ids) if operation.headers else None,
        content=operation.content(ids) if operation.content else None,
    )
    if operation.method == "PATCH" and "{upload_id}" in operation.path and response.is_success:
        ids.upload_offset = int(response.headers["Upload-Offset"])  # where the next PATCH goes
    return response


class AllRecords(logging.Handler):
    """Every log record (formatted as the service writes them) while installed."""

    def __init__(self) -> None:
        super().__init__(level=logging.DEBUG)
        self.setFormatter(JsonFormatter())
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(self.format(record))


def revoke(service: ApiServer, token: str) -> None:
    with transaction(service.settings.sqlalchemy_url) as session:
        session.execute(
            update(ApiToken)
            .where(ApiToken.token_hash == hash_token(token))
            .values(revoked_at=utc_now())
        )


def session_cookie(service: ApiServer, token: str) -> str:
    """The dashboard cookie for ``token`` (signed in through the API)."""
    with httpx.Client(base_url=service.base_url) as browser:
        response = browser.post("/api/v1/session", json={"token": token})
        assert response.status_code == 200, response.text
        return response.cookies[SESSION_COOKIE]


def state_of(service: ApiServer, client: httpx.Client, ids: Objects) -> dict[str, Any]:
    """What a refused call must not change."""
    site = client.get(f"/api/v1/sites/{ids.site_id}").json()
    with transaction(service.settings.sqlalchemy_url) as session:
        scans = session.scalar(
            select(func.count()).select_from(Scan).where(Scan.site_id == ids.site_id)
        )
        jobs = session.scalar(
            select(func.count()).select_from(Job).where(Job.site_id == ids.site_id)
        )
        uploads = session.scalars(
            select(ResumableUpload)
            .where(ResumableUpload.site_id == ids.site_id)
            .order_by(ResumableUpload.id)
        ).all()
        upload_rows = [
            (row.id, row.state, row.offset, row.length, row.upload_metadata, row.expires_at)
            for row in uploads
        ]
    part = upload_path(service.settings, ids.upload_id)
    upload_bytes = part.read_bytes() if part.is_file() else None
    return {
        "site": site,
        "scans": scans,
        "jobs": jobs,
        "uploads": upload_rows,
        "upload bytes": upload_bytes,
    }


@pytest.fixture(scope="module")
def world(service: ApiServer) -> dict[str, Any]:
    """A's objects (with unique markers), tokens of both organisations and the callers."""
    org_a, org_b = unique_name("org-a"), unique_name("org-b")
    tokens = {
        (org, role): service.token(role, organisation)
        for org, organisation in (("A", org_a), ("B", org_b))
        for role in ("writer", "admin", "reader")
    }
    revoked_token = service.token("writer", org_a)
    a_writer = service.client(tokens[("A", "writer")])
    markers = {
        "site name": unique_name("secret-site-name"),
        "site description": unique_name("secret-description"),
        "scan file name": unique_name("secret-file") + ".ply",
    }
    site = create_site(a_writer, name=markers["site name"], description=markers["site description"])
    reference = upload(
        a_writer,
        site["id"],
        ply_bytes(room_points(3000, seed=1)),
        reference=True,
        filename=markers["scan file name"],
    ).json()["scan"]
    created = upload(
        a_writer,
        site["id"],
        ply_bytes(room_points(2500, seed=4)),
        filename=markers["scan file name"],
    ).json()
    scan, job = created["scan"], created["job"]
    finish_job(service, job["id"], reference["n_points"], scan["n_points"])
    queued = upload(a_writer, site["id"], ply_bytes(room_points(2000, seed=6))).json()["job"]
    markers["reference sha256"] = reference["sha256"]
    markers["scan sha256"] = scan["sha256"]
    markers["organisation name"] = org_a
    a_admin = service.client(tokens[("A", "admin")])
    webhook = a_admin.post("/api/v1/webhooks", json={"url": WEBHOOK_URL}).json()
    ids = Objects(site["id"], reference["id"], scan["id"], job["id"], queued["id"], webhook["id"])
    ids.schedule_id = create_schedule(a_writer, site["id"])
    ids.upload_id, ids.upload_offset = upload_in_progress(
        a_writer, site["id"], filename=markers["scan file name"]
    )
    markers["upload file name (base64, as in Upload-Metadata)"] = base64.b64encode(
        markers["scan file name"].encode()
    ).decode()
    owner_head = a_writer.head(f"/api/v1/uploads/{ids.upload_id}", headers=TUS)
    assert leaked_markers(answer_text(owner_head), markers), "the header leak check would be blind"
    b_writer = service.client(tokens[("B", "writer")])
    b_site = create_site(b_writer)
    b_reference = upload(
        b_writer, b_site["id"], ply_bytes(room_points(3000, seed=2)), reference=True
    ).json()["scan"]
    b_job = upload(b_writer, b_site["id"], ply_bytes(room_points(2000, seed=3))).json()["job"]
    b_admin = service.client(tokens[("B", "admin")])
    b_webhook = b_admin.post("/api/v1/webhooks", json={"url": WEBHOOK_URL}).json()
    link_as_token = a_writer.post(f"/api/v1/jobs/{ids.job_id}/view-link").json()["url"]
    link_value = link_as_token.split("link=", 1)[1]
    revoke(service, revoked_token)
    b_cookie = session_cookie(service, tokens[("B", "writer")])
    a_reader_cookie = session_cookie(service, tokens[("A", "reader")])
    callers = [
        Caller(f"{org}-{role}", org, role, headers={"Authorization": f"Bearer {token}"})
        for (org, role), token in tokens.items()
    ] + [
        Caller("B-session-cookie", "B", "writer", cookies={SESSION_COOKIE: b_cookie}),
        Caller("A-reader-session-cookie", "A", "reader", cookies={SESSION_COOKIE: a_reader_cookie}),
        Caller("no-token", None, None),
        Caller(
            "unknown-token", None, None, headers={"Authorization": f"Bearer sdt_{uuid.uuid4().hex}"}
        ),
        Caller("revoked-A-token", None, None, headers={"Authorization": f"Bearer {revoked_token}"}),
        Caller("basic-scheme", None, None, headers={"Authorization": "Basic YTpi"}),
        Caller("empty-bearer", None, None, headers={"Authorization": "Bearer"}),
        Caller("view-link-as-token", None, None, headers={"Authorization": f"Bearer {link_value}"}),
        Caller(
            "forged-session-cookie", None, None, cookies={SESSION_COOKIE: b_cookie[:-4] + "AAAA"}
        ),
    ]
    secrets = [*tokens.values(), revoked_token, link_value, b_cookie, a_reader_cookie]
    return {
        "ids": ids,
        "markers": markers,
        "callers": callers,
        "secrets": secrets,
        "a_writer": a_writer,
        "a_admin": a_admin,
        "tokens": tokens,
        "org_b": org_b,
        "b_ids": {
            "site": b_site["id"],
            "scan": b_reference["id"],
            "job": b_job["id"],
            "schedule": create_schedule(b_writer, b_site["id"]),
            "webhook": b_webhook["id"],
            "upload": upload_in_progress(b_writer, b_site["id"])[0],
        },
    }


def create_schedule(client: httpx.Client, site_id: str) -> str:
    """A nightly schedule of the site; its id."""
    response = client.post(f"/api/v1/sites/{site_id}/schedules", json=NIGHTLY)
    assert response.status_code == 201, response.text
    return str(response.json()["id"])


def upload_in_progress(
    client: httpx.Client, site_id: str, filename: str = "matrix.ply"
) -> tuple[str, int]:
    """A resumable upload of ``SCAN_CONTENT`` to the site with its first chunk received; its id
    and offset."""
    location = new_upload(client, len(SCAN_CONTENT), site=site_id, filename=filename)
    first = patch(client, location, 0, SCAN_CONTENT[:UPLOAD_CHUNK_BYTES])
    assert first.status_code == 204, first.text
    return location.rsplit("/", 1)[1], int(first.headers["Upload-Offset"])


def answer_text(response: httpx.Response) -> str:
    """The response's headers and body, as a leak is searched in them (HEAD has only headers)."""
    headers = "\n".join(f"{name}: {value}" for name, value in response.headers.items())
    return f"{headers}\n\n{response.text}"


def leaked_markers(text: str, markers: dict[str, str]) -> list[str]:
    return [label for label, marker in markers.items() if marker in text]


def test_every_operation_is_in_the_matrix(service: ApiServer) -> None:
    schema = httpx.get(f"{service.base_url}/openapi.json").json()
    in_schema = {(method.upper(), path) for path, ops in schema["paths"].items() for method in ops}
    covered = {(operation.method, operation.path) for operation in OPERATIONS}
    missing = in_schema - covered - PUBLIC_OPERATIONS
    print(
        f"\n[reliability] matrix covers {len(covered)} of {len(in_schema)} operations "
        f"({len(PUBLIC_OPERATIONS)} public); missing {sorted(missing)}"
    )
    assert not missing, f"operations missing from the authorisation matrix: {sorted(missing)}"


def test_only_the_owner_path_succeeds_and_nothing_leaks(service: ApiServer, world: dict) -> None:
    ids: Objects = world["ids"]
    markers: dict[str, str] = world["markers"]
    a_writer: httpx.Client = world["a_writer"]
    clients = {caller.name: client_for(service, caller) for caller in world["callers"]}
    records = AllRecords()
    logging.getLogger().addHandler(records)
    wrong: list[str] = []
    leaks: list[str] = []
    statuses: Counter[int] = Counter()
    calls = 0
    started = time.monotonic()
    try:
        before = state_of(service, a_writer, ids)
        # Everyone but A's writers and admins first: A's state must not move.
        refused_callers = [
            c
            for c in world["callers"]
            if not (c.organisation == "A" and c.role in ("writer", "admin"))
        ]
        for caller in refused_callers:
            for operation in OPERATIONS:
                expected = expected_status(operation, caller)
                response = call(clients[caller.name], operation, ids, caller)
                calls += 1
                statuses[response.status_code] += 1
                if response.status_code != expected:
                    wrong.append(
                        f"{caller.name} {operation.method} {operation.path}: "
                        f"{response.status_code}, expected {expected}: "
                        f"{response.text[:160]}"
                    )
                if caller.organisation != "A":
                    text = answer_text(response)
                    found = leaked_markers(text, markers)
                    a_ids = (ids.site_id, ids.scan_id, ids.job_id, ids.webhook_id, ids.upload_id)
                    if response.status_code < 400 and operation.scoped:
                        found += [f"id {value}" for value in a_ids if value in text]
                    if caller.organisation == "B" and not operation.scoped:
                        found += [f"id {value}" for value in a_ids if value in text]
                    if SCAN_CONTENT[-64:] in response.content:
                        found.append("scan bytes")
                    if found:
                        leaks.append(f"{caller.name} {operation.method} {operation.path}: {found}")
                if response.status_code == 500:
                    wrong.append(f"server error: {response.text[:200]}")
        after_refused = state_of(service, a_writer, ids)
        # A's readers may read (the session cookie ones too) and so change nothing either.
        # Then A's writers and admins: every operation succeeds (but admin ones for writers).
        owners = [
            c for c in world["callers"] if c.organisation == "A" and c.role in ("writer", "admin")
        ]
        for caller in owners:
            ids.spare_site_ids.append(create_site(a_writer)["id"])
            ids.spare_schedule_ids.append(create_schedule(a_writer, ids.site_id))
            spare_webhook = world["a_admin"].post("/api/v1/webhooks", json={"url": WEBHOOK_URL})
            ids.spare_webhook_ids.append(spare_webhook.json()["id"])
            ids.spare_upload_ids.append(upload_in_progress(a_writer, ids.site_id)[0])
            for operation in OPERATIONS:
                response = call(clients[caller.name], operation, ids, caller)
                calls += 1
                statuses[response.status_code] += 1
                if response.status_code != expected_status(operation, caller):  # 403: writers
                    wrong.append(  # on admin operations
                        f"{caller.name} {operation.method} {operation.path}: "
                        f"{response.status_code}: {response.text[:160]}"
                    )
        # Guessed ids: A's writer on ids that are not A's.
        b_ids = world["b_ids"]
        guesses = {
            "random": Objects(
                uuid.uuid4().hex,
                uuid.uuid4().hex,
                uuid.uuid4().hex,
                uuid.uuid4().hex,
                uuid.uuid4().hex,
                uuid.uuid4().hex,
                schedule_id=uuid.uuid4().hex,
                upload_id=uuid.uuid4().hex,
            ),
            "other organisation's": Objects(
                b_ids["site"],
                b_ids["scan"],
                b_ids["scan"],
                b_ids["job"],
                b_ids["job"],
                b_ids["webhook"],
                schedule_id=b_ids["schedule"],
                upload_id=b_ids["upload"],
            ),
            "off by one": Objects(
                off_by_one(ids.site_id),
                off_by_one(ids.scan_id),
                off_by_one(ids.scan_id),
                off_by_one(ids.job_id),
                "0",
                off_by_one(ids.webhook_id),
                schedule_id=off_by_one(ids.schedule_id),
                upload_id=off_by_one(ids.upload_id),
            ),
            "junk": Objects(
                "..",
                "%2e%2e%2fadmin-token",
                "0 OR 1=1",
                "*",
                "null",
                "..",
                schedule_id="%00",
                upload_id="' OR ''='",
            ),
        }
        owner = next(c for c in owners if c.role == "admin")  # passes every role check
        for label, guessed in guesses.items():
            for operation in OPERATIONS:
                if not operation.scoped:
                    continue
                guessed.spare_site_ids.append(guessed.site_id)
                guessed.spare_schedule_ids.append(guessed.schedule_id)
                guessed.spare_webhook_ids.append(guessed.webhook_id)
                guessed.spare_upload_ids.append(guessed.upload_id)
                response = call(clients[owner.name], operation, guessed, owner)
                calls += 1
                statuses[response.status_code] += 1
                acceptable = {404} if label != "junk" else {404, 405, 422}
                dot_segment = "{site_id}" in operation.path or "{webhook_id}" in operation.path
                if label == "junk" and dot_segment and ".." not in response.request.url.path:
                    # the client resolved the junk id "..": /sites/../jobs is GET /jobs, another
                    # route of the matrix (checked there), answering for the caller's own data
                    acceptable.add(200)
                if response.status_code not in acceptable:
                    wrong.append(
                        f"guessed ({label}) {operation.method} {operation.path}: "
                        f"{response.status_code}: {response.text[:160]}"
                    )
                if label == "other organisation's" and leaked_markers(
                    response.text, {"B org": world["org_b"]}
                ):
                    leaks.append(f"B's organisation via guessed id {operation.path}")
    finally:
        logging.getLogger().removeHandler(records)
    elapsed = time.monotonic() - started
    log_text = "\n".join(records.lines)
    secrets_in_logs = [secret[:10] + "..." for secret in world["secrets"] if secret in log_text]
    record_figure(
        "authorisation-matrix",
        load=f"{len(OPERATIONS)} operations x {len(world['callers'])} callers + "
        f"{len(guesses)} kinds of guessed ids",
        faults="other organisation (3 roles + session cookie), no/unknown/revoked/forged "
        "credentials, readers writing, guessed ids",
        inputs=f"{calls} requests",
        result=(
            f"{len(wrong)} wrong statuses; {len(leaks)} leaks; "
            f"{len(secrets_in_logs)} secrets in {len(records.lines)} log lines; "
            f"statuses {dict(sorted(statuses.items()))}; {elapsed:.1f} s"
        ),
        statuses=dict(statuses),
        wrong=wrong,
        leaks=leaks,
    )
    assert not wrong, "\n".join(wrong)
    assert not leaks, "\n".join(leaks)
    assert after_refused == before, (before, after_refused)
    assert records.lines, "no log records were captured: the log check would prove nothing"
    assert not secrets_in_logs, secrets_in_logs


def view_page(
    service: ApiServer, job_id: str, link: str | None = None, cookies: dict[str, str] | None = None
) -> httpx.Response:
    with httpx.Client(base_url=service.base_url, cookies=cookies or {}) as browser:
        return browser.get(f"/jobs/{job_id}/view", params={"link": link} if link else None)


def test_view_links_open_only_their_own_job_until_they_expire(
    service: ApiServer, world: dict
) -> None:
    ids: Objects = world["ids"]
    a_writer: httpx.Client = world["a_writer"]
    key = secret_key(service.settings)
    made = a_writer.post(f"/api/v1/jobs/{ids.queued_job_id}/view-link")
    assert made.status_code == 200, made.text
    valid = made.json()["url"].split("link=", 1)[1]
    with transaction(service.settings.sqlalchemy_url) as session:
        writer_token = session.scalar(
            select(ApiToken).where(
                ApiToken.token_hash == hash_token(world["tokens"][("A", "writer")])
            )
        )
        assert writer_token is not None
        expired, _ = make_view_link(ids.queued_job_id, writer_token, key, ttl=-5)
        other_job, _ = make_view_link(ids.job_id, writer_token, key, ttl=600)
    body, _, mac = valid.partition(".")
    forged_key, _ = make_view_link(ids.queued_job_id, writer_token, b"guessed-key" * 3, ttl=600)
    b_link_response = service.client(world["tokens"][("B", "writer")]).post(
        f"/api/v1/jobs/{world['b_ids']['job']}/view-link"
    )
    b_link = b_link_response.json()["url"].split("link=", 1)[1]
    revoked_maker = service.token("writer", world["markers"]["organisation name"])
    revoked_link = (
        service.client(revoked_maker)
        .post(f"/api/v1/jobs/{ids.queued_job_id}/view-link")
        .json()["url"]
        .split("link=", 1)[1]
    )
    revoke(service, revoked_maker)
    b_cookie = next(c for c in world["callers"] if c.name == "B-session-cookie").cookies
    cases = {
        # 409: authorised, the queued job's view just is not ready (the viewer is not started).
        "valid link": (view_page(service, ids.queued_job_id, valid), 409),
        "no link, no session": (view_page(service, ids.queued_job_id), 401),
        "expired link": (view_page(service, ids.queued_job_id, expired), 403),
        "link of another job of A": (view_page(service, ids.queued_job_id, other_job), 403),
        "link of B's job": (view_page(service, ids.queued_job_id, b_link), 403),
        "link signed with a guessed key": (view_page(service, ids.queued_job_id, forged_key), 403),
        "tampered payload": (view_page(service, ids.queued_job_id, body[:-2] + "xx." + mac), 403),
        "mac only": (view_page(service, ids.queued_job_id, "." + mac), 403),
        "link of a revoked token": (view_page(service, ids.queued_job_id, revoked_link), 403),
        "B's session cookie": (view_page(service, ids.queued_job_id, cookies=b_cookie), 404),
        "stale view cookie of another job": (
            view_page(service, ids.queued_job_id, cookies={VIEW_COOKIE: other_job}),
            401,
        ),
    }
    wrong = {
        name: (response.status_code, expected)
        for name, (response, expected) in cases.items()
        if response.status_code != expected
    }
    leaks = [
        name
        for name, (response, _) in cases.items()
        if response.status_code != 409 and leaked_markers(response.text, world["markers"])
    ]
    record_figure(
        "view-links",
        load=f"{len(cases)} page loads of a job's 3D view",
        faults="expired, forged, tampered, other-job, other-organisation and revoked links",
        inputs=f"{len(cases)} links/cookies",
        result=f"{len(wrong)} wrong statuses; {len(leaks)} leaks",
        statuses={name: response.status_code for name, (response, _) in cases.items()},
    )
    assert not wrong, wrong
    assert not leaks, leaks


def websocket_handshake(
    service: ApiServer, job_id: str, cookies: dict[str, str], origin: str | None = None
) -> int:
    """The HTTP status of the 3D view's websocket handshake (101 when it was accepted)."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    url = service.base_url.replace("http://", "ws://") + f"/jobs/{job_id}/view"
    headers = {"Cookie": "; ".join(f"{name}={value}" for name, value in cookies.items())}
    if origin is not None:
        headers["Origin"] = origin
    try:
        with connect(url, additional_headers=headers, open_timeout=10):
            return 101
    except InvalidStatus as exc:
        return exc.response.status_code


def test_the_view_websocket_opens_only_for_the_owner(service: ApiServer, world: dict) -> None:
    ids: Objects = world["ids"]
    callers = {caller.name: caller for caller in world["callers"]}
    owner_cookie = callers["A-reader-session-cookie"].cookies
    with transaction(service.settings.sqlalchemy_url) as session:
        writer_token = session.scalar(
            select(ApiToken).where(
                ApiToken.token_hash == hash_token(world["tokens"][("A", "writer")])
            )
        )
        assert writer_token is not None
        expired, _ = make_view_link(ids.job_id, writer_token, secret_key(service.settings), -5)
    cases = {
        # Accepted, then closed with the reason (the queued job has no view yet): no viewer starts.
        "A's session, queued job": (
            websocket_handshake(service, ids.queued_job_id, owner_cookie),
            101,
        ),
        "no credentials": (websocket_handshake(service, ids.job_id, {}), 403),
        "B's session cookie": (
            websocket_handshake(service, ids.job_id, callers["B-session-cookie"].cookies),
            403,
        ),
        "expired view-link cookie": (
            websocket_handshake(service, ids.job_id, {VIEW_COOKIE: expired}),
            403,
        ),
        "A's session from another origin": (
            websocket_handshake(service, ids.job_id, owner_cookie, origin="http://evil.example"),
            403,
        ),
    }
    wrong = {name: pair for name, pair in cases.items() if pair[0] != pair[1]}
    record_figure(
        "view-websocket",
        load=f"{len(cases)} websocket handshakes on the 3D view",
        faults="no credentials, other organisation's cookie, expired link, cross-origin",
        inputs=f"{len(cases)} handshakes",
        result=f"{len(wrong)} wrong; statuses { {name: got for name, (got, _) in cases.items()} }",
    )
    assert not wrong, wrong

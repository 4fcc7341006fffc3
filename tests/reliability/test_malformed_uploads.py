"""Issue 5 (4): a malformed-file corpus uploaded over HTTP never breaks the service.

Every bad file of the core's reader corpus (``tests/core/test_formats.py``: truncations, wrong
magic, header counts that disagree with the body, 2^31-point headers, compressed-PCD and LAZ
chunk-table bombs...) is sent raw with its name, as a multipart form and raw without a name
(format sniffed from the content); to those come zero-point and NaN/inf clouds in every format,
an npz deflate bomb, path-traversal and non-UTF-8 file names, polyglots and random mutations of
valid files.  Pass: each answer is a 4xx JSON error with a useful message (mutations may also be
valid files, then 202), never a 5xx nor a logged unhandled error; rejected uploads leave no scan
row, job row or file; the service still answers and accepts a good scan afterwards.
"""

from __future__ import annotations

import functools
import io
import json
import logging
import os
import subprocess
import sys
import time
import zipfile
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

import httpx
import numpy as np
import pytest

from app.db.models import Job, Scan
from app.testing.files import las_bytes, npy_bytes, npz_bytes, pcd_bytes, ply_bytes, text_bytes
from app.testing.paths import PROJECT_ROOT
from app.testing.scenes import random_points, room_points
from tests.helpers.corpus import (
    FUZZ_SEEDS,
    MALFORMED,
    las_with_point_count,
    mutate_bytes,
    npy_header,
)
from tests.helpers.database import count_rows
from tests.helpers.figures import record_figure
from tests.helpers.http import create_site, upload
from tests.helpers.server import ApiServer

ACCEPTABLE_REJECTIONS = frozenset({400, 413, 415, 422})
MUTATIONS_PER_FORMAT = 8
MIN_USEFUL_DETAIL_CHARACTERS = 12
SERVICE_FRAGMENTS = {"laz-absurd-count": "more than the limit"}
"""Reader-corpus cases whose message differs behind the service (its max_points answers first)."""


@dataclass(frozen=True)
class BadUpload:
    """One upload of the corpus and what its rejection must say."""

    name: str
    content: bytes
    filename: str | None = None
    multipart: bool = False
    raw_multipart_filename: bytes | None = None
    fragment: str | None = None
    may_be_valid: bool = False


@functools.cache
def _npz_deflate_bomb() -> bytes:
    """points.npy claiming 2^31 x 3 float64, followed by 64 MB of zeros deflated to ~64 kB."""
    member = npy_header((2**31, 3)) + bytes(64 * 1024 * 1024)
    stream = io.BytesIO()
    with zipfile.ZipFile(stream, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("points.npy", member)
    return stream.getvalue()


def _reader_corpus_uploads() -> Iterator[BadUpload]:
    for case, (filename, build, fragment) in sorted(MALFORMED.items()):
        content = build()
        if not content:  # the service refuses an empty body before the reader sees it
            fragment = "empty"
        fragment = SERVICE_FRAGMENTS.get(case, fragment)
        yield BadUpload(f"{case}/raw", content, filename, fragment=fragment)
        yield BadUpload(f"{case}/multipart", content, filename, multipart=True, fragment=fragment)
        yield BadUpload(f"{case}/sniffed", content, None)


def _empty_and_non_finite_uploads() -> Iterator[BadUpload]:
    zero = np.zeros((0, 3))
    nan = np.full((64, 3), np.nan)
    inf = np.full((64, 3), np.inf)
    builders = {
        "ply": lambda p: ply_bytes(p),
        "pcd": lambda p: pcd_bytes(p, "ascii"),
        "npy": npy_bytes,
        "npz": lambda p: npz_bytes(points=p),
        "xyz": lambda p: text_bytes(p),
    }
    for suffix, build in builders.items():
        for label, points in (("zero-points", zero), ("all-nan", nan), ("all-inf", inf)):
            if suffix == "ply" and label != "all-inf":
                continue  # ply-zero-vertices and ply-nan-only are in the reader corpus
            yield BadUpload(f"{suffix}-{label}", build(points), f"scan.{suffix}")
    for suffix, compress in (("las", False), ("laz", True)):
        content = las_bytes(random_points(), compress=compress)
        yield BadUpload(f"{suffix}-zero-points", las_with_point_count(content, 0), f"scan.{suffix}")
        yield BadUpload(
            f"{suffix}-count-40M-in-a-small-file",
            las_with_point_count(content, 40_000_000),
            f"scan.{suffix}",
            fragment="absurd LAZ header" if compress else "truncated body",
        )
        yield BadUpload(
            f"{suffix}-count-2^31",
            las_with_point_count(content, 2**31),
            f"scan.{suffix}",
            fragment="limit" if suffix == "las" else None,
        )


def _bomb_uploads() -> Iterator[BadUpload]:
    yield BadUpload("npz-deflate-bomb", _npz_deflate_bomb(), "scan.npz", fragment="limit")
    yield BadUpload("npz-deflate-bomb/sniffed", _npz_deflate_bomb(), None, fragment="limit")


def _hostile_name_uploads() -> Iterator[BadUpload]:
    truncated_ply = ply_bytes(random_points())[:-7]
    for label, name in (
        ("traversal-posix", "../../../../etc/passwd.ply"),
        ("traversal-windows", "..\\..\\Windows\\system32\\scan.ply"),
        ("absolute", "/etc/shadow.ply"),
        ("nul-byte", "scan\x00.ply"),
        ("control-characters", "scan\r\n\x1b[31m.ply"),
        ("only-dots", "...."),
        ("too-long", "a" * 1200 + ".ply"),
        ("unicode-direction", "scan\u202egnp.ply"),
    ):
        yield BadUpload(f"name-{label}/raw", truncated_ply, name)
        yield BadUpload(f"name-{label}/multipart", truncated_ply, name, multipart=True)
    for label, raw in (
        ("invalid-utf8", b"\xff\xfe\xfd.ply"),
        ("latin1", "mesure-\u00e9t\u00e9.ply".encode("latin-1")),
        ("traversal-bytes", b"..\\../\xc0\xaf..\xc0\xafetc/passwd.ply"),
        ("overlong-slash", b"\xc0\xae\xc0\xae\xc0\xafscan.ply"),
    ):
        yield BadUpload(
            f"name-{label}/multipart-bytes", truncated_ply, None, raw_multipart_filename=raw
        )


def _polyglot_uploads() -> Iterator[BadUpload]:
    ply = ply_bytes(random_points())
    pcd = pcd_bytes(random_points())
    las = las_bytes(random_points())
    npz = npz_bytes(points=random_points())
    npy = npy_bytes(random_points())
    yield BadUpload("polyglot-gif-ply", b"GIF89a\x01\x00\x01\x00" + ply, "scan.ply")
    yield BadUpload("polyglot-pdf-ply", b"%PDF-1.7\n%\xe2\xe3\xcf\xd3\n" + ply, "scan.ply")
    yield BadUpload("polyglot-html-ply", b"<html><script>alert(1)</script>" + ply, "scan.ply")
    yield BadUpload("polyglot-ply-header-pcd-body", ply.split(b"end_header\n")[0] + pcd, None)
    yield BadUpload("polyglot-npy-magic-ply", b"\x93NUMPY\x01\x00" + ply, "scan.npy")
    yield BadUpload(
        "polyglot-pcd-header-las-body", pcd.split(b"DATA")[0] + b"DATA binary\n" + las, "scan.pcd"
    )
    yield BadUpload("polyglot-las-magic-pcd", b"LASF" + pcd, "scan.las")
    # These are valid files under a foreign name or wrapper: the content may win (accepted).
    yield BadUpload("polyglot-ply-then-zip", ply + npz, "scan.npz", may_be_valid=True)
    yield BadUpload("polyglot-zip-named-ply", npz, "scan.ply", may_be_valid=True)
    yield BadUpload("polyglot-las-named-pcd", las, "scan.pcd", may_be_valid=True)
    yield BadUpload("polyglot-npy-named-xyz", npy, "scan.xyz", may_be_valid=True)
    yield BadUpload("polyglot-ply-then-las", ply + las, "scan.ply", may_be_valid=True)


def _mutated_uploads() -> Iterator[BadUpload]:
    """Byte flips, truncations and insertions of valid files (some stay valid: 2xx allowed)."""
    for kind, build in sorted(FUZZ_SEEDS.items()):
        content = build(random_points(200))
        rng = np.random.default_rng(1000 + sorted(FUZZ_SEEDS).index(kind))
        for index in range(MUTATIONS_PER_FORMAT):
            data = mutate_bytes(bytearray(content), rng, index % 4, min_length=1)
            suffix = kind.split("-")[0]
            yield BadUpload(
                f"mutated-{kind}-{index}", bytes(data), f"scan.{suffix}", may_be_valid=True
            )


def build_corpus() -> list[BadUpload]:
    """Every upload of the corpus, in a fixed order."""
    return [
        *_reader_corpus_uploads(),
        *_empty_and_non_finite_uploads(),
        *_bomb_uploads(),
        *_hostile_name_uploads(),
        *_polyglot_uploads(),
        *_mutated_uploads(),
    ]


def send(client: httpx.Client, site_id: str, item: BadUpload) -> httpx.Response:
    """Upload ``item`` as a comparison scan of ``site_id``."""
    if item.raw_multipart_filename is not None:
        boundary = "reliabilityboundary"
        body = (
            f"--{boundary}\r\n".encode()
            + b'Content-Disposition: form-data; name="file"; filename="'
            + item.raw_multipart_filename
            + b'"\r\nContent-Type: application/octet-stream\r\n\r\n'
            + item.content
            + f"\r\n--{boundary}--\r\n".encode()
        )
        return client.post(
            f"/api/v1/sites/{site_id}/scans",
            content=body,
            headers={"Content-Type": f"multipart/form-data; boundary={boundary}"},
        )
    return upload(client, site_id, item.content, filename=item.filename, multipart=item.multipart)


class ErrorRecords(logging.Handler):
    """Keeps every ERROR (and worse) record logged while installed."""

    def __init__(self) -> None:
        super().__init__(level=logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def rows_of_site(service: ApiServer, site_id: str) -> tuple[int, int]:
    """``(scans, jobs)`` rows of the site in the database."""
    return count_rows(service, Scan, site_id=site_id), count_rows(service, Job, site_id=site_id)


def problem_with(item: BadUpload, response: httpx.Response) -> str | None:
    """Why this answer is not acceptable for this upload (None when it is)."""
    status = response.status_code
    if status >= 500:
        return f"{status} {response.text[:300]}"
    if status in (201, 202):
        return None if item.may_be_valid else f"accepted a bad file: {response.text[:200]}"
    if status not in ACCEPTABLE_REJECTIONS:
        return f"unexpected status {status}: {response.text[:200]}"
    try:
        body = response.json()
    except ValueError:
        return f"{status} without a JSON body: {response.text[:200]}"
    detail = body.get("detail") if isinstance(body, dict) else None
    if set(body) != {"error", "detail"} or not isinstance(detail, str):
        return f"{status} with an unexpected body shape: {body}"
    if len(detail) < MIN_USEFUL_DETAIL_CHARACTERS or "Traceback" in detail:
        return f"{status} with an unhelpful detail: {detail!r}"
    if item.fragment is not None and item.fragment not in detail:
        return f"{status} detail lacks {item.fragment!r}: {detail!r}"
    return None


def test_the_malformed_corpus_over_http_is_rejected_cleanly(service: ApiServer) -> None:
    corpus = build_corpus()
    assert len(corpus) >= 200, len(corpus)
    client = service.client(service.token("writer"))
    site = create_site(client)
    reference = upload(client, site["id"], ply_bytes(room_points(3000, seed=1)), reference=True)
    assert reference.status_code == 201, reference.text
    errors = ErrorRecords()
    logging.getLogger().addHandler(errors)
    statuses: Counter[int] = Counter()
    error_codes: Counter[str] = Counter()
    problems: list[str] = []
    outcomes: dict[str, int] = {}
    accepted = 0
    started = time.monotonic()
    try:
        for item in corpus:
            response = send(client, site["id"], item)
            statuses[response.status_code] += 1
            if response.status_code in (201, 202):
                accepted += 1
            elif response.headers.get("content-type", "").startswith("application/json"):
                error_codes[str(response.json().get("error"))] += 1
            outcomes[item.name] = response.status_code
            problem = problem_with(item, response)
            if problem is not None:
                problems.append(f"{item.name}: {problem}")
    finally:
        logging.getLogger().removeHandler(errors)
    elapsed = time.monotonic() - started
    health = client.get("/api/v1/health")
    good = upload(client, site["id"], ply_bytes(room_points(2000, seed=5)), filename="good.ply")
    scans, jobs = rows_of_site(service, site["id"])
    site_files = sorted((service.settings.scans_dir / site["id"]).iterdir())
    leftovers = sorted(service.settings.tmp_dir.iterdir())
    server_errors = sum(count for status, count in statuses.items() if status >= 500)
    record_figure(
        "malformed-uploads",
        load=f"{len(corpus)} sequential uploads over HTTP (raw, multipart, sniffed)",
        faults="malformed files in every format, bombs, hostile names, polyglots, mutations",
        inputs=f"{len(corpus)} files",
        result=(
            f"statuses {dict(sorted(statuses.items()))}; {server_errors} server errors; "
            f"{len(problems)} bad answers; {len(errors.records)} logged errors; "
            f"{accepted} valid mutations accepted; leftovers: {len(leftovers)} tmp files; "
            f"{elapsed:.1f} s"
        ),
        statuses=dict(statuses),
        error_codes=dict(error_codes),
        problems=problems,
        outcomes=outcomes,
    )
    assert not problems, f"{len(problems)} of {len(corpus)} answers are wrong:\n" + "\n".join(
        problems
    )
    assert not errors.records, [record.getMessage() for record in errors.records]
    assert health.status_code == 200, health.text
    assert good.status_code == 202, good.text
    # The reference, the accepted mutations and the good scan: nothing else left a row or file.
    assert (scans, jobs) == (accepted + 2, accepted + 1), (scans, jobs, accepted)
    assert len(site_files) == accepted + 2, site_files
    assert leftovers == [], leftovers


def test_the_corpus_is_large_and_covers_every_format() -> None:
    corpus = build_corpus()
    suffixes = Counter((item.filename or "").rsplit(".", 1)[-1] for item in corpus if item.filename)
    print(
        f"\n[reliability] corpus: {len(corpus)} files, by suffix {dict(sorted(suffixes.items()))}"
    )
    assert len(corpus) >= 200
    for suffix in ("ply", "pcd", "las", "laz", "xyz", "csv", "txt", "npy", "npz"):
        assert suffixes[suffix] > 0, (suffix, suffixes)


WORKER_MEMORY_CAP_BYTES = 3 * 1024**3
RUN_JOBS_IN_A_WORKER = """
import json, sys
from app.config import Settings
from app.jobs.execution import execute_job
settings = Settings()
for job_id in sys.argv[1:]:
    print(json.dumps({"job_id": job_id, "outcome": execute_job(job_id, settings)}), flush=True)
"""


@pytest.mark.slow
def test_accepted_strange_files_end_succeeded_or_failed_with_a_reason(
    service: ApiServer,
) -> None:
    """Mutations and polyglots that the reader accepts get a job; a worker process (memory
    capped with RLIMIT_AS) runs each: it ends ``succeeded`` or ``failed`` with a reason and the
    worker survives every one of them."""
    client = service.client(service.token("writer"))
    site = create_site(client)
    reference = upload(client, site["id"], ply_bytes(room_points(3000, seed=1)), reference=True)
    assert reference.status_code == 201, reference.text
    job_ids: dict[str, str] = {}
    for item in build_corpus():
        if item.may_be_valid:
            response = send(client, site["id"], item)
            assert response.status_code < 500, (item.name, response.text)
            if response.status_code == 202:
                job_ids[response.json()["job"]["id"]] = item.name
    assert job_ids, "no strange file was accepted: nothing to run"
    environment = {
        **os.environ,
        "SCANDIFF_DATA_DIR": str(service.settings.data_dir),
        "SCANDIFF_JOB_MEMORY_LIMIT_BYTES": str(WORKER_MEMORY_CAP_BYTES),
        "OMP_NUM_THREADS": "1",
    }
    started = time.monotonic()
    worker = subprocess.run(
        [sys.executable, "-c", RUN_JOBS_IN_A_WORKER, *job_ids],
        cwd=PROJECT_ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=900,
    )
    elapsed = time.monotonic() - started
    outcomes = {
        entry["job_id"]: entry["outcome"]
        for entry in (
            json.loads(line) for line in worker.stdout.splitlines() if line.startswith("{")
        )
    }
    rows = {job_id: client.get(f"/api/v1/jobs/{job_id}").json() for job_id in job_ids}
    statuses = Counter(row["status"] for row in rows.values())
    failed_without_reason = [
        job_ids[job_id]
        for job_id, row in rows.items()
        if row["status"] == "failed" and not row["error"]
    ]
    reasons = Counter(str(row["error"])[:80] for row in rows.values() if row["status"] == "failed")
    record_figure(
        "accepted-strange-files-in-a-worker",
        load=f"{len(job_ids)} jobs in one worker process (RLIMIT_AS {WORKER_MEMORY_CAP_BYTES} B)",
        faults="valid-but-strange uploads: byte mutations, polyglots, foreign suffixes",
        inputs=f"{len(job_ids)} accepted files",
        result=(
            f"job statuses {dict(statuses)}; worker exit {worker.returncode}; "
            f"{len(failed_without_reason)} failed without a reason; {elapsed:.1f} s"
        ),
        failure_reasons=dict(reasons),
    )
    assert worker.returncode == 0, worker.stderr[-3000:]
    assert set(outcomes) == set(job_ids), worker.stderr[-3000:]
    assert set(statuses) <= {"succeeded", "failed"}, statuses
    assert not failed_without_reason, failed_without_reason

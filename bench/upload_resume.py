"""A resumable (tus) upload of a large scan, cut at 80 % and resumed by a new client.

Starts the real ``scandiff serve`` (app/testing/service.py) on a fresh data directory, writes
a binary PLY of about ``--megabytes`` MB (float32 x, y, z), and uploads it as a site's reference
through ``/api/v1/uploads`` with the maintained ``tuspy`` client in ``--chunk-megabytes``
chunks, each with its SHA-256 ``Upload-Checksum`` and the whole file's SHA-256 in the metadata.
The first client stops after 80 % of the file (the link is lost); a second client asks HEAD for
the offset and sends the rest; the last PATCH makes the scan (checksum, validation, summary,
atomic store).  Prints the throughput of both parts, the resumed byte count, the time of the
completing PATCH, whether the stored scan's SHA-256 is the file's, and for comparison the
same file's time as one plain ``POST /api/v1/sites/{id}/scans``.

Run: ``.venv/bin/python -m bench.upload_resume [--megabytes 200] [--chunk-megabytes 8]``.
"""

from __future__ import annotations

import argparse
import hashlib
import tempfile
import time
from pathlib import Path

import numpy as np
from tusclient.client import TusClient
from tusclient.uploader import Uploader

from app.testing.service import ServiceProcess

WRITE_POINTS = 1_000_000
"""Points generated and written at a time."""
CUT_SHARE = 0.8


class Sha256Uploader(Uploader):
    """tuspy's uploader with SHA-256 chunk checksums (its default is SHA-1)."""

    CHECKSUM_ALGORITHM_PAIR = ("sha256", hashlib.sha256)


def write_ply(path: Path, megabytes: float, seed: int = 5) -> str:
    """A binary PLY of random float32 points of about ``megabytes`` MB; its SHA-256."""
    n_points = int(megabytes * 1e6) // 12
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n_points}\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n"
    ).encode()
    rng = np.random.default_rng(seed)
    hasher = hashlib.sha256(header)
    with open(path, "wb") as output:
        output.write(header)
        for start in range(0, n_points, WRITE_POINTS):
            count = min(WRITE_POINTS, n_points - start)
            block = rng.uniform(-50.0, 50.0, size=(count, 3)).astype("<f4").tobytes()
            hasher.update(block)
            output.write(block)
    return hasher.hexdigest()


def main() -> None:
    """Upload, cut, resume, complete; print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--megabytes", type=float, default=200.0)
    parser.add_argument("--chunk-megabytes", type=float, default=8.0)
    arguments = parser.parse_args()
    chunk_size = int(arguments.chunk_megabytes * 1e6)
    with tempfile.TemporaryDirectory(prefix="upload-resume-") as directory:
        path = Path(directory) / "survey.ply"
        sha256 = write_ply(path, arguments.megabytes)
        size = path.stat().st_size
        service = ServiceProcess(
            Path(directory) / "data",
            workers=1,
            env={"SCANDIFF_MAX_UPLOAD_BYTES": str(size + 1), "SCANDIFF_MAX_POINTS": "100000000"},
        ).start()
        try:
            with service.client() as client:
                response = client.post("/api/v1/sites", json={"name": "survey"})
                response.raise_for_status()
                site_id = response.json()["id"]
            tus = TusClient(
                f"{service.base_url}/api/v1/uploads",
                headers={"Authorization": f"Bearer {service.admin_token}"},
            )
            cut = int(CUT_SHARE * size)
            with open(path, "rb") as stream:
                first = Sha256Uploader(
                    file_stream=stream,
                    client=tus,
                    chunk_size=chunk_size,
                    upload_checksum=True,
                    metadata={
                        "site": site_id,
                        "filename": "survey.ply",
                        "reference": "true",
                        "checksum": f"sha256:{sha256}",
                    },
                )
                started = time.perf_counter()
                first.upload(stop_at=cut)
                first_seconds = time.perf_counter() - started
                url, sent_before_cut = first.url, first.offset
            with open(path, "rb") as stream:
                started = time.perf_counter()
                second = Sha256Uploader(
                    file_stream=stream,
                    client=tus,
                    url=url,
                    chunk_size=chunk_size,
                    upload_checksum=True,
                )
                resumed_from = second.offset  # from HEAD
                last_chunk_seconds = 0.0
                while second.offset < size:
                    chunk_started = time.perf_counter()
                    second.upload_chunk()
                    last_chunk_seconds = time.perf_counter() - chunk_started
                second_seconds = time.perf_counter() - started
            with service.client(timeout=600) as client:
                state = client.get(url.removeprefix(service.base_url)).json()
                scan = state["result"]["scan"]
                with open(path, "rb") as stream:  # the same file as one plain upload
                    started = time.perf_counter()
                    plain = client.post(
                        f"/api/v1/sites/{site_id}/scans",
                        params={"reference": "true", "filename": "plain.ply"},
                        content=iter(lambda: stream.read(1 << 20), b""),
                        headers={"Content-Type": "application/octet-stream"},
                    )
                    plain_seconds = time.perf_counter() - started
                plain.raise_for_status()
        finally:
            service.stop()
    megabyte = 1e6
    resumed_bytes = size - resumed_from
    print(f"file: {size / megabyte:.1f} MB binary PLY, {scan['n_points']:,} points")
    print(f"chunks: {chunk_size / megabyte:.1f} MB, each with a SHA-256 Upload-Checksum")
    print(
        f"before the cut: {sent_before_cut / megabyte:.1f} MB in {first_seconds:.2f} s "
        f"({sent_before_cut / megabyte / first_seconds:.1f} MB/s)"
    )
    print(
        f"resumed from HEAD's offset {resumed_from:,}: {resumed_bytes:,} bytes resumed "
        f"({resumed_bytes / size:.1%} of the file, none sent twice: "
        f"{sent_before_cut + resumed_bytes == size})"
    )
    print(
        f"after the cut: {resumed_bytes / megabyte:.1f} MB in {second_seconds:.2f} s "
        f"({resumed_bytes / megabyte / second_seconds:.1f} MB/s, including the completing PATCH)"
    )
    print(
        f"completing PATCH (last chunk + checksum + validation + store): {last_chunk_seconds:.2f} s"
    )
    total_seconds = first_seconds + second_seconds
    print(f"overall: {size / megabyte / total_seconds:.1f} MB/s")
    print(
        f"the same file as one plain POST: {plain_seconds:.2f} s "
        f"({size / megabyte / plain_seconds:.1f} MB/s)"
    )
    print(f"state: {state['state']}, status {state['result_status']}")
    print(f"stored scan sha256 matches the file: {scan['sha256'] == sha256}")


if __name__ == "__main__":
    main()

"""Storage helpers: file-name sanitising and the start-up sweep of leftovers."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.models import Organisation, Scan, Site
from app.db.session import transaction
from app.services.storage import (
    ensure_directories,
    sanitise_filename,
    sweep_temporary_files,
)
from tests.helpers.http import unique_name
from tests.helpers.jobs import new_job


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ("scan.ply", "scan.ply"),
        ("../../etc/passwd", "passwd"),
        ("C:\\Users\\robot\\scan 01.laz", "scan 01.laz"),
        ("/abs/path/.hidden.pcd", "hidden.pcd"),
        ("..", None),
        ("", None),
        (None, None),
        ("a\x00b\nc.ply", "a_b_c.ply"),
        ("bad\udcffbyte.ply", "bad_byte.ply"),  # an undecodable byte (surrogate escape)
        ("Straße.ply", "Straße.ply"),
        ("x" * 400 + ".ply", "x" * 251 + ".ply"),
        ("name;rm -rf $HOME|.ply", "name_rm -rf _HOME_.ply"),
    ],
)
def test_sanitise_filename(given: str | None, expected: str | None) -> None:
    assert sanitise_filename(given) == expected


def test_long_unicode_names_stay_within_255_bytes() -> None:
    cleaned = sanitise_filename("é" * 300 + ".ply")
    assert cleaned is not None and cleaned.endswith(".ply")
    assert len(cleaned.encode()) <= 255


def test_the_sweep_removes_leftovers_and_keeps_what_rows_reference(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path / "data")
    ensure_directories(settings)
    upgrade_to_head(settings.sqlalchemy_url)
    with transaction(settings.sqlalchemy_url) as session:
        organisation = Organisation(name=unique_name("sweep"))
        session.add(organisation)
        session.flush()
        site = Site(organisation_id=organisation.id, name="s")
        session.add(site)
        session.flush()
        scan = Scan(
            organisation_id=organisation.id,
            site_id=site.id,
            filename="a.ply",
            format="ply",
            size_bytes=1,
            sha256="0" * 64,
            storage_path=f"scans/{site.id}/{'a' * 32}.ply",
            n_points=10,
            bbox_min=[0, 0, 0],
            bbox_max=[1, 1, 1],
        )
        session.add(scan)
        # a row pointing outside the data directory (its jobs fail saying so): no reason to stop
        session.add(
            Scan(
                organisation_id=organisation.id,
                site_id=site.id,
                filename="outside.ply",
                format="ply",
                size_bytes=1,
                sha256="0" * 64,
                storage_path=str(tmp_path / "elsewhere" / "outside.ply"),
                n_points=10,
                bbox_min=[0, 0, 0],
                bbox_max=[1, 1, 1],
            )
        )
        session.flush()
        job = new_job(site, scan.id, scan.id)
        session.add(job)
        session.flush()
        site_id, job_id = site.id, job.id
    kept_scan = settings.scans_dir / site_id / f"{'a' * 32}.ply"
    kept_cache = kept_scan.with_suffix(".geometry")  # the reference's k-NN geometry cache
    kept_trajectory = kept_scan.with_name(kept_scan.name + ".trajectory.npz")  # sent with it
    kept_bag_options = kept_scan.with_name(kept_scan.name + ".bag-options.json")
    orphan_scan = settings.scans_dir / site_id / f"{'b' * 32}.ply"
    orphan_trajectory = orphan_scan.with_name(orphan_scan.name + ".trajectory.npz")
    orphan_cache = orphan_scan.with_suffix(".geometry")
    orphan_site_directory = settings.scans_dir / ("c" * 32)
    kept_results = settings.results_dir / job_id
    orphan_results = settings.results_dir / ("d" * 32)
    foreign_results = settings.results_dir / "not-a-job-directory"
    temporary = settings.tmp_dir / "123-abc.part"
    for path in (
        kept_scan,
        kept_cache,
        kept_trajectory,
        kept_bag_options,
        orphan_scan,
        orphan_cache,
        orphan_trajectory,
        orphan_site_directory / "x.ply",
        temporary,
    ):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"data")
    for directory in (kept_results, orphan_results, foreign_results):
        directory.mkdir(parents=True)
        (directory / "labels.npz").write_bytes(b"npz")

    # A periodic sweep with a grace period leaves fresh files alone.
    assert sweep_temporary_files(settings, min_age_seconds=3600) == 0
    assert temporary.exists() and orphan_scan.exists()

    old = time.time() - 10
    os.utime(temporary, (old, old))
    removed = sweep_temporary_files(settings)
    assert removed == 6
    assert kept_scan.exists() and kept_results.exists() and foreign_results.exists()
    assert kept_cache.exists() and kept_trajectory.exists() and kept_bag_options.exists()
    assert not orphan_trajectory.exists()
    assert not temporary.exists()
    assert not orphan_scan.exists() and not orphan_cache.exists()
    assert not orphan_site_directory.exists()
    assert not orphan_results.exists()


def test_the_sweep_survives_an_unmigrated_database(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path)
    ensure_directories(settings)
    (settings.tmp_dir / "1-x.part").write_bytes(b"x")
    assert sweep_temporary_files(settings) == 1


@pytest.mark.parametrize("data_dir_shared", [False, True])
def test_an_api_only_start_spares_uploads_other_processes_are_writing(
    tmp_path: Path, data_dir_shared: bool
) -> None:
    """``scandiff serve --workers 0`` shares its data directory: a fresh upload elsewhere stays."""
    from app.cli.serve import prepare

    settings = Settings(data_dir=tmp_path / "data")
    ensure_directories(settings)
    in_flight = settings.tmp_dir / "456-def.part"  # another replica's upload, still streaming
    unreferenced = settings.scans_dir / ("e" * 32) / "just-installed.ply"  # row not yet inserted
    for path in (in_flight, unreferenced):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"data")
    prepare(settings, data_dir_shared=data_dir_shared)
    assert in_flight.exists() is data_dir_shared
    assert unreferenced.exists() is data_dir_shared

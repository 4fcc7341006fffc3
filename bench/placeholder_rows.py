"""Rows the database benchmarks stand on: an organisation, its sites and placeholder scans.

``bench.job_list``, ``bench.regions_page`` and ``bench.metrics_scrape`` time reads of job and
region rows; those rows need an organisation, sites and scans to point at, whose files are
never read (a scan row here has no file: only its columns matter to the queries timed).
"""

from __future__ import annotations

from collections.abc import Callable

from app.config import Settings
from app.db.models import Organisation, Scan, Site, new_id
from app.db.session import transaction

__all__ = ["placeholder_organisation"]


def placeholder_organisation(
    settings: Settings,
    *,
    n_sites: int = 1,
    scan_size: Callable[[], int] = lambda: 1000,
) -> tuple[str, dict[str, list[str]]]:
    """Insert one organisation with ``n_sites`` sites of two placeholder scans each.

    Sites are named ``bench`` (one site) or ``site 0``, ``site 1``...; each scan's
    ``size_bytes`` is ``scan_size()``, called once per scan in order (reference, then scan, site
    by site).  Returns the organisation's id and each site's ``[reference, scan]`` scan ids.
    """
    organisation = new_id()
    scans = {new_id(): [new_id(), new_id()] for _ in range(n_sites)}
    with transaction(settings.sqlalchemy_url) as session:
        session.add(Organisation(id=organisation, name=f"bench-{organisation[:8]}"))
        session.flush()  # no relationships between these models: insert parents first
        for index, site in enumerate(scans):
            name = "bench" if n_sites == 1 else f"site {index}"
            session.add(Site(id=site, organisation_id=organisation, name=name))
        session.flush()
        for site, scan_ids in scans.items():
            for scan_id in scan_ids:
                session.add(
                    Scan(
                        id=scan_id,
                        organisation_id=organisation,
                        site_id=site,
                        filename="scan.ply",
                        format="ply",
                        size_bytes=scan_size(),
                        sha256="0" * 64,
                        storage_path=f"scans/{site}/{scan_id}.ply",
                        n_points=1000,
                        bbox_min=[0.0, 0.0, 0.0],
                        bbox_max=[1.0, 1.0, 1.0],
                    )
                )
    return organisation, scans

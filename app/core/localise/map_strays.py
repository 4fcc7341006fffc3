"""A fused map's stray samples left out of the comparison, then given back their places.

:mod:`~app.core.localise.stray_samples` keeps a map's stray samples (flying pixels, lone
returns) from being change candidates.  They are no surface either for the other cloud: a
chair turned in place has its new silhouette's flying pixels scattered through the old
chair's place, and each old chair point with one of them nearer than the change threshold
was "on the scan's surface" (RGB-D room 303 with drift: 375 of the 439 old chair points that
had a scan point within 10 cm had a stray one; the turned chair 99 % -> 36 %).  So a cloud
given without origins or a trajectory (a map, "nothing given") is compared without its stray
samples (:func:`~app.core.localise.stray_samples.cloud_strays`), and they come back unchanged,
in no region, their distance NaN.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from app.core.localise.changes import Localisation
from app.core.localise.epoch import EpochCloud
from app.core.localise.regions import ChangedRegion
from app.core.localise.stray_samples import cloud_strays

__all__ = ["map_kept", "with_strays_back"]


def map_kept(epoch: EpochCloud) -> NDArray[np.int64] | None:
    """Indices (k,) of ``epoch``'s points that are no stray sample when it is a map given
    without origins or trajectory and has some; None to keep every point."""
    if epoch.origin is not None or epoch.trajectory_rays is not None:
        return None
    stray = cloud_strays(np.asarray(epoch.points, dtype=np.float64))
    return np.flatnonzero(~stray) if stray.any() else None


def with_strays_back(
    localisation: Localisation,
    kept: tuple[NDArray[np.int64] | None, NDArray[np.int64] | None],
    sizes: tuple[int, int],
) -> Localisation:
    """``localisation`` of the kept points (``kept[0]`` of the reference, ``kept[1]`` of the
    scan; None: all) over whole clouds of ``sizes`` points: strays unchanged, no region, NaN
    distance; regions' point indices into the whole clouds."""
    arrays = {}
    for side, rows, size in zip(("reference", "scan"), kept, sizes, strict=True):
        label = getattr(localisation, f"{side}_label")
        distance = getattr(localisation, f"{side}_distance")
        region = getattr(localisation, f"{side}_region")
        if rows is None:
            arrays.update(
                {f"{side}_label": label, f"{side}_distance": distance, f"{side}_region": region}
            )
            continue
        whole_label = np.zeros(size, dtype=label.dtype)
        whole_label[rows] = label
        whole_distance = np.full(size, np.nan, dtype=distance.dtype)
        whole_distance[rows] = distance
        whole_region = np.full(size, -1, dtype=region.dtype)
        whole_region[rows] = region
        arrays.update(
            {
                f"{side}_label": whole_label,
                f"{side}_distance": whole_distance,
                f"{side}_region": whole_region,
            }
        )

    def placed(region: ChangedRegion) -> ChangedRegion:
        rows = kept[0] if region.kind == "removed" else kept[1]
        if rows is None:
            return region
        return dataclasses.replace(region, point_indices=rows[region.point_indices])

    parameters = dict(localisation.parameters)
    for side, rows, size in zip(("reference", "scan"), kept, sizes, strict=True):
        parameters[f"{side}_strays_left_out"] = 0 if rows is None else int(size - len(rows))
    return dataclasses.replace(
        localisation,
        **arrays,
        regions=[placed(region) for region in localisation.regions],
        uncertain_regions=[placed(region) for region in localisation.uncertain_regions],
        parameters=parameters,
    )

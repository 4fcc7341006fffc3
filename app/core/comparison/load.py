"""Stage 1, **load**: the comparison's settings and both clouds in one local frame.

Both clouds are shifted by one rounded origin taken from the reference
(:func:`app.core.cloud.choose_local_origin`) so georeferenced coordinates keep their
millimetres in float arithmetic; every coordinate reported is shifted back.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, TypedDict

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud, choose_local_origin
from app.core.comparison_settings import ComparisonSettings, parse_comparison_params
from app.core.detectors import canonical_method, warm_up
from app.core.threads import available_threads


@dataclass
class LoadedPair:
    """Both clouds of a comparison, its settings and its local frame.

    Not frozen for one reason: :meth:`release_scan_points` drops the scan's shifted copy once
    it is aligned (24 bytes a point when the files are georeferenced).

    Attributes
    ----------
    reference, scan : PointCloud
        The clouds as read from their files.
    method : str
        The detector's canonical name.
    variant : str
    settings : ComparisonSettings
        Every parameter, validated and split by stage.
    local_origin : ndarray, shape (3,)
        Subtracted from both clouds' file coordinates.
    reference_points : ndarray, shape (n, 3)
        The reference in the local frame (float64; float32 for a pair read lean).
    scan_points : ndarray, shape (m, 3), or None
        The scan in the local frame (None once released).
    threads : int
        Threads the localiser may use.
    """

    reference: PointCloud
    scan: PointCloud
    method: str
    variant: str
    settings: ComparisonSettings
    local_origin: NDArray[np.float64]
    reference_points: NDArray[np.float64]
    scan_points: NDArray[np.float64] | None
    threads: int

    def release_scan_points(self) -> None:
        """Drop the scan's local copy (the aligned scan replaces it)."""
        self.scan_points = None


class PairOptions(TypedDict, total=False):
    """The keyword arguments of :func:`load_pair`, which :func:`app.core.pipeline.compare` and
    :func:`app.core.tiling.compare.compare_tiled` pass on (documented there)."""

    method: str
    variant: str
    align: bool
    random_state: int
    params: Mapping[str, Any] | None
    threads: int | None
    frame_offset: NDArray[np.float64] | None


def load_pair(
    reference: PointCloud,
    scan: PointCloud,
    *,
    method: str = "gmm",
    variant: str = "improved",
    align: bool = True,
    random_state: int = 0,
    params: Mapping[str, Any] | None = None,
    threads: int | None = None,
    frame_offset: NDArray[np.float64] | None = None,
) -> LoadedPair:
    """Validate the parameters and bring both clouds into one local frame.

    Parameters are those of :func:`app.core.pipeline.compare`.  The detector's libraries
    start loading on a thread (:func:`app.core.detectors.warm_up`) while the clouds are
    aligned.

    ``frame_offset`` (shape (3,)): the clouds are already in a local frame, their file
    coordinates minus this offset (a pair read lean, :mod:`app.core.tiling.lean`, float32):
    it is the local origin, and the points are used as they are.

    Returns
    -------
    LoadedPair

    Raises
    ------
    InputError
        Unknown method, variant or parameter.
    """
    method = canonical_method(method)
    settings = parse_comparison_params(
        method, variant, params, random_state=random_state, align=align
    )
    warm_up()
    if frame_offset is not None:  # already local (read lean): no choice, no shift
        local_origin = np.asarray(frame_offset, dtype=np.float64).reshape(3)
        shifted = False
    else:
        local_origin = choose_local_origin(reference.points)
        # no copy when the data is already local (1M points: 24 MB a cloud); nothing below
        # modifies these arrays in place
        shifted = bool(local_origin.any())
    return LoadedPair(
        reference=reference,
        scan=scan,
        method=method,
        variant=variant,
        settings=settings,
        local_origin=local_origin,
        reference_points=reference.points - local_origin if shifted else reference.points,
        scan_points=scan.points - local_origin if shifted else scan.points,
        threads=available_threads() if threads is None else max(1, int(threads)),
    )

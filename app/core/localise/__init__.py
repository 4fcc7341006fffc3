"""Per-point change labels and changed regions between a reference scan and an aligned rescan.

The paper's scores say *whether* a site changed; this package says *where*.  Real rescans are
independent samplings at different densities from a moved sensor, with occlusions and sparse
far surfaces, so plain cloud-to-cloud nearest-neighbour distances with one global threshold
flood with false alarms.  The method (steps in :mod:`app.core.localise.changes`, reasons and
measured numbers in ``docs/localisation.md``) fits local surfaces, measures distances to the
other cloud's surface against a noise-calibrated threshold, tests what the other sensor could
see, and groups changed points into regions.

Modules, each depending only on those below it:

- :mod:`~app.core.localise.changes`: :func:`localise_changes` and :class:`Localisation`;
- :mod:`~app.core.localise.epoch`: :class:`EpochCloud`, one cloud and what is known of its
  sensor, as :func:`localise_changes` takes it;
- :mod:`~app.core.localise.visibility`: candidates become changed or unobserved;
- :mod:`~app.core.localise.rays`: the ray test from the other sensor's origin;
- :mod:`~app.core.localise.origin_free`: without any origin or station, the surface test
  (``origin_free_test="surfaces"``): sampling gap, shadow on the other's plane, or change;
- :mod:`~app.core.localise.regions`: connected regions of changed points;
- :mod:`~app.core.localise.distance`: point-to-surface distances, support factor, alignment
  residual, and the per-cloud :class:`~app.core.localise.distance.Side`;
- :mod:`~app.core.localise.surface`: plane fits, spacing and noise of each cloud;
- :mod:`~app.core.localise.neighbourhoods`: the k-NN search, in line or on its own thread;
- :mod:`~app.core.localise.settings`: keyword parameters and input checks.

This module lists the package's public names.  They are imported on first use (PEP 562): a
process that only needs one submodule (the geometry cache needs ``neighbourhoods`` and
``surface``) does not load the others, which import scipy (~0.3 CPU s a process start).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.core.localise.changes import Localisation, localise_changes
    from app.core.localise.epoch import EpochCloud
    from app.core.localise.neighbourhoods import (
        Neighbourhoods,
        NeighbourhoodSearch,
        nearest_neighbourhoods,
        neighbourhood_size,
        start_neighbourhood_search,
    )
    from app.core.localise.regions import ChangedRegion
    from app.core.localise.settings import DEFAULT_PARAMETERS

_SUBMODULE_OF_NAME = {
    "DEFAULT_PARAMETERS": "settings",
    "ChangedRegion": "regions",
    "EpochCloud": "epoch",
    "Localisation": "changes",
    "NeighbourhoodSearch": "neighbourhoods",
    "Neighbourhoods": "neighbourhoods",
    "localise_changes": "changes",
    "nearest_neighbourhoods": "neighbourhoods",
    "neighbourhood_size": "neighbourhoods",
    "start_neighbourhood_search": "neighbourhoods",
}

__all__ = [
    "DEFAULT_PARAMETERS",
    "ChangedRegion",
    "EpochCloud",
    "Localisation",
    "NeighbourhoodSearch",
    "Neighbourhoods",
    "localise_changes",
    "nearest_neighbourhoods",
    "neighbourhood_size",
    "start_neighbourhood_search",
]


def __getattr__(name: str) -> Any:
    """A public name, imported from its submodule on first use (then cached here)."""
    submodule = _SUBMODULE_OF_NAME.get(name)
    if submodule is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{submodule}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])

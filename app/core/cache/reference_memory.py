"""The interface a registration recalls its reference-only arrays through (a protocol).

:func:`~app.core.registration.register_scan` takes a :class:`ReferenceMemory`;
:mod:`app.core.cache.reference_alignment` keeps one in the reference's geometry cache file.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

__all__ = ["ReferenceMemory", "recalled"]


class ReferenceMemory(Protocol):
    """Arrays worked out from the reference alone, kept between its alignments.

    ``name`` says what an array is (``"spacing"``, ``"grid"``, ``"coarse"``, ``"fit"``) and
    ``parameters`` the numbers it was computed with; :meth:`recall` returns an array only for
    the same name and parameters (and the same reference, which the memory is for).
    """

    def recall(self, name: str, parameters: tuple[float, ...]) -> NDArray | None:
        """The array remembered for ``name`` and ``parameters``, or None."""
        ...

    def remember(self, name: str, parameters: tuple[float, ...], array: NDArray) -> None:
        """Keep ``array``, computed for ``name`` and ``parameters``."""
        ...


def recalled(
    memory: ReferenceMemory | None,
    name: str,
    parameters: tuple[float, ...],
    compute: Callable[[], NDArray[np.float64]],
) -> NDArray[np.float64]:
    """``memory``'s array for ``name`` and ``parameters``, else ``compute()`` (remembered)."""
    if memory is not None:
        found = memory.recall(name, parameters)
        if found is not None:
            return found
    array = compute()
    if memory is not None:
        memory.remember(name, parameters, array)
    return array

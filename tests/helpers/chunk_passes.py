"""A spy on ``for_each_chunk`` as one module calls it: the passes' chunk and thread counts.

Shared by the tests that check a pass is split into chunks on two threads (the same result as
on one): they patch the module's own ``for_each_chunk`` name and read what it was called with.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest


def recorded_chunk_passes(
    monkeypatch: pytest.MonkeyPatch, module: ModuleType
) -> list[tuple[int, int]]:
    """Patch ``module.for_each_chunk`` to record each call's (chunk count, threads) and still
    run the pass; the list the calls are appended to."""
    passes: list[tuple[int, int]] = []
    for_each_chunk = module.for_each_chunk

    def recorded(work: Any, chunks: Any, threads: int) -> None:
        chunks = list(chunks)
        passes.append((len(chunks), threads))
        for_each_chunk(work, chunks, threads)

    monkeypatch.setattr(module, "for_each_chunk", recorded)
    return passes

"""Faster parts of the station search (app.core.origins.concurrence) against plain references."""

from __future__ import annotations

import numpy as np

from app.core.origins import concurrence
from app.core.origins.columns import normal_z


def test_closed_form_normals_are_those_of_eigh():
    rng = np.random.default_rng(5)
    # patches of 8 points: flat at every tilt, noisy, thin (a line), and a few degenerate
    count = 20_000
    tilt = rng.normal(size=(count, 3))
    tilt /= np.linalg.norm(tilt, axis=1, keepdims=True)
    flat = rng.normal(size=(count, 8, 3)) * rng.uniform(0.01, 0.2, (count, 1, 1))
    flat -= np.einsum("nkd,nd->nk", flat, tilt)[..., None] * tilt[:, None, :]  # in the plane
    noise = rng.normal(size=(count, 8, 3)) * rng.choice([0.0, 1e-3, 1e-2], (count, 1, 1))
    neighbourhood = flat + noise + rng.uniform(-50.0, 50.0, (count, 1, 3))
    neighbourhood[:50] = neighbourhood[:50, :1]  # all eight at one point
    line = rng.normal(size=(50, 1, 3))
    neighbourhood[50:100] = line * rng.normal(size=(50, 8, 1))  # collinear

    centred = neighbourhood - neighbourhood.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    expected = np.abs(vectors[:, 2, 0])
    found = normal_z(neighbourhood)
    assert np.all((found >= 0.0) & (found <= 1.0 + 1e-12))
    # degenerate patches (no single least-variance direction) aside, the same normals
    defined = slice(100, None)
    np.testing.assert_allclose(found[defined], expected[defined], atol=1e-6)
    level = found >= concurrence.MIN_NORMAL_Z
    expected_level = expected >= concurrence.MIN_NORMAL_Z
    assert np.count_nonzero(level[defined] != expected_level[defined]) <= count // 1000


def _masked_votes(start_cell, direction, shape):
    """Reference for concurrence._hough_votes: every step of every line, those outside masked."""
    steps = concurrence._vote_steps()
    direction32 = direction.astype(np.float32)
    row = start_cell[:, 0, None] + steps * direction32[:, 0, None]
    column = start_cell[:, 1, None] + steps * direction32[:, 1, None]
    inside = (row >= 0) & (row < shape[0]) & (column >= 0) & (column < shape[1])
    cells = row[inside].astype(np.int64) * shape[1] + column[inside].astype(np.int64)
    return np.bincount(cells, minlength=int(shape[0] * shape[1])).astype(float)


def test_votes_of_the_runs_inside_the_grid_are_those_of_every_step_masked(monkeypatch):
    rng = np.random.default_rng(6)
    monkeypatch.setattr(concurrence, "VOTE_BATCH", 20_000)  # several batches
    for _ in range(12):
        shape = np.array(rng.integers(20, 900, 2), dtype=np.int64)
        count = int(rng.integers(1, 400))
        # anchors inside, near and on the edges and outside the grid (cell units)
        start_cell = rng.uniform(-60.0, 60.0, (count, 2)) + rng.uniform(0, 1, (count, 2)) * shape
        start_cell[: count // 4] = np.round(start_cell[: count // 4])
        angle = rng.uniform(0.0, 2 * np.pi, count)
        direction = np.column_stack([np.cos(angle), np.sin(angle)])
        direction[: count // 8] = np.round(direction[: count // 8])  # axis-parallel, zeros
        direction[count // 8 : count // 6] *= -1.0
        start_cell = start_cell.astype(np.float32)
        votes = concurrence._hough_votes(start_cell, direction, shape)
        np.testing.assert_array_equal(votes, _masked_votes(start_cell, direction, shape))

"""The compiled k-NN (``app/core/localise/_knn_kernel.c``, built by setup.py where a C compiler
is) against the pykdtree queries it replaces and that run without it: the same neighbours and
k-th distances to the bit, ties (equally far points) left to pykdtree, the same labels."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.datasets.lidar import lidar_pair
from app.core.datasets.scenes import raycast_scene
from app.core.localise import neighbourhoods, regions
from app.core.localise.neighbourhoods import nearest_neighbourhoods
from app.core.pipeline import compare
from tests.helpers.environment import c_compiler_found

KERNEL = neighbourhoods.KNN_KERNEL
needs_kernel = pytest.mark.skipif(KERNEL is None, reason="installed without a C compiler")


def pykdtree_neighbourhoods(points, n_neighbors, monkeypatch):
    """:func:`nearest_neighbourhoods` by pykdtree's chunked queries (the kernel switched off)."""
    with monkeypatch.context() as patched:
        patched.setattr(neighbourhoods, "KNN_KERNEL", None)
        return nearest_neighbourhoods(points, n_neighbors)


def assert_same(compiled, plain) -> None:
    assert compiled.neighbor_index.dtype == plain.neighbor_index.dtype == np.uint32
    assert np.array_equal(compiled.neighbor_index, plain.neighbor_index)
    assert np.array_equal(compiled.kth_distance.view(np.uint64), plain.kth_distance.view(np.uint64))
    # each a spatial order (the kernel tree's or Morton's): any permutation gives the same
    # answers to the passes that follow it
    rows = np.arange(compiled.neighbor_index.shape[0])
    assert np.array_equal(np.sort(compiled.order), rows)
    assert np.array_equal(np.sort(plain.order), rows)


def test_the_kernel_is_built_where_a_c_compiler_is():
    if not c_compiler_found():
        pytest.skip("no C compiler: pykdtree's queries run")
    assert KERNEL is not None, "setup.py builds app.core.localise._knn_kernel: reinstall"


@needs_kernel
@pytest.mark.parametrize("threads", [1, 2])
def test_a_scanned_room_has_pykdtrees_neighbours(threads, monkeypatch):
    points = lidar_pair(layout="room", angular_step_deg=1.2, random_state=5).reference
    compiled = nearest_neighbourhoods(points, 10, threads=threads)
    assert_same(compiled, pykdtree_neighbourhoods(points, 10, monkeypatch))


@needs_kernel
def test_two_threads_take_the_leaves_block_by_block(monkeypatch):
    """With two threads the kernel's leaves go out in LEAF_BLOCKS blocks from one counter (a
    thread that was slower leaves the rest to the other), every leaf once: pykdtree's
    neighbours."""
    points = lidar_pair(layout="room", angular_step_deg=1.2, random_state=5).reference
    asked: list[tuple[int, int]] = []
    self_neighbours = KERNEL.self_neighbours

    def recorded(tree, k1, index, kth, tie, flag, first, last):
        asked.append((first, last))
        return self_neighbours(tree, k1, index, kth, tie, flag, first, last)

    monkeypatch.setattr(KERNEL, "self_neighbours", recorded)
    compiled = nearest_neighbourhoods(points, 10, threads=2)
    n_leaves = KERNEL.leaf_count(KERNEL.build_tree(points))
    assert len(asked) == neighbourhoods.LEAF_BLOCKS
    bounds = sorted(asked)
    assert bounds[0][0] == 0 and bounds[-1][1] == n_leaves
    assert all(one[1] == two[0] for one, two in itertools.pairwise(bounds))
    monkeypatch.undo()
    assert_same(compiled, pykdtree_neighbourhoods(points, 10, monkeypatch))


@needs_kernel
@pytest.mark.parametrize("n_neighbors", [1, 10, 30])
def test_equally_far_points_are_left_to_pykdtree(n_neighbors, monkeypatch):
    """A lattice (every neighbour at one of a few distances), duplicated points and points
    rounded to float32: orders among equals are pykdtree's walk's, so those points are asked
    of pykdtree; the others are the kernel's, the same numbers."""
    rng = np.random.default_rng(7)
    lattice = np.stack(np.meshgrid(*[np.arange(12.0)] * 3), axis=-1).reshape(-1, 3) * 0.1
    blob = rng.normal(size=(3000, 3))
    duplicated = np.concatenate([blob, blob[:200], blob[:50]])
    rounded = rng.uniform(-2, 2, size=(4000, 3)).astype(np.float32).astype(np.float64)
    for points in (lattice, duplicated, rounded):
        points = np.ascontiguousarray(rng.permutation(points))
        compiled = nearest_neighbourhoods(points, n_neighbors, threads=2)
        assert_same(compiled, pykdtree_neighbourhoods(points, n_neighbors, monkeypatch))


@needs_kernel
def test_the_kernel_trees_order_is_the_spatial_order(monkeypatch):
    """With the kernel, the cloud's spatial order is its tree's leaf order (a copy), not a
    Morton sort of its own; nearby points come together in it."""

    def no_morton_sort(points):
        raise AssertionError("spatial_order called although the kernel's tree has an order")

    points = lidar_pair(layout="room", angular_step_deg=1.2, random_state=5).reference
    points = np.ascontiguousarray(np.random.default_rng(2).permutation(points))
    with monkeypatch.context() as patched:
        patched.setattr(neighbourhoods, "spatial_order", no_morton_sort)
        found = nearest_neighbourhoods(points, 10)
    assert found.order.dtype == np.intp
    assert np.array_equal(np.sort(found.order), np.arange(len(points)))
    step_in_order = np.linalg.norm(np.diff(points[found.order], axis=0), axis=1)
    step_in_file = np.linalg.norm(np.diff(points, axis=0), axis=1)
    assert np.median(step_in_order) < np.median(step_in_file) / 10
    order = np.empty(len(points), dtype=np.intp)
    with pytest.raises(ValueError, match="order_out"):
        KERNEL.tree_order(KERNEL.build_tree(points), order[1:])


@needs_kernel
def test_the_kernel_flags_the_points_it_cannot_order():
    points = np.array([[0.0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 3, 0], [5, 5, 5]])
    index = np.empty((5, 2), dtype=np.uint32)
    kth = np.empty(5)
    tie = np.empty(5, dtype=np.uint8)
    ties = KERNEL.self_neighbours(
        KERNEL.build_tree(points), 2, index, kth, tie, np.zeros(1, np.uint8)
    )
    # the origin has two nearest at 1; the others' second nearest is unique
    assert ties == 1 and tie.tolist() == [1, 0, 0, 0, 0]
    assert index[1:].tolist() == [[1, 0], [2, 0], [3, 0], [4, 3]]
    assert kth[1:].tolist() == [1.0, 1.0, 9.0, 25.0 + 4.0 + 25.0]


def _assert_self_neighbours_are_a_brute_force_sorts(points: np.ndarray, k1: int) -> None:
    """The kernel's k1 nearest of each of ``points`` (shape (n, 3)) among them, their tie flags,
    tie count and k1-th squared distances, against a brute-force sort (the same arithmetic)."""
    offset = points[None, :, :] - points[:, None, :]
    squared = offset[..., 0] * offset[..., 0] + offset[..., 1] * offset[..., 1]
    squared = squared + offset[..., 2] * offset[..., 2]
    nearest = np.sort(squared, axis=1)[:, : k1 + 1]
    expected_tie = (np.diff(nearest, axis=1) == 0).any(axis=1)
    index = np.empty((len(points), k1), np.uint32)
    kth = np.empty(len(points))
    tie = np.empty(len(points), np.uint8)
    ties = KERNEL.self_neighbours(
        KERNEL.build_tree(points), k1, index, kth, tie, np.zeros(1, np.uint8)
    )
    assert ties == expected_tie.sum()
    assert np.array_equal(tie.astype(bool), expected_tie)
    unique = ~expected_tie
    order = np.argsort(squared, axis=1, kind="stable")[:, :k1]
    assert np.array_equal(index[unique], order[unique])
    assert np.array_equal(kth[unique], nearest[unique, k1 - 1])


@needs_kernel
@pytest.mark.parametrize("k1", [2, 5, 11])
def test_the_tie_flags_are_those_of_a_brute_force_sort(k1):
    """The kernel keeps each point's k1 nearest and flags it when two of its k1 + 1 nearest
    are equally far, also when the (k1 + 1)-th (never kept) is as far as the k1-th; on
    coordinates rounded to a coarse grid (many equal distances) the flags, the neighbours
    and the k1-th distances of the others are a brute-force sort's."""
    rng = np.random.default_rng(11)
    for _ in range(20):
        points = np.round(rng.uniform(0, 1, size=(int(rng.integers(40, 400)), 3)), 1)
        _assert_self_neighbours_are_a_brute_force_sorts(points, k1)


@needs_kernel
@pytest.mark.parametrize("k1", [2, 11, 20])
def test_the_own_leaf_bound_skips_no_neighbour(k1):
    """Each point's own leaf is scanned first taking only the candidates within a bound guessed
    from the point before it (exact whenever k1 of them are within it, else a wider bound):
    on clumps of very different spreads (where the guess often fails), far from the origin,
    with duplicated points, the neighbours, k1-th distances and tie flags are still a
    brute-force sort's."""
    rng = np.random.default_rng(5)
    for _ in range(12):
        centres = rng.uniform(-1.0, 1.0, size=(int(rng.integers(2, 8)), 3))
        spreads = 10.0 ** rng.uniform(-4, 0, size=centres.shape[0])
        sizes = rng.integers(1, 120, size=centres.shape[0])
        points = np.vstack(
            [
                c + s * rng.standard_normal((n, 3))
                for c, s, n in zip(centres, spreads, sizes, strict=True)
            ]
        )
        points = np.vstack([points, points[rng.integers(0, len(points), 5)]])  # duplicates
        points += rng.uniform(-1e3, 1e3, size=3)
        if len(points) < k1 + 1:
            continue
        _assert_self_neighbours_are_a_brute_force_sorts(points, k1)


@needs_kernel
def test_the_smallest_cloud_and_arrays_the_kernel_cannot_read(monkeypatch):
    rng = np.random.default_rng(3)
    smallest = rng.normal(size=(11, 3))  # k + 1 = n
    assert_same(
        nearest_neighbourhoods(smallest, 10), pykdtree_neighbourhoods(smallest, 10, monkeypatch)
    )
    points = rng.normal(size=(500, 3))
    with pytest.raises(ValueError, match="float64"):
        KERNEL.build_tree(points.astype(np.float32))
    with pytest.raises(ValueError):
        KERNEL.build_tree(points[::2])
    tree = KERNEL.build_tree(points)
    outputs = (np.empty((500, 11), np.uint32), np.empty(500), np.empty(500, np.uint8))
    with pytest.raises(ValueError, match="index_out"):
        KERNEL.self_neighbours(
            tree, 11, np.empty((500, 10), np.uint32), *outputs[1:], np.zeros(1, np.uint8)
        )
    with pytest.raises(ValueError, match="k \\+ 1"):
        KERNEL.self_neighbours(tree, 501, *outputs, np.zeros(1, np.uint8))
    # thousands of equal points: refused by the kernel, found by pykdtree all the same
    equal = np.zeros((5000, 3))
    with pytest.raises(ValueError, match="equal points"):
        KERNEL.self_neighbours(
            KERNEL.build_tree(equal),
            11,
            np.empty((5000, 11), np.uint32),
            np.empty(5000),
            np.empty(5000, np.uint8),
            np.zeros(1, np.uint8),
        )
    assert_same(nearest_neighbourhoods(equal, 10), pykdtree_neighbourhoods(equal, 10, monkeypatch))


@needs_kernel
def test_a_cancelled_search_stops_inside_the_kernel():
    """The kernel's loop reads the search's flag between leaves, without the GIL: set, it
    stops (-1) and the search gives nothing."""
    points = np.random.default_rng(5).normal(size=(20_000, 3))
    outputs = (np.empty((20_000, 11), np.uint32), np.empty(20_000), np.empty(20_000, np.uint8))
    tree = KERNEL.build_tree(points)
    assert KERNEL.self_neighbours(tree, 11, *outputs, np.ones(1, np.uint8)) == -1
    event = neighbourhoods.CancelEvent()
    event.set()
    assert event.is_set() and event.flag[0] == 1
    assert nearest_neighbourhoods(points, 10, event) is None


@needs_kernel
def test_labels_are_pykdtrees(monkeypatch):
    pair = raycast_scene(n_points=20_000, change="box", random_state=3)
    clouds = (
        PointCloud.from_array(pair.reference, sensor_origin=pair.reference_origin),
        PointCloud.from_array(pair.scan, sensor_origin=pair.scan_origin),
    )
    compiled = compare(*clouds)
    monkeypatch.setattr(neighbourhoods, "KNN_KERNEL", None)
    plain = compare(*clouds)
    assert np.count_nonzero(compiled.scan_label == 1) > 0
    for name in ("reference_label", "scan_label", "reference_distance", "scan_distance"):
        assert np.array_equal(getattr(compiled, name), getattr(plain, name), equal_nan=True), name
    assert compiled.score == plain.score


@needs_kernel
def test_the_nearest_point_in_the_other_cloud_is_pykdtrees():
    """:func:`kernel_nearest` walks the other cloud's kernel tree a leaf of own points at a
    time: pykdtree's nearest point and distance to the bit; the points with two nearest
    equally far (a lattice against itself shifted, duplicates) are pykdtree's answers."""
    pair = lidar_pair(layout="room", angular_step_deg=1.2, random_state=5)
    rng = np.random.default_rng(11)
    lattice = np.stack(np.meshgrid(*[np.arange(12.0)] * 3), axis=-1).reshape(-1, 3)
    blob = rng.normal(size=(3000, 3))
    cases = (
        (pair.reference, pair.scan),
        (lattice + 0.5, lattice),
        (blob, np.concatenate([blob[::2] + 0.01, blob[:300] + 0.01])),
    )
    for own, other in cases:
        own, other = np.ascontiguousarray(own), np.ascontiguousarray(other)
        own_found = nearest_neighbourhoods(own, 10)
        other_found = nearest_neighbourhoods(other, 10)
        found = neighbourhoods.kernel_nearest(
            own, own_found.kernel_tree, other_found.kernel_tree, other_found.tree
        )
        distance, index = other_found.tree.query(own, k=1)
        assert found is not None and found[1].dtype == np.uint32
        assert np.array_equal(found[0].view(np.uint64), distance.view(np.uint64))
        assert np.array_equal(found[1], index)
        shared = neighbourhoods.kernel_nearest(
            own, own_found.kernel_tree, other_found.kernel_tree, other_found.tree, threads=2
        )
        assert shared is not None
        assert np.array_equal(shared[0].view(np.uint64), distance.view(np.uint64))
        assert np.array_equal(shared[1], index)
    tied = np.empty(len(lattice), dtype=np.uint8)
    lattice_tree = KERNEL.build_tree(np.ascontiguousarray(lattice))
    shifted_tree = KERNEL.build_tree(np.ascontiguousarray(lattice + 0.5))
    outputs = (np.empty(len(lattice), np.uint32), np.empty(len(lattice)), tied)
    # a node shifted by half a step is as far from 2-8 lattice nodes but at the far corner
    ties = KERNEL.nearest_other(shifted_tree, lattice_tree, *outputs)
    assert ties == tied.sum() > 0.9 * len(lattice)


@needs_kernel
def test_the_cluster_graph_is_pykdtrees(monkeypatch):
    """``regions.cluster_labels``' links by the kernel's neighbours (distances computed as
    pykdtree computes them, its bound strict) are those of pykdtree's bounded query: a
    scanned room, a lattice whose neighbours lie exactly at the bound (pykdtree leaves them
    out) or tie, duplicated points (asked of the bounded query)."""
    room = lidar_pair(layout="room", angular_step_deg=1.2, random_state=5).reference[:20_000]
    rng = np.random.default_rng(4)
    lattice = np.stack(np.meshgrid(*[np.arange(9.0)] * 3), axis=-1).reshape(-1, 3)
    cases = (
        (room, rng.uniform(0.01, 0.2, len(room))),
        (lattice, np.where(rng.random(len(lattice)) < 0.5, 1.0, 1.5)),
        (lattice, np.ones(len(lattice))),
        (np.concatenate([room[:3000], room[:500]]), np.full(3500, 0.05)),
    )
    used = []
    kernel_links = regions.kernel_self_neighbours

    def recorded(points, n_neighbors, threads=1):
        found = kernel_links(points, n_neighbors, threads)
        used.append(found is not None)
        return found

    monkeypatch.setattr(regions, "kernel_self_neighbours", recorded)
    for points, radius in cases:
        points = np.ascontiguousarray(points)
        neighbour, linked = regions._links(points, radius, 11)
        labels = regions.cluster_labels(points, radius)
        # the kernel's leaves in blocks on two threads: the same links
        shared_neighbour, shared_linked = regions._links(points, radius, 11, threads=2)
        assert np.array_equal(shared_linked, linked)
        assert np.array_equal(shared_neighbour[:, 1:][linked], neighbour[:, 1:][linked])
        assert np.array_equal(regions.cluster_labels(points, radius, threads=2), labels)
        with monkeypatch.context() as plain:
            plain.setattr(neighbourhoods, "KNN_KERNEL", None)
            plain_neighbour, plain_linked = regions._links(points, radius, 11)
            plain_labels = regions.cluster_labels(points, radius)
        assert np.array_equal(linked, plain_linked)
        assert np.array_equal(neighbour[:, 1:][linked], plain_neighbour[:, 1:][plain_linked])
        assert np.array_equal(labels, plain_labels)
    assert used == [True, True, True, True, False, False] * len(cases)


@needs_kernel
def test_two_threads_share_the_kernel_trees_leaves_in_blocks():
    """The nearest points and the cluster graph's neighbours on two threads: the kernel tree's
    leaves in :data:`neighbourhoods.LEAF_BLOCKS` blocks that together cover every leaf once
    (each block writes its own points' rows); one call over all leaves on one thread."""
    points = np.random.default_rng(30).normal(size=(5_000, 3))
    tree = KERNEL.build_tree(points)
    n_leaves = KERNEL.leaf_count(tree)
    for threads, expected in ((1, [(0, -1)]), (2, None)):
        calls: list[tuple[int, int]] = []

        def search(first: int, last: int, calls: list[tuple[int, int]] = calls) -> int:
            calls.append((first, last))
            return last - first

        found = neighbourhoods._by_leaf_blocks(search, tree, threads)
        if expected is not None:
            assert calls == expected
            continue
        assert len(calls) == neighbourhoods.LEAF_BLOCKS
        assert sorted(found) == sorted(last - first for first, last in calls)
        bounds = sorted(calls)
        assert bounds[0][0] == 0 and bounds[-1][1] == n_leaves
        assert all(left[1] == right[0] for left, right in itertools.pairwise(bounds))

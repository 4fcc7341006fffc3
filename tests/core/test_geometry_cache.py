"""The reference's cached geometry (k-NN, surfaces, origin): keyed, verified, rebuilt when missing
or corrupt."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from app.core import registration
from app.core.cache import geometry as geometry_cache
from app.core.cache import reference_origin
from app.core.cache.geometry import GeometryCache, cache_key, code_version
from app.core.cache.reference_alignment import ALIGNMENT_FACT_PREFIX, ReferenceAlignmentCache
from app.core.cache.reference_origin import (
    ORIGIN_FACT,
    ReferenceOriginCache,
    origin_from_record,
    origin_record,
)
from app.core.cloud import PointCloud, choose_local_origin
from app.core.comparison import localise as localise_stage
from app.core.comparison import origins as origins_stage
from app.core.datasets.scenes import raycast_scene
from app.core.localise import neighbourhoods, surface
from app.core.localise.neighbourhoods import nearest_neighbourhoods
from app.core.localise.surface import with_surfaces
from app.core.origins.resolve import ResolvedOrigin
from app.core.pipeline import compare

N_NEIGHBORS = 10
SMALL_AHEAD_MIN_POINTS = 10_000
"""REFERENCE_AHEAD_MIN_POINTS here: the scene is 15k points, not 55k (on two threads the
reference's search still runs ahead; what the cache holds does not depend on the size)."""


@pytest.fixture(scope="module", autouse=True)
def small_run_ahead_threshold():
    with pytest.MonkeyPatch.context() as patched:
        patched.setattr(localise_stage, "REFERENCE_AHEAD_MIN_POINTS", SMALL_AHEAD_MIN_POINTS)
        yield


@pytest.fixture(scope="module")
def pair():
    return raycast_scene(
        n_points=SMALL_AHEAD_MIN_POINTS + 5_000,
        change="box",
        pose_error=(0.03, 0.4),
        random_state=11,
    )


class UncachedResults(dict):
    """The comparison without a cache, per thread count, computed when first asked for."""

    def __init__(self, pair):
        super().__init__()
        self.pair = pair

    def __missing__(self, threads):
        reference = PointCloud.from_array(self.pair.reference)
        scan = PointCloud.from_array(self.pair.scan)
        self[threads] = compare(reference, scan, threads=threads)
        return self[threads]


@pytest.fixture(scope="module")
def uncached(pair):
    """The comparison without a cache, on one or two threads (each run once, when needed)."""
    return UncachedResults(pair)


# Each cache test runs on one thread count in `make test` and on the other in `make test-slow`:
# the cache's behaviour does not depend on it, and the default suite still covers both (the
# build/use/rebuild test on two threads, the hit tests on one).
ONE_THREAD_FAST = [1, pytest.param(2, marks=pytest.mark.slow)]
TWO_THREADS_FAST = [pytest.param(1, marks=pytest.mark.slow), 2]


def assert_same_result(result, expected):
    assert result.score == expected.score and result.changed == expected.changed
    for name in ("reference_label", "scan_label", "reference_region", "scan_region"):
        np.testing.assert_array_equal(getattr(result, name), getattr(expected, name))
    np.testing.assert_array_equal(result.scan_distance, expected.scan_distance)


def test_key_changes_with_reference_code_and_parameters(monkeypatch):
    base = cache_key("a" * 64, None)
    with monkeypatch.context() as patched:
        patched.setattr(geometry_cache, "code_version", lambda: "0123456789abcdef")
        assert cache_key("a" * 64, None) != base
    assert cache_key("a" * 64, {"n_neighbors": 10}) == base  # the default, spelled out
    assert cache_key("b" * 64, None) != base
    assert cache_key("a" * 64, {"n_neighbors": 12}) != base
    assert cache_key("a" * 64, {"threshold_factor": 4.0}) != base
    assert len(code_version()) == 16


def test_the_code_digests_read_every_source_they_name():
    # the keys hash the text of the code that made a cache; a module moved without its name
    # changed here would silently drop out of the key (a stale cache trusted after a change)
    core = Path(geometry_cache.__file__).resolve().parent.parent
    assert [name for name in geometry_cache._CODE_FILES if not (core / name).is_file()] == []
    assert [
        pattern for pattern in reference_origin._ORIGIN_CODE_PATTERNS if not any(core.glob(pattern))
    ] == []


def test_store_then_load_gives_the_search_back(tmp_path, pair):
    points = pair.reference
    found = nearest_neighbourhoods(points, N_NEIGHBORS)
    cache = GeometryCache(tmp_path / "ref.geometry", cache_key("ref", None))
    assert cache.load(points, N_NEIGHBORS) is None  # missing
    size = cache.store(found)
    assert size == cache.path.stat().st_size > found.neighbor_index.nbytes
    loaded = cache.load(points, N_NEIGHBORS)
    np.testing.assert_array_equal(loaded.neighbor_index, found.neighbor_index)
    np.testing.assert_array_equal(loaded.kth_distance, found.kth_distance)
    np.testing.assert_array_equal(loaded.order, found.order)
    np.testing.assert_array_equal(loaded.tree.query(points[:50], k=1)[1], np.arange(50))
    # another key, k or cloud: not used
    assert GeometryCache(cache.path, cache_key("other", None)).load(points, N_NEIGHBORS) is None
    assert cache.load(points, N_NEIGHBORS + 1) is None
    assert cache.load(points[:-1], N_NEIGHBORS) is None


@pytest.mark.parametrize("damage", ["flipped byte", "truncated", "garbage", "other points"])
def test_a_damaged_or_foreign_file_is_not_trusted(tmp_path, pair, damage):
    points = pair.reference
    cache = GeometryCache(tmp_path / "ref.geometry", cache_key("ref", None))
    cache.store(nearest_neighbourhoods(points, N_NEIGHBORS))
    data = bytearray(cache.path.read_bytes())
    if damage == "flipped byte":
        data[len(data) // 2] ^= 0x40
    elif damage == "truncated":
        data = data[:-100]
    elif damage == "garbage":
        data = bytearray(b"SCANDIFF-GEOMETRY\n[1, 2]\n" + bytes(100))
    cache.path.write_bytes(bytes(data))
    if damage == "other points":  # a valid file of another cloud of the same size
        moved = points + np.random.default_rng(0).normal(0.0, 0.01, points.shape)
        cache.store(nearest_neighbourhoods(moved, N_NEIGHBORS))
    assert cache.load(points, N_NEIGHBORS) is None


@pytest.mark.parametrize("threads", TWO_THREADS_FAST)
def test_compare_with_a_cache_gives_the_same_result_and_rebuilds_a_corrupt_one(
    tmp_path, pair, uncached, threads
):
    reference, scan = PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan)
    cache = GeometryCache(tmp_path / "ref.geometry", cache_key("ref", None))
    first = compare(reference, scan, threads=threads, geometry_cache=cache)  # missing: built
    assert_same_result(first, uncached[threads])
    written = cache.path.read_bytes()
    # whether the reference's search ran ahead (two threads) or after its origin (one), the
    # file holds the origin and the alignment's arrays too (the hit tests count their reuse)
    assert cache.load_fact(ORIGIN_FACT, origin_key(cache, reference)) is not None
    header = json.loads(written.split(b"\n", 2)[1])
    names = {entry["name"] for entry in header["array_facts"]}
    assert {"alignment.spacing", "alignment.grid", "alignment.coarse"} <= names
    second = compare(reference, scan, threads=threads, geometry_cache=cache)  # used
    assert_same_result(second, uncached[threads])
    assert cache.path.read_bytes() == written
    damaged = bytearray(written)
    damaged[-8] ^= 0x01
    cache.path.write_bytes(bytes(damaged))
    third = compare(reference, scan, threads=threads, geometry_cache=cache)  # corrupt: rebuilt
    assert_same_result(third, uncached[threads])
    assert cache.path.read_bytes() == written


def test_an_unwritable_cache_costs_nothing_but_time(tmp_path, pair, uncached):
    reference, scan = PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan)
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    cache = GeometryCache(blocker / "ref.geometry", cache_key("ref", None))
    assert_same_result(compare(reference, scan, threads=1, geometry_cache=cache), uncached[1])
    assert not cache.path.exists()


def test_surfaces_are_cached_with_the_neighbourhoods_and_checked(tmp_path, pair):
    points = pair.reference
    found = with_surfaces(points, nearest_neighbourhoods(points, N_NEIGHBORS))
    cache = GeometryCache(tmp_path / "ref.geometry", cache_key("ref", None))
    cache.store(found)
    loaded = cache.load(points, N_NEIGHBORS)
    for name in ("normal", "plane_constant", "spacing", "linear", "variation"):
        np.testing.assert_array_equal(
            getattr(loaded.surfaces, name), getattr(found.surfaces, name), err_msg=name
        )
    assert loaded.surfaces.noise == found.surfaces.noise
    assert loaded.surfaces.linear.dtype == bool
    # a flipped byte among the surfaces (after the neighbour index): not trusted
    data = bytearray(cache.path.read_bytes())
    data[-len(points) * 10] ^= 0x10
    cache.path.write_bytes(bytes(data))
    assert cache.load(points, N_NEIGHBORS) is None
    # planes of other points, with a checksum that matches: the sample refit disagrees
    tilted = dataclasses.replace(
        found.surfaces, normal=np.roll(found.surfaces.normal, 1, axis=1).copy()
    )
    cache.store(dataclasses.replace(found, surfaces=tilted))
    assert cache.load(points, N_NEIGHBORS) is None


def count_calls(monkeypatch, calls, *targets):
    """Count calls of each ``(module, name)`` in ``calls[name]`` (modules that import a
    function by name each get their own patch)."""
    for module, name in targets:
        original = getattr(module, name)

        def counted(*args, _name=name, _original=original, **kwargs):
            calls[_name] = calls.get(_name, 0) + 1
            return _original(*args, **kwargs)

        monkeypatch.setattr(module, name, counted)


@pytest.mark.parametrize("threads", ONE_THREAD_FAST)
def test_a_cache_hit_does_only_the_scan_side_work(tmp_path, pair, uncached, monkeypatch, threads):
    """A comparison with the reference cached reads its neighbourhoods, surfaces and origin
    (one search, one fit and one origin resolution fewer than when the cache is filled) and
    gives the uncached result; a damaged origin fact is resolved again and written back."""
    reference, scan = PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan)
    uncached[threads]  # computed (once per module) before the calls are counted
    cache = GeometryCache(tmp_path / "ref.geometry", cache_key("ref", None))
    calls: dict[str, int] = {}
    count_calls(
        monkeypatch,
        calls,
        (neighbourhoods, "nearest_neighbourhoods"),
        (surface, "nearest_neighbourhoods"),
        (geometry_cache, "nearest_neighbourhoods"),
        (surface, "fit_surfaces"),
        (origins_stage, "resolve_stations"),
    )
    compare(reference, scan, threads=threads, geometry_cache=cache)  # fills it
    filling = dict(calls)
    assert cache.load_fact(ORIGIN_FACT, origin_key(cache, reference)) is not None
    calls.clear()
    hit = compare(reference, scan, threads=threads, geometry_cache=cache)
    assert_same_result(hit, uncached[threads])
    assert hit.sensor_origins == uncached[threads].sensor_origins
    assert hit.localisation == uncached[threads].localisation
    # (the pipeline resolves only the reference's origin itself; the scan's goes through
    # origins.own_frame: the filling run counted one call, the hit none)
    assert {name: calls.get(name, 0) for name in filling} == {
        name: count - 1 for name, count in filling.items()
    }

    # the origin fact damaged (its value no longer matches its checksum): resolved again
    lines = cache.path.read_bytes().split(b"\n", 2)
    header = json.loads(lines[1])
    header["facts"][ORIGIN_FACT]["value"]["source"] = "given"
    cache.path.write_bytes(b"\n".join([lines[0], json.dumps(header).encode(), lines[2]]))
    assert cache.load_fact(ORIGIN_FACT, origin_key(cache, reference)) is None
    calls.clear()
    again = compare(reference, scan, threads=threads, geometry_cache=cache)
    assert_same_result(again, uncached[threads])
    assert again.sensor_origins == uncached[threads].sensor_origins
    assert calls.get("resolve_stations", 0) == filling["resolve_stations"]
    assert calls["fit_surfaces"] == filling["fit_surfaces"] - 1  # the surfaces were still good
    assert cache.load_fact(ORIGIN_FACT, origin_key(cache, reference)) is not None  # rewritten
    assert cache.load(pair.reference, N_NEIGHBORS) is not None  # with its arrays


def origin_key(cache, reference):
    return ReferenceOriginCache.of(
        cache,
        reference,
        choose_local_origin(reference.points),
        given=None,
        estimate=True,
        recover="auto",
    ).key


def test_an_origin_record_gives_the_resolution_back_exactly():
    resolved = ResolvedOrigin(
        np.array([1.0, 2.0 / 3.0, -1e-17]),
        "estimated",
        0.873,
        ["a warning"],
        {"ring_share": 0.91, "seconds": 0.52},  # its run time is not kept (files would differ)
    )
    back = origin_from_record(json.loads(json.dumps(origin_record(resolved))))
    np.testing.assert_array_equal(back.origin, resolved.origin)
    assert (back.source, back.confidence, back.warnings, back.evidence) == (
        "estimated",
        0.873,
        ["a warning"],
        {"ring_share": 0.91},
    )
    assert origin_from_record({"origin": [1, 2, 3]}) is None  # not a record
    stations = ResolvedOrigin(np.zeros((2, 3)), "recovered", None, station_confidence=[0.9, 0.8])
    assert origin_from_record(origin_record(stations)).station_confidence == [0.9, 0.8]


def test_array_facts_are_kept_after_the_arrays_checked_and_replaced(tmp_path, pair):
    points = pair.reference
    cache = GeometryCache(tmp_path / "ref.geometry", cache_key("ref", None))
    grid = np.arange(30.0).reshape(10, 3)
    cache.store(nearest_neighbourhoods(points, N_NEIGHBORS), {"grid": ("k1", grid)})
    np.testing.assert_array_equal(cache.load_array_fact("grid", "k1"), grid)
    assert cache.load_array_fact("grid", "k2") is None  # stored for another key
    assert cache.load_array_fact("other", "k1") is None
    assert cache.load(points, N_NEIGHBORS) is not None  # the arrays before it are still read
    assert not cache.store_facts({"grid": ("k1", grid.copy())})  # there already: no rewrite
    spacing = np.array([0.25])
    assert cache.store_facts({"spacing": ("k3", spacing), "note": ("k4", {"a": 1})})
    np.testing.assert_array_equal(cache.load_array_fact("spacing", "k3"), spacing)
    np.testing.assert_array_equal(cache.load_array_fact("grid", "k1"), grid)
    assert cache.load_fact("note", "k4") == {"a": 1}
    assert cache.load(points, N_NEIGHBORS) is not None
    written = cache.path.read_bytes()
    # a flipped byte in the first array fact: that fact is not trusted, the rest still are
    damaged = bytearray(written)
    damaged[-spacing.nbytes - 5] ^= 0x20
    cache.path.write_bytes(bytes(damaged))
    assert cache.load_array_fact("grid", "k1") is None
    np.testing.assert_array_equal(cache.load_array_fact("spacing", "k3"), spacing)
    assert cache.load(points, N_NEIGHBORS) is not None
    assert cache.store_facts({"grid": ("k1", grid)})  # written again, as it was
    np.testing.assert_array_equal(cache.load_array_fact("grid", "k1"), grid)
    # a file cut short, or with bytes added, is not used at all
    cache.path.write_bytes(written[:-3])
    assert cache.load(points, N_NEIGHBORS) is None
    assert cache.load_array_fact("spacing", "k3") is None
    cache.path.write_bytes(written + b"x")
    assert cache.load(points, N_NEIGHBORS) is None


@pytest.mark.parametrize("threads", ONE_THREAD_FAST)
def test_a_cache_hit_recalls_the_reference_alignment_work(
    tmp_path, pair, uncached, monkeypatch, threads
):
    """With the reference cached, its point spacing, grid centroids and their downsamplings
    are read from the file (only the scan's spacing is estimated), with the uncached result;
    a damaged alignment array is computed again and written back."""
    reference, scan = PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan)
    uncached[threads]  # computed (once per module) before the calls are counted
    cache = GeometryCache(tmp_path / "ref.geometry", cache_key("ref", None))
    calls: dict[str, int] = {}
    count_calls(
        monkeypatch,
        calls,
        (registration, "estimate_point_spacing"),
        (registration, "_downsample"),
    )
    compare(reference, scan, threads=threads, geometry_cache=cache)  # fills it
    filling = dict(calls)
    header = json.loads(cache.path.read_bytes().split(b"\n", 2)[1])
    names = [entry["name"] for entry in header["array_facts"]]
    assert {"alignment.spacing", "alignment.grid", "alignment.coarse"} <= set(names)
    assert all(name.startswith(ALIGNMENT_FACT_PREFIX) for name in names)
    written = cache.path.read_bytes()
    calls.clear()
    hit = compare(reference, scan, threads=threads, geometry_cache=cache)
    assert_same_result(hit, uncached[threads])
    assert hit.registration == uncached[threads].registration
    assert filling["estimate_point_spacing"] == 2 and calls["estimate_point_spacing"] == 1
    assert calls["_downsample"] == filling["_downsample"] - (1 + ("alignment.fit" in names))
    assert cache.path.read_bytes() == written  # nothing rewritten
    # the spacing's value damaged (its checksum no longer matches): estimated again, rewritten
    offset = len(written) - sum(int(np.prod(entry["shape"])) * 8 for entry in header["array_facts"])
    for entry in header["array_facts"]:
        if entry["name"] == "alignment.spacing":
            break
        offset += int(np.prod(entry["shape"])) * 8
    damaged = bytearray(written)
    damaged[offset] ^= 0x01
    cache.path.write_bytes(bytes(damaged))
    calls.clear()
    again = compare(reference, scan, threads=threads, geometry_cache=cache)
    assert_same_result(again, uncached[threads])
    assert calls["estimate_point_spacing"] == 2
    assert cache.path.read_bytes() == written


def test_the_alignment_memory_recalls_only_its_own_plausible_arrays(tmp_path, pair):
    cache = GeometryCache(tmp_path / "ref.geometry", cache_key("ref", None))
    cache.store(nearest_neighbourhoods(pair.reference[:2_000], N_NEIGHBORS))
    assert ReferenceAlignmentCache.of(None, {}) is None
    facts: dict = {}
    memory = ReferenceAlignmentCache.of(cache, facts)
    grid = np.random.default_rng(0).normal(size=(50, 3))
    assert memory.recall("grid", (0.1,)) is None
    memory.remember("grid", (0.1,), grid)
    memory.remember("spacing", (), np.array([0.05]))
    assert set(facts) == {"alignment.grid", "alignment.spacing"}  # written with the arrays
    memory.keep()  # or added to the file afterwards
    fresh = ReferenceAlignmentCache.of(cache, {})
    np.testing.assert_array_equal(fresh.recall("grid", (0.1,)), grid)
    assert fresh.recall("spacing", ())[0] == 0.05
    assert fresh.recall("grid", (np.nextafter(0.1, 1.0),)) is None  # other parameters
    other_reference = GeometryCache(cache.path, cache_key("other", None))
    assert ReferenceAlignmentCache.of(other_reference, {}).recall("spacing", ()) is None
    # an array of the wrong form under the right key and checksum: not used
    name, key = fresh._fact("grid", (0.2,))
    assert cache.store_facts({name: (key, np.zeros((4, 2)))})
    assert fresh.recall("grid", (0.2,)) is None


def test_without_a_cache_the_search_ahead_fits_the_reference_surfaces_too(pair):
    """They are fitted on the search's thread, beside the alignment, as with a cache: the same
    surfaces as fitted later by the localiser."""
    points = np.ascontiguousarray(pair.reference)
    search = geometry_cache.reference_neighbourhoods(points, {}, cache=None, ahead=True)
    assert isinstance(search, neighbourhoods.NeighbourhoodSearch)
    found = search.take()
    assert found.surfaces is not None
    expected = with_surfaces(points, nearest_neighbourhoods(points, N_NEIGHBORS)).surfaces
    for field in dataclasses.fields(expected):
        np.testing.assert_array_equal(
            getattr(found.surfaces, field.name), getattr(expected, field.name)
        )
    assert geometry_cache.reference_neighbourhoods(points, {}, cache=None, ahead=False) is None

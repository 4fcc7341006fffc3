"""Contract of the EMD change detectors, and the properties the improved variants exist for."""

from __future__ import annotations

import json

import numpy as np
import pytest
from sklearn.mixture import GaussianMixture

from app.core.detectors import (
    METHODS,
    VARIANTS,
    Detection,
    base,
    make_detector,
    plane_extraction,
    voxel_grid,
)
from app.core.detectors.gmm import (
    MixtureStart,
    bures_wasserstein_distances,
    fit_mixture,
    refine_mixture,
)
from app.core.detectors.pca import improved_pca_emd, paper_pca_emd, principal_axes
from app.core.detectors.plane_extraction import (
    PlaneSettings,
    VoteWorkspace,
    _candidate_planes,
    _refined,
    _vote,
)
from app.core.emd import earth_movers_distance
from app.core.errors import InputError
from tests.helpers.chunk_passes import recorded_chunk_passes

SMALL = {"max_points": 2000}
"""Working sets of 2000 points (default 4000), to keep the tests quick."""
FAST = {**SMALL, "n_resamples": 8}
"""... and fewer calibration resamples than the default 20."""


def sklearn_fit(
    points: np.ndarray,
    n_components: int,
    *,
    seed: int,
    reg_covar: float,
    max_iter: int,
    start: GaussianMixture | None = None,
) -> GaussianMixture:
    """scikit-learn's EM, cold (k-means start) or warm-started from ``start``: what the GMM
    detector's own EM (``fit_mixture``, ``refine_mixture``) reproduces."""
    warm_start = (
        {}
        if start is None
        else {
            "weights_init": start.weights_,
            "means_init": start.means_,
            "precisions_init": start.precisions_,
        }
    )
    mixture = GaussianMixture(
        n_components,
        covariance_type="full",
        reg_covar=reg_covar,
        max_iter=max_iter,
        random_state=seed,
        **warm_start,
    )
    return mixture.fit(points)


def corridor(n_points: int, rng: np.random.Generator, noise: float = 0.005) -> np.ndarray:
    """Points on the walls x = +-1 and the ceiling z = 2 of a 4 m corridor, shape (n, 3)."""
    surface = rng.integers(0, 3, n_points)
    along = rng.uniform(-2.0, 2.0, n_points)
    across = rng.uniform(0.0, 2.0, n_points)
    points = np.column_stack([np.where(surface == 0, -1.0, 1.0), along, across])
    ceiling = surface == 2
    points[ceiling] = np.column_stack(
        [across[ceiling] - 1.0, along[ceiling], np.full(ceiling.sum(), 2.0)]
    )
    return points + rng.normal(0.0, noise, points.shape)


def box_faces(n_points: int, rng: np.random.Generator, noise: float = 0.005) -> np.ndarray:
    """Points on the free faces of a 0.8 x 1 x 1.2 m box against the wall x = -1."""
    low, high = np.array([-1.0, 0.5, 0.0]), np.array([-0.2, 1.5, 1.2])
    points = rng.uniform(low, high, (n_points, 3))
    face = rng.integers(0, 4, n_points)
    points[face == 0, 0] = high[0]
    points[face == 1, 1] = low[1]
    points[face == 2, 1] = high[1]
    points[face == 3, 2] = high[2]
    return points + rng.normal(0.0, noise, points.shape)


@pytest.fixture(scope="module")
def scene() -> dict[str, np.ndarray]:
    """A reference, an independent rescan of it, and a rescan with a box added (1/7 of it).

    6000 points each: more than ``max_points``, so the detectors take the production path
    (common voxel grid, paired calibration).
    """
    rng = np.random.default_rng(11)
    return {
        "reference": corridor(6000, rng),
        "rescan": corridor(6000, rng),
        "with_box": np.vstack([corridor(6000, rng), box_faces(1000, rng)]),
    }


ALL = [(method, variant) for method in METHODS for variant in VARIANTS]


@pytest.mark.parametrize(("method", "variant"), ALL)
def test_identical_clouds_score_about_zero_and_are_not_changed(method, variant, scene):
    detector = make_detector(method, variant, **FAST)
    shuffled = scene["reference"][np.random.default_rng(0).permutation(6000)]
    detection = detector.detect(scene["reference"], shuffled)
    assert isinstance(detection, Detection)
    assert detection.score == pytest.approx(0.0, abs=1e-6)
    assert detection.threshold > detection.score
    assert detection.changed is False
    json.dumps(detection.calibration)  # JSON-serialisable
    assert detection.calibration["n_resamples"] >= 2
    assert detection.calibration["false_alarm_rate"] == 0.01


def test_small_clouds_are_used_whole_and_calibrated_by_plain_permutation():
    rng = np.random.default_rng(5)
    detection = make_detector("gmm", **FAST).detect(corridor(300, rng), corridor(300, rng))
    assert detection.calibration["voxel_size"] == 0.0
    assert detection.calibration["n_reference_working"] == 300
    assert detection.calibration["calibration"] == "permutation"


@pytest.mark.parametrize("method", METHODS)
def test_improved_detects_an_added_box_and_not_a_plain_rescan(method, scene):
    detector = make_detector(method, **SMALL)
    unchanged = detector.detect(scene["reference"], scene["rescan"])
    changed = detector.detect(scene["reference"], scene["with_box"])
    assert changed.score > unchanged.score
    assert changed.changed is True
    assert unchanged.changed is False
    assert changed.score > changed.threshold
    assert changed.calibration["calibration"] == "paired"
    assert changed.calibration["p_value"] == pytest.approx(1.0 / 21.0)


@pytest.mark.parametrize(("method", "variant"), ALL)
def test_get_params_round_trips_through_make_detector(method, variant):
    detector = make_detector(method, variant, random_state=5, false_alarm_rate=0.05)
    params = detector.get_params()
    assert params["variant"] == variant
    assert params["random_state"] == 5
    assert params["false_alarm_rate"] == 0.05
    assert json.loads(json.dumps(params)) == params
    rebuilt = make_detector(method, **params)
    assert type(rebuilt) is type(detector)
    assert rebuilt.get_params() == params


@pytest.mark.parametrize(("method", "variant"), ALL)
def test_same_random_state_gives_the_same_detection(method, variant, scene):
    first = make_detector(method, variant, random_state=3, **FAST)
    second = make_detector(method, variant, random_state=3, **FAST)
    one = first.detect(scene["reference"], scene["rescan"])
    two = second.detect(scene["reference"], scene["rescan"])
    assert one == two
    assert first.distance(scene["reference"], scene["rescan"]) == one.score


def test_large_clouds_are_thinned_to_max_points_on_a_common_voxel_grid():
    rng = np.random.default_rng(2)
    reference, scan = corridor(20_000, rng), corridor(5_000, rng)
    detection = make_detector("pca", max_points=1000, n_resamples=8).detect(reference, scan)
    assert detection.calibration["voxel_size"] > 0
    assert detection.calibration["n_reference_working"] <= 1000
    assert detection.calibration["n_scan_working"] <= 1000
    paper = make_detector("pca", "paper", max_points=1000, n_resamples=8).detect(reference, scan)
    assert paper.calibration["voxel_size"] == 0.0


@pytest.mark.parametrize(
    ("method", "variant", "params", "message"),
    [
        ("pcaa", "improved", {}, "valid: \\['gmm', 'pca', 'planes'\\]"),
        ("pca", "better", {}, "valid: \\['improved', 'paper'\\]"),
        ("gmm", "improved", {"n_component": 3}, "n_components"),
        ("gmm", "improved", {"n_components": 0}, ">= 1"),
        ("gmm", "improved", {"n_components": 2.5}, "integer"),
        ("gmm", "paper", {"covariance_floor": 0.1}, "unknown parameter"),
        ("planes", "improved", {"inlier_distance": 0.1}, "unknown parameter"),
        ("pca", "improved", {"false_alarm_rate": 0.0}, "false_alarm_rate"),
        ("pca", "improved", {"calibration": "bootstrap"}, "permutation"),
        ("pca", "improved", {"voxel_size": -1.0}, "voxel_size"),
        ("pca", "improved", {"voxel_size": "big"}, "voxel_size"),
        ("pca", "improved", {"n_resamples": True}, "n_resamples"),
    ],
)
def test_bad_parameters_raise_input_error_naming_the_valid_ones(method, variant, params, message):
    with pytest.raises(InputError, match=message):
        make_detector(method, variant, **params)


@pytest.mark.parametrize(
    ("reference", "message"),
    [
        (np.zeros((5, 3)), "at least 10"),
        (np.zeros((20, 2)), "shape"),
        (np.full((20, 3), np.nan), "NaN"),
    ],
)
def test_bad_clouds_raise_input_error(reference, message):
    with pytest.raises(InputError, match=message):
        make_detector("pca").distance(reference, np.zeros((20, 3)))


def test_improved_pca_is_invariant_to_eigenvector_signs_and_the_papers_is_not():
    rng = np.random.default_rng(0)
    values_a, vectors_a = principal_axes(corridor(500, rng))
    values_b, vectors_b = principal_axes(corridor(500, rng))
    flipped_b = vectors_b * np.array([[-1.0], [1.0], [-1.0]])
    improved = improved_pca_emd(values_a, vectors_a, values_b, vectors_b)
    assert improved_pca_emd(values_a, vectors_a, values_b, flipped_b) == pytest.approx(improved)
    paper = paper_pca_emd(values_a, vectors_a, values_b, vectors_b)
    paper_flipped = paper_pca_emd(values_a, vectors_a, values_b, flipped_b)
    assert abs(paper_flipped - paper) > 0.5


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
def test_gmm_warm_start_reduces_the_spread_between_noise_realisations():
    rng = np.random.default_rng(1)
    clean = corridor(300, rng, noise=0.0)
    reg_covar = 2e-3
    cold, warm = [], []
    for _ in range(5):
        reference = clean + rng.normal(0.0, 0.01, clean.shape)
        scan = clean + rng.normal(0.0, 0.01, clean.shape)
        reference_model = sklearn_fit(reference, 8, seed=0, reg_covar=reg_covar, max_iter=100)
        for store, start in ((cold, None), (warm, reference_model)):
            iterations = 100 if start is None else 1
            scan_model = sklearn_fit(
                scan, 8, seed=0, reg_covar=reg_covar, max_iter=iterations, start=start
            )
            ground = bures_wasserstein_distances(
                reference_model.means_,
                reference_model.covariances_,
                scan_model.means_,
                scan_model.covariances_,
            )
            store.append(
                earth_movers_distance(
                    reference_model.weights_, scan_model.weights_, ground
                ).distance
            )
    assert np.std(warm) < 0.5 * np.std(cold)
    assert np.mean(warm) < 0.5 * np.mean(cold)


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
@pytest.mark.parametrize("iterations", [1, 4, 100])
def test_gmm_refinement_is_scikit_learns_warm_started_fit_to_the_bit(iterations):
    rng = np.random.default_rng(3)
    reference = corridor(1500, rng, noise=0.01)
    scan = np.vstack([corridor(1500, rng, noise=0.01), box_faces(200, rng)])
    reference_model = sklearn_fit(reference, 8, seed=0, reg_covar=2e-3, max_iter=100)
    expected = sklearn_fit(
        scan, 8, seed=0, reg_covar=2e-3, max_iter=iterations, start=reference_model
    )
    weights, means, covariances = refine_mixture(
        scan, MixtureStart.from_mixture(reference_model), reg_covar=2e-3, max_iter=iterations
    )
    np.testing.assert_array_equal(weights, expected.weights_)
    np.testing.assert_array_equal(means, expected.means_)
    np.testing.assert_array_equal(covariances, expected.covariances_)


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
@pytest.mark.parametrize(("seed", "iterations"), [(0, 100), (1, 3), (2, 1), (3, 100)])
def test_gmm_fit_is_scikit_learns_fit_to_the_bit(seed, iterations):
    rng = np.random.default_rng(seed)
    points = np.vstack([corridor(1500, rng, noise=0.01), box_faces(200, rng)])
    expected = sklearn_fit(points, 8, seed=seed, reg_covar=1e-6, max_iter=iterations)
    fitted = fit_mixture(points, 8, seed=seed, reg_covar=1e-6, max_iter=iterations)
    np.testing.assert_array_equal(fitted.weights, expected.weights_)
    np.testing.assert_array_equal(fitted.means, expected.means_)
    np.testing.assert_array_equal(fitted.covariances, expected.covariances_)
    np.testing.assert_array_equal(fitted.precisions_cholesky, expected.precisions_cholesky_)
    np.testing.assert_array_equal(fitted.precisions, expected.precisions_)
    assert (fitted.n_iter, fitted.converged) == (expected.n_iter_, expected.converged_)


def test_bures_distance_matches_closed_forms():
    means = np.array([[0.0, 0.0, 0.0]])
    identity = np.eye(3)[None]
    # Same covariance: the distance is the distance between the means.
    shifted = bures_wasserstein_distances(means, identity, np.array([[3.0, 4.0, 0.0]]), identity)
    assert shifted[0, 0] == pytest.approx(5.0)
    # Commuting covariances: ||sqrt(A) - sqrt(B)||_F.
    scaled = bures_wasserstein_distances(means, identity, means, 4.0 * identity)
    assert scaled[0, 0] == pytest.approx(np.sqrt(3.0))


def test_plane_refinements_shared_between_candidates_change_nothing(monkeypatch):
    rng = np.random.default_rng(6)
    points = np.vstack([corridor(3000, rng, noise=0.01), box_faces(500, rng)])
    settings = PlaneSettings(0.2, 0.03, 0.03, 300, 3, 15)
    # as in a round of the extraction: the 10 best-supported of 300 random triples
    candidates, triples = _candidate_planes(points, 300, rng)
    weights = _vote(candidates, points[triples], settings)
    candidates = candidates[np.argsort(-weights, kind="stable")[:10]]
    refits = {"alone": 0, "shared": 0}
    counting = "alone"

    def counted_refit(inliers: np.ndarray) -> np.ndarray:
        refits[counting] += 1
        return plane_fit(inliers)

    plane_fit = plane_extraction._refit
    monkeypatch.setattr(plane_extraction, "_refit", counted_refit)
    known: dict = {}
    for candidate in candidates:
        counting = "alone"
        alone_plane, alone_inliers = _refined(points, candidate, settings)
        counting = "shared"
        plane, inliers = _refined(points, candidate, settings, known)
        np.testing.assert_array_equal(plane, alone_plane)
        np.testing.assert_array_equal(inliers, alone_inliers)
    assert refits["shared"] < refits["alone"]  # the shortcut was taken


def test_plane_vote_reusing_its_buffers_or_with_a_floor_gives_the_same_weights():
    rng = np.random.default_rng(7)
    points = corridor(3000, rng, noise=0.01)
    settings = PlaneSettings(0.2, 0.03, 0.03, 300, 3, 15)
    workspace = VoteWorkspace()
    for count in (300, 120, 300, 7):
        candidates, triples = _candidate_planes(points, count, rng)
        reused = _vote(candidates, points[triples], settings, workspace)
        fresh = _vote(candidates, points[triples], settings)
        np.testing.assert_array_equal(reused, fresh)
        # with a floor, weights that can reach it are exact, the others stay below it
        floor = int(np.percentile(fresh, 70)) + 1
        floored = _vote(candidates, points[triples], settings, workspace, floor=floor)
        reachable = fresh >= floor
        assert 0 < reachable.sum() < count or count < 100
        np.testing.assert_array_equal(floored[reachable], fresh[reachable])
        assert np.all(floored[~reachable] < floor)
        # against the definition, pair by pair
        gaps = np.linalg.norm(candidates[:, None, :3] - candidates[None, :, :3], axis=2)
        heights = np.abs(
            np.einsum("ik,jck->ijc", candidates[:, :3], points[triples]) - candidates[:, None, 3:]
        ).max(axis=2)
        expected = ((gaps < 0.2) & (heights < 0.03)).sum(axis=1)
        assert np.abs(reused - expected).sum() <= 0.001 * count * count  # ties at a threshold


def test_voxel_ids_by_blocks_equal_the_whole_array_formula(monkeypatch):
    """Voxel ids computed a block of rows at a time (the grid taken from the coordinates'
    extremes first) equal the ids and grid size of the whole-array formula, for a grid anchored
    below, inside and above the points and blocks that do not divide the row count."""
    rng = np.random.default_rng(18)
    points = rng.uniform(-7.0, 4.0, size=(10_001, 3)) * [1.0, 3.0, 0.3]
    monkeypatch.setattr(voxel_grid, "VOXEL_BLOCK_ROWS", 1_000)
    for origin in (points.min(axis=0) - 0.3, np.zeros(3), points.max(axis=0) + 0.7):
        for size in (0.01, 0.37, 5.0):
            cells = np.floor((points - origin) / size).astype(np.int64)
            cells -= cells.min(axis=0)
            extent = cells.max(axis=0) + 1
            expected = (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]
            voxels, n_cells = voxel_grid.voxel_ids(points, size, origin)
            np.testing.assert_array_equal(voxels, expected)
            assert n_cells == int(np.prod(extent))


def test_voxel_thinning_on_a_dense_grid_picks_what_the_sort_picks(monkeypatch):
    """The dense per-cell path (grids up to a few cells a point) and the sort path choose the
    same representatives and count the same voxels, ties between duplicates included."""
    rng = np.random.default_rng(8)
    points = rng.uniform(-3.0, 5.0, size=(40_000, 3)) * [1.0, 1.0, 0.2]
    points[7::7] = points[3:-4:7]  # duplicated points: equal keys in a voxel
    keys = base.point_keys(points, seed=3)
    origin = points.min(axis=0) - 0.01
    extremes = (points.min(axis=0), points.max(axis=0))
    dense = {
        size: (
            voxel_grid.voxel_representatives(points, size, origin, keys),
            voxel_grid._occupied_voxels(points, size, extremes),
        )
        for size in (0.05, 0.3, 2.0)
    }
    assert voxel_grid._dense_cell_limit(len(points)) > (8.0 / 0.3) ** 2 * (1.6 / 0.3)  # dense used
    monkeypatch.setattr(voxel_grid, "_dense_cell_limit", lambda n_points: 0)
    for size, (representatives, occupied) in dense.items():
        np.testing.assert_array_equal(
            voxel_grid.voxel_representatives(points, size, origin, keys), representatives
        )
        assert voxel_grid._occupied_voxels(points, size, extremes) == occupied


def test_the_voxel_size_search_counts_its_voxels_by_blocks_on_two_threads(monkeypatch):
    """The occupied voxels of each step of :func:`voxel_grid.auto_voxel_size` are marked by
    blocks of rows on the detector's threads (the keys beside it may finish first): every
    count is the number of distinct voxel ids, and the size is the one-thread size."""
    rng = np.random.default_rng(29)
    points = rng.uniform(-3.0, 5.0, size=(30_001, 3)) * [1.0, 2.0, 0.2]
    monkeypatch.setattr(voxel_grid, "VOXEL_BLOCK_ROWS", 1_000)
    monkeypatch.setattr(voxel_grid, "OCCUPANCY_TASK_ROWS", 4_000)
    extremes = (points.min(axis=0), points.max(axis=0))
    for size in (0.05, 0.3, 2.0):
        voxels, _ = voxel_grid.voxel_ids(points, size, extremes[0])
        assert voxel_grid._occupied_voxels(points, size, extremes, 2) == np.unique(voxels).size
    one = voxel_grid.auto_voxel_size(points, 2_000, 1)
    marked = recorded_chunk_passes(monkeypatch, voxel_grid)
    assert voxel_grid.auto_voxel_size(points, 2_000, 2) == one
    assert marked and all(count == 8 and threads == 2 for count, threads in marked)

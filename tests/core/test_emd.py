"""The EMD of the paper's eq. (1), checked against cases solved by hand."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.emd import EmdResult, earth_movers_distance


def line_distances(first: list[float], second: list[float]) -> np.ndarray:
    """|x_i - y_j| for points on a line, shape (len(first), len(second))."""
    return np.abs(np.subtract.outer(np.asarray(first), np.asarray(second)))


def test_equal_weights_match_the_obvious_assignment():
    # Two unit masses at 0 and 10 against two at 1 and 12: move 0->1 (1) and 10->12 (2).
    result = earth_movers_distance([1.0, 1.0], [1.0, 1.0], line_distances([0, 10], [1, 12]))
    assert isinstance(result, EmdResult)
    assert result.distance == pytest.approx(3.0 / 2.0)
    np.testing.assert_allclose(result.flow, [[1.0, 0.0], [0.0, 1.0]])


def test_one_dimensional_case_splits_mass_as_solved_by_hand():
    # a: 0.5 at x=0, 0.5 at x=1; b: 0.25 at x=0, 0.75 at x=2 (equal totals).
    # Optimal plan: 0.25 stays at 0 (cost 0); 0.25 goes 0->2 (cost 0.5); 0.5 goes 1->2 (0.5).
    # In 1-D the EMD is the integral of |F_a - F_b|: 0.25 on [0,1) + 0.25 on [1,2) = 1.0.
    result = earth_movers_distance([0.5, 0.5], [0.25, 0.75], line_distances([0, 1], [0, 2]))
    assert result.distance == pytest.approx(1.0)
    assert result.flow.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(result.flow.sum(axis=1), [0.5, 0.5])
    np.testing.assert_allclose(result.flow.sum(axis=0), [0.25, 0.75])


def test_unequal_totals_transport_only_the_smaller_mass_and_normalise_by_it():
    # W = 3 (unit masses at 0, 1, 2), U = 2 (unit masses at 0.1 and 1.2).
    # Only min(W, U) = 2 moves: 0->0.1 (0.1) and 1->1.2 (0.2); the mass at 2 stays.
    # EMD = 0.3 / 2.
    result = earth_movers_distance(
        [1.0, 1.0, 1.0], [1.0, 1.0], line_distances([0, 1, 2], [0.1, 1.2])
    )
    assert result.distance == pytest.approx(0.15)
    assert result.flow.sum() == pytest.approx(2.0)
    np.testing.assert_allclose(result.flow[2], [0.0, 0.0], atol=1e-12)


def test_partial_transport_ignores_far_surplus_mass():
    # The heavier set has an extra mass very far away: partial transport leaves it alone,
    # so the EMD is the same as without it (a full transport would be dominated by it).
    near = earth_movers_distance([1.0], [1.0], line_distances([0], [1]))
    with_surplus = earth_movers_distance([1.0, 1.0], [1.0], line_distances([0, 1000], [1]))
    assert with_surplus.distance == pytest.approx(near.distance) == pytest.approx(1.0)


def test_weights_need_not_be_normalised():
    scaled = earth_movers_distance([2.0, 2.0], [2.0, 2.0], line_distances([0, 10], [1, 12]))
    assert scaled.distance == pytest.approx(1.5)
    assert scaled.flow.sum() == pytest.approx(4.0)


def test_symmetric_in_its_arguments():
    rng = np.random.default_rng(3)
    points_a, points_b = rng.normal(size=(5, 2)), rng.normal(size=(7, 2))
    weights_a, weights_b = rng.uniform(0.1, 1.0, 5), rng.uniform(0.1, 1.0, 7)
    ground = np.linalg.norm(points_a[:, None] - points_b[None], axis=2)
    forward = earth_movers_distance(weights_a, weights_b, ground)
    backward = earth_movers_distance(weights_b, weights_a, ground.T)
    assert forward.distance == pytest.approx(backward.distance)


def test_zero_for_identical_sets():
    rng = np.random.default_rng(4)
    points = rng.normal(size=(6, 3))
    weights = rng.uniform(0.1, 1.0, 6)
    ground = np.linalg.norm(points[:, None] - points[None], axis=2)
    assert earth_movers_distance(weights, weights, ground).distance == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize(
    ("weights_a", "weights_b", "ground", "message"),
    [
        ([1.0, -1.0], [1.0], [[1.0], [1.0]], "negative"),
        ([1.0, np.nan], [1.0], [[1.0], [1.0]], "NaN"),
        ([1.0, 1.0], [1.0], [[1.0, 2.0]], "shape"),
        ([1.0], [1.0], [[np.nan]], "NaN"),
        ([1.0], [1.0], [[-1.0]], "negative"),
        ([], [1.0], np.zeros((0, 1)), "non-empty"),
        ([0.0, 0.0], [1.0], [[1.0], [1.0]], "zero total"),
        ([[1.0]], [1.0], [[1.0]], "1-D"),
    ],
)
def test_invalid_inputs_raise_value_error(weights_a, weights_b, ground, message):
    with pytest.raises(ValueError, match=message):
        earth_movers_distance(weights_a, weights_b, ground)


@pytest.mark.parametrize("partial", [False, True])
def test_the_optimal_cost_equals_pots_network_simplex(partial: bool) -> None:
    ot = pytest.importorskip("ot")
    rng = np.random.default_rng(7 + partial)
    worst = 0.0
    for trial in range(300):
        m, n = (8, 8) if trial % 3 == 0 else rng.integers(1, 25, 2)
        weights_a, weights_b = rng.uniform(0.0, 1.0, m), rng.uniform(0.0, 1.0, n)
        weights_a[0] += 0.1  # a zero total is refused
        weights_b[0] += 0.1
        ground = rng.uniform(0.0, 5.0, (m, n))
        if trial % 2:
            ground = np.round(ground)  # ties: degenerate transport problems
        if partial:
            weights_b *= rng.uniform(0.3, 3.0) * weights_a.sum() / weights_b.sum()
            mass = min(weights_a.sum(), weights_b.sum())
            flow = ot.partial.partial_wasserstein(weights_a, weights_b, ground, m=mass)
        else:
            weights_b *= weights_a.sum() / weights_b.sum()
            mass = weights_a.sum()
            flow = ot.emd(weights_a, weights_b, ground)
        expected = float(np.sum(flow * ground) / mass)
        result = earth_movers_distance(weights_a, weights_b, ground)
        worst = max(worst, abs(result.distance - expected) / max(expected, 1e-300))
        assert result.flow.sum() == pytest.approx(mass, rel=1e-12)
        assert (result.flow.sum(axis=1) <= weights_a * (1 + 1e-12) + 1e-15).all()
        assert (result.flow.sum(axis=0) <= weights_b * (1 + 1e-12) + 1e-15).all()
    assert worst <= 1e-9

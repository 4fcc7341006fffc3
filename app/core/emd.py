"""The Earth Mover's Distance of Amorim, Rocha & Dias, eq. (1).

Given weighted points ``A = {(x_i, w_i)}`` (m of them, total weight ``W``) and
``B = {(y_j, u_j)}`` (n of them, total weight ``U``) and the ground distances ``d_ij``, the EMD
is the cheapest *partial* transport of mass ``min(W, U)`` from one set to the other, divided by
``min(W, U)``::

    EMD(A, B) = min_F sum_ij f_ij d_ij / min(W, U)
    subject to f_ij >= 0, sum_j f_ij <= w_i, sum_i f_ij <= u_j, sum_ij f_ij = min(W, U).

When ``W == U`` this is the ordinary optimal-transport (Wasserstein-1) cost per unit mass and a
true distance if ``d`` is one; when the totals differ, the surplus mass of the heavier set is
left where it is and costs nothing, so the EMD is then *not* a distance (the paper's remark).
Both cases are one small linear programme, solved by :func:`transport_plan` with HiGHS's
simplex (``scipy.optimize.linprog``): the optimal cost equals POT's network simplex (``ot.emd``,
``ot.partial.partial_wasserstein``) to ~1e-12 relative (``tests/core/test_emd.py`` compares
them on random problems), without POT's import, which loads scikit-learn (~0.8 CPU s).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

EQUAL_MASS_RTOL = 1e-9
"""Relative tolerance under which two total weights are treated as equal (full transport)."""


@dataclass(frozen=True)
class EmdResult:
    """An optimal flow and its cost.

    Attributes
    ----------
    distance : float
        The EMD of eq. (1): transport cost divided by the transported mass ``min(W, U)``.
    flow : ndarray, shape (m, n)
        Optimal flow ``f_ij`` from point ``i`` of the first set to point ``j`` of the second;
        it sums to ``min(W, U)``.
    """

    distance: float
    flow: NDArray[np.float64]


def _as_weights(weights: NDArray, name: str) -> NDArray[np.float64]:
    array = np.asarray(weights, dtype=np.float64)
    if array.ndim != 1 or array.shape[0] == 0:
        raise ValueError(f"{name} must be a non-empty 1-D array, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or inf")
    if (array < 0).any():
        raise ValueError(f"{name} contains negative weights (min {array.min():g})")
    if array.sum() <= 0:
        raise ValueError(f"{name} has zero total weight: there is no mass to transport")
    return array


DENSE_CELLS = 1024
"""Plans of at most this many cells get a dense constraint matrix (faster to hand to HiGHS: the
detectors' 8 x 8 and 3 x 3 problems); larger ones a sparse one ((m + n) x m n would not fit)."""


@functools.lru_cache(maxsize=16)
def _margin_matrix(m: int, n: int) -> Any:
    """The row-sum and column-sum constraints of an (m, n) plan, shape (m + n, m n), read-only."""
    cells = np.arange(m * n)
    if m * n <= DENSE_CELLS:
        margins = np.zeros((m + n, m * n))
        margins[cells // n, cells] = 1.0
        margins[m + cells % n, cells] = 1.0
        margins.flags.writeable = False
        return margins
    from scipy.sparse import coo_array, vstack

    rows = coo_array((np.ones(m * n), (cells // n, cells)), shape=(m, m * n))
    columns = coo_array((np.ones(m * n), (cells % n, cells)), shape=(n, m * n))
    return vstack([rows, columns]).tocsr()


def transport_plan(
    supply: NDArray[np.float64],
    demand: NDArray[np.float64],
    cost: NDArray[np.float64],
    *,
    mass: float | None = None,
) -> NDArray[np.float64]:
    """An optimal transport plan, by the simplex method (HiGHS through ``scipy.optimize``).

    Parameters
    ----------
    supply : ndarray, shape (m,)
        Non-negative masses of the sources.
    demand : ndarray, shape (n,)
        Non-negative masses of the sinks; with ``mass`` None, the same total as ``supply``.
    cost : ndarray, shape (m, n)
        Cost of moving a unit of mass from source ``i`` to sink ``j``.
    mass : float or None
        None: every mass moves (row sums ``supply``, column sums ``demand``). Otherwise a
        partial plan that moves exactly ``mass``, with row and column sums at most ``supply``
        and ``demand``.

    Returns
    -------
    ndarray, shape (m, n)
        The plan ``f_ij >= 0`` of least total cost ``sum f_ij c_ij``.

    Raises
    ------
    ValueError
        The solver found no optimum (infeasible masses).
    """
    from scipy.optimize import linprog  # ~0.06 s, on first use

    margins = _margin_matrix(*cost.shape)
    m, n = cost.shape
    bounds = np.concatenate([supply, demand])
    if mass is None:
        result = linprog(cost.ravel(), A_eq=margins, b_eq=bounds, method="highs-ds")
    else:
        result = linprog(
            cost.ravel(),
            A_ub=margins,
            b_ub=bounds,
            A_eq=np.ones((1, m * n)),
            b_eq=[mass],
            method="highs-ds",
        )
    if result.status != 0:
        raise ValueError(f"no optimal transport plan: {result.message}")
    return np.clip(result.x.reshape(m, n), 0.0, None)


def earth_movers_distance(
    weights_a: NDArray, weights_b: NDArray, ground_distance: NDArray
) -> EmdResult:
    """EMD between two weighted point sets, exactly as the paper's eq. (1).

    Parameters
    ----------
    weights_a : array_like, shape (m,)
        Non-negative weights ``w_i`` of the first set (total ``W > 0``).
    weights_b : array_like, shape (n,)
        Non-negative weights ``u_j`` of the second set (total ``U > 0``).
    ground_distance : array_like, shape (m, n)
        Non-negative finite ground distance ``d_ij`` between point ``i`` of the first set and
        point ``j`` of the second.

    Returns
    -------
    EmdResult
        ``distance`` (cost / ``min(W, U)``) and the optimal ``flow``, shape (m, n).

    Raises
    ------
    ValueError
        Wrong shapes, empty sets, NaN/inf, negative weights or distances, zero total weight.
    """
    weights_a = _as_weights(weights_a, "weights_a")
    weights_b = _as_weights(weights_b, "weights_b")
    cost = np.asarray(ground_distance, dtype=np.float64)
    expected_shape = (weights_a.shape[0], weights_b.shape[0])
    if cost.shape != expected_shape:
        raise ValueError(
            f"ground_distance must have shape {expected_shape} (len(weights_a), len(weights_b)),"
            f" got {cost.shape}"
        )
    if not np.isfinite(cost).all():
        raise ValueError("ground_distance contains NaN or inf")
    if (cost < 0).any():
        raise ValueError(f"ground_distance contains negative entries (min {cost.min():g})")
    cost = np.ascontiguousarray(cost)

    total_a = float(weights_a.sum())
    total_b = float(weights_b.sum())
    transported = min(total_a, total_b)
    if abs(total_a - total_b) <= EQUAL_MASS_RTOL * max(total_a, total_b):
        # Equal masses: ordinary optimal transport. Rescale b so the sums agree to the last bit.
        flow = transport_plan(weights_a, weights_b * (total_a / total_b), cost)
    else:
        flow = transport_plan(weights_a, weights_b, cost, mass=transported)
    flow = np.asarray(flow, dtype=np.float64)
    distance = float(np.sum(flow * cost) / transported)
    return EmdResult(distance=max(distance, 0.0), flow=flow)


def euclidean_ground_distances(
    points_a: NDArray[np.float64], points_b: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Euclidean ground distances ``d_ij = |x_i - y_j|`` between two sets of weighted points.

    Parameters
    ----------
    points_a : ndarray, shape (m, d)
    points_b : ndarray, shape (n, d)

    Returns
    -------
    ndarray, shape (m, n)
    """
    return np.linalg.norm(points_a[:, None, :] - points_b[None, :, :], axis=2)

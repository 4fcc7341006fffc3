"""GMM-EMD: compare Gaussian mixtures fitted to two clouds (paper section III-B, eq. (4)).

``paper``
    A ``K``-component full-covariance mixture is fitted to each cloud independently with
    scikit-learn's EM (k-means initialisation, one initialisation, at most 100 iterations,
    tolerance 1e-3 on the lower bound, ``reg_covar`` 1e-6: scikit-learn's defaults, with the
    detector's ``random_state``; :func:`fit_mixture` runs scikit-learn's k-means (its numpy
    twin, :mod:`app.core.detectors.kmeans`, with the same labels) and then the
    same EM arithmetic as ``GaussianMixture.fit``, with the same bits, at a third of the cost
    per iteration). Each component is the point
    ``theta = (mu, vec Sigma)`` in R^12 weighted by its mixing probability, with Euclidean
    ground distance. The paper does not say which ``K`` it used; we use 8 for both variants.

``improved``
    * **warm start / anchoring**: EM on two noisy copies of one scene lands in different but
      equally good splits of the surfaces into components, and the EMD then measures the
      difference between splits, not between scenes. One model is fitted to the reference
      (k-means start, ``max_iter`` iterations); then *both* clouds are described by
      ``refine_iterations`` EM iterations started from it (default 1: one E-step with the
      shared model's responsibilities, one M-step). Both are thus described on the same
      partition, only what the data moves, moves, and identical clouds give identical models
      (``d(S, S) = 0``). Calibration resamples go through exactly the same two refinements,
      so they cost two EM iterations each.
    * **covariance floor**: points on a plane give components with almost zero thickness;
      a few millimetres of noise then reshuffle the responsibilities at every plane
      intersection. ``reg_covar`` is set to ``(covariance_floor * rms_radius)**2`` of the
      reference working set: the model does not resolve structure thinner than that.
    * **ground distance**: the 2-Wasserstein (Bures) distance between the two Gaussians,
      ``sqrt(|mu_a - mu_b|^2 + tr(S_a + S_b - 2 (S_a^1/2 S_b S_a^1/2)^1/2))``, a true metric in
      metres that weighs a change of mean and a change of spread consistently (Euclidean
      distance on ``vec Sigma`` mixes metres and square metres).
    * **weights**: the shared model's mixing probabilities on *both* sides. After the
      refinement, how many points fall in each component depends on the sampling pattern
      (viewpoint, lidar ring spacing) as much as on the scene; what a change does to the
      geometry shows in the components' means and covariances; the null narrows and a box is
      detected more often (figures in docs/detectors.md).
    * fixed ``K`` rather than BIC (BIC's choice flips between epochs of one scene) and the fit
      on at most ``max_points`` points thinned on a common voxel grid (see ``base``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from app.core.detectors.base import ChangeDetector
from app.core.detectors.kmeans import kmeans_labels
from app.core.emd import earth_movers_distance, euclidean_ground_distances
from app.core.errors import InputError
from app.core.parameters import ParamSpec

if TYPE_CHECKING:  # scikit-learn is imported when a detector first runs (see detectors.warm_up)
    from sklearn.mixture import GaussianMixture


def _psd_sqrt(matrices: NDArray[np.float64]) -> NDArray[np.float64]:
    """Symmetric square roots of a stack of symmetric PSD matrices, shape (..., d, d)."""
    eigenvalues, eigenvectors = np.linalg.eigh(matrices)
    roots = np.sqrt(np.clip(eigenvalues, 0.0, None))
    return (eigenvectors * roots[..., None, :]) @ np.swapaxes(eigenvectors, -1, -2)


def bures_wasserstein_distances(
    means_a: NDArray[np.float64],
    covariances_a: NDArray[np.float64],
    means_b: NDArray[np.float64],
    covariances_b: NDArray[np.float64],
) -> NDArray[np.float64]:
    """2-Wasserstein distance between every Gaussian of ``a`` and every Gaussian of ``b``.

    Parameters
    ----------
    means_a : ndarray, shape (k, d)
    covariances_a : ndarray, shape (k, d, d)
    means_b : ndarray, shape (l, d)
    covariances_b : ndarray, shape (l, d, d)

    Returns
    -------
    ndarray, shape (k, l)
        ``sqrt(|mu_a - mu_b|^2 + tr(S_a) + tr(S_b) - 2 tr((S_a^1/2 S_b S_a^1/2)^1/2))``.
    """
    roots_a = _psd_sqrt(covariances_a)  # (k, d, d)
    products = roots_a[:, None] @ covariances_b[None, :] @ roots_a[:, None]  # (k, l, d, d)
    cross_trace = np.sqrt(np.clip(np.linalg.eigvalsh(products), 0.0, None)).sum(axis=-1)
    mean_term = np.sum((means_a[:, None, :] - means_b[None, :, :]) ** 2, axis=-1)
    trace_a = np.trace(covariances_a, axis1=-2, axis2=-1)
    trace_b = np.trace(covariances_b, axis1=-2, axis2=-1)
    squared = mean_term + trace_a[:, None] + trace_b[None, :] - 2.0 * cross_trace
    return np.sqrt(np.clip(squared, 0.0, None))


def parameter_vectors(mixture: Mixture) -> NDArray[np.float64]:
    """The paper's ``theta_k = (mu_k, vec Sigma_k)``, shape (K, 3 + 9)."""
    n_components = mixture.means.shape[0]
    return np.hstack([mixture.means, mixture.covariances.reshape(n_components, -1)])


@dataclass(frozen=True)
class Mixture:
    """A fitted full-covariance Gaussian mixture (what :func:`fit_mixture` returns).

    Attributes
    ----------
    weights : ndarray, shape (K,)
    means : ndarray, shape (K, d)
    covariances : ndarray, shape (K, d, d)
    precisions_cholesky : ndarray, shape (K, d, d)
        Upper-triangular ``U_k`` with ``Sigma_k^-1 = U_k U_k^T``.
    n_iter : int
        EM iterations run.
    converged : bool
        Whether the mean log-likelihood changed by less than ``tol`` before ``max_iter``.
    """

    weights: NDArray[np.float64]
    means: NDArray[np.float64]
    covariances: NDArray[np.float64]
    precisions_cholesky: NDArray[np.float64]
    n_iter: int
    converged: bool

    @property
    def precisions(self) -> NDArray[np.float64]:
        """``U_k U_k^T``, shape (K, d, d), as scikit-learn's ``precisions_``."""
        precisions = np.empty_like(self.precisions_cholesky)
        for k, cholesky in enumerate(self.precisions_cholesky):
            precisions[k] = cholesky @ cholesky.T
        return precisions


@dataclass(frozen=True)
class MixtureStart:
    """A full-covariance Gaussian mixture to start EM refinements from.

    Attributes
    ----------
    weights : ndarray, shape (K,)
    means : ndarray, shape (K, d)
    precisions_cholesky : ndarray, shape (K, d, d)
        Upper-triangular ``U_k`` with ``precision_k = U_k U_k^T``, computed from the
        precisions exactly as scikit-learn does for ``precisions_init``.
    """

    weights: NDArray[np.float64]
    means: NDArray[np.float64]
    precisions_cholesky: NDArray[np.float64]

    @classmethod
    def from_precisions(
        cls,
        weights: NDArray[np.float64],
        means: NDArray[np.float64],
        precisions: NDArray[np.float64],
    ) -> MixtureStart:
        """The start scikit-learn makes of ``weights_init``, ``means_init``,
        ``precisions_init``: shapes (K,), (K, d), (K, d, d)."""
        from scipy import linalg  # on first use: API processes need no scipy

        flipped = [
            np.flip(linalg.cholesky(np.flip(precision), lower=True)) for precision in precisions
        ]
        return cls(
            weights=np.array(weights, dtype=np.float64),
            means=np.array(means, dtype=np.float64),
            precisions_cholesky=np.stack(flipped),
        )

    @classmethod
    def from_mixture(cls, mixture: Mixture | GaussianMixture) -> MixtureStart:
        """The start scikit-learn would make of ``weights_init=mixture.weights_`` etc."""
        if isinstance(mixture, Mixture):
            return cls.from_precisions(mixture.weights, mixture.means, mixture.precisions)
        return cls.from_precisions(mixture.weights_, mixture.means_, mixture.precisions_)


def _log_gaussian_densities(
    points: NDArray[np.float64],
    means: NDArray[np.float64],
    precisions_cholesky: NDArray[np.float64],
) -> NDArray[np.float64]:
    """``log N(x_i | mu_k, Sigma_k)``, shape (n, K), as scikit-learn's ``full`` case."""
    n_points, n_features = points.shape
    log_det = np.sum(
        np.log(precisions_cholesky.reshape(means.shape[0], -1)[:, :: n_features + 1]), axis=1
    )
    squared = np.empty((n_points, means.shape[0]))
    for k in range(means.shape[0]):
        whitened = (points @ precisions_cholesky[k]) - (means[k] @ precisions_cholesky[k])
        squared[:, k] = np.sum(np.square(whitened), axis=1)
    return -0.5 * (n_features * math.log(2 * math.pi) + squared) + log_det


def _log_sum_exp_rows(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """``log(sum(exp(values), axis=1))``, shape (n,), with scikit-learn's rounding."""
    row_max = np.max(values, axis=1, keepdims=True)
    at_max = values == row_max
    others = values.copy()
    others[at_max] = -np.inf
    n_at_max = np.sum(at_max.astype(np.float64), axis=1, keepdims=True, dtype=np.float64)
    shift = np.where(np.isfinite(row_max), row_max, 0)
    total = np.sum(np.exp(others - shift), axis=1, keepdims=True, dtype=np.float64)
    total = np.where(total == 0, total, total / n_at_max)
    return np.squeeze(np.log1p(total) + np.log(n_at_max) + row_max, axis=1)


def _precisions_cholesky(covariances: NDArray[np.float64]) -> NDArray[np.float64]:
    """``U_k`` (upper triangular, ``Sigma_k^-1 = U_k U_k^T``), shape (K, d, d)."""
    from scipy import linalg  # on first use: API processes need no scipy

    identity = np.eye(covariances.shape[1])
    result = np.empty_like(covariances)
    for k, covariance in enumerate(covariances):
        try:
            lower = linalg.cholesky(covariance, lower=True)
        except np.linalg.LinAlgError as exc:
            raise ValueError(
                "EM refinement failed: a component's covariance is not positive definite"
            ) from exc
        result[k] = linalg.solve_triangular(lower, identity, lower=True).T
    return result


def _m_step(
    points: NDArray[np.float64], responsibilities: NDArray[np.float64], reg_covar: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Component sizes (K,), means (K, d) and covariances (K, d, d), as scikit-learn's."""
    n_features = points.shape[1]
    counts = np.sum(responsibilities, axis=0) + 10 * np.finfo(np.float64).eps
    means = (responsibilities.T @ points) / counts[:, np.newaxis]
    covariances = np.empty((means.shape[0], n_features, n_features))
    for k in range(means.shape[0]):
        centred = points - means[k, :]
        covariances[k] = ((responsibilities[:, k] * centred.T) @ centred) / counts[k]
        covariances[k].flat[:: n_features + 1] += reg_covar
    return counts, means, covariances


def _em(
    points: NDArray[np.float64],
    weights: NDArray[np.float64],
    means: NDArray[np.float64],
    precisions_cholesky: NDArray[np.float64],
    *,
    reg_covar: float,
    max_iter: int,
    tol: float,
    final_precisions: bool,
) -> Mixture:
    """EM iterations from the given parameters, scikit-learn's loop (see :func:`fit_mixture`).

    ``final_precisions=False`` skips the Cholesky factors of the last M-step (its
    ``precisions_cholesky`` is then the previous one): refinements only use the means and
    covariances.
    """
    covariances = np.empty((means.shape[0], points.shape[1], points.shape[1]))
    lower_bound = -np.inf
    converged = False
    n_iter = 0
    for n_iter in range(1, max_iter + 1):
        # E-step: log responsibilities under the current model
        weighted = _log_gaussian_densities(points, means, precisions_cholesky) + np.log(weights)
        log_norm = _log_sum_exp_rows(weighted)
        with np.errstate(under="ignore"):
            log_responsibilities = weighted - log_norm[:, np.newaxis]
        previous_bound, lower_bound = lower_bound, np.mean(log_norm)
        # M-step
        counts, means, covariances = _m_step(points, np.exp(log_responsibilities), reg_covar)
        weights = counts / np.sum(counts)
        converged = abs(lower_bound - previous_bound) < tol
        if final_precisions or not (converged or n_iter == max_iter):
            precisions_cholesky = _precisions_cholesky(covariances)
        if converged:
            break
    return Mixture(weights, means, covariances, precisions_cholesky, n_iter, bool(converged))


def fit_mixture(
    points: NDArray[np.float64],
    n_components: int,
    *,
    seed: int,
    reg_covar: float,
    max_iter: int,
    tol: float = 1e-3,
) -> Mixture:
    """EM fit from a k-means start: scikit-learn's ``GaussianMixture(...).fit`` to the bit.

    The same k-means (scikit-learn's, one initialisation, seeded with ``seed``: the same labels
    from :func:`app.core.detectors.kmeans.kmeans_labels`, without scikit-learn), then the same
    operations in the same order as ``GaussianMixture(n_components, covariance_type="full",
    reg_covar=reg_covar, max_iter=max_iter, tol=tol, random_state=seed).fit(points)``, without
    its validation, per-call overhead and final E-step, which cost more than an EM iteration
    on a working set (figures in docs/performance.md). ``tests/core/test_detectors.py``
    checks the equality.

    Parameters
    ----------
    points : ndarray, shape (n, d), float64
    n_components : int
        ``K`` (<= n).
    seed : int
    reg_covar : float
    max_iter : int
    tol : float

    Returns
    -------
    Mixture
    """
    points = np.asarray(points, dtype=np.float64)
    labels = kmeans_labels(points, n_components, np.random.RandomState(seed))
    responsibilities = np.zeros((points.shape[0], n_components))
    responsibilities[np.arange(points.shape[0]), labels] = 1
    counts, means, covariances = _m_step(points, responsibilities, reg_covar)
    weights = counts / points.shape[0]
    return _em(
        points,
        weights,
        means,
        _precisions_cholesky(covariances),
        reg_covar=reg_covar,
        max_iter=max_iter,
        tol=tol,
        final_precisions=True,
    )


def refine_mixture(
    points: NDArray[np.float64],
    start: MixtureStart,
    *,
    reg_covar: float,
    max_iter: int,
    tol: float = 1e-3,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """EM iterations on ``points`` started from ``start``: scikit-learn's warm-started fit.

    The same operations in the same order as ``GaussianMixture(covariance_type="full",
    weights_init=..., means_init=..., precisions_init=..., max_iter=max_iter).fit(points)``
    (so the same bits), without its input validation, its final E-step (it only serves
    ``fit_predict``'s labels) and its per-call overhead, which cost more than the iteration
    (figures in docs/performance.md). ``tests/core/test_detectors.py`` checks the equality.

    Parameters
    ----------
    points : ndarray, shape (n, d), float64
    start : MixtureStart
    reg_covar : float
        Added to the diagonal of every covariance.
    max_iter : int
        At most this many E+M iterations (>= 1).
    tol : float
        Stop when the mean log-likelihood changes by less (scikit-learn's default 1e-3).

    Returns
    -------
    weights : ndarray, shape (K,)
    means : ndarray, shape (K, d)
    covariances : ndarray, shape (K, d, d)
    """
    refined = _em(
        np.asarray(points, dtype=np.float64),
        start.weights,
        start.means,
        start.precisions_cholesky,
        reg_covar=reg_covar,
        max_iter=max_iter,
        tol=tol,
        final_precisions=False,
    )
    return refined.weights, refined.means, refined.covariances


class GmmDetector(ChangeDetector):
    """GMM-EMD change detector; see the module docstring for the two variants.

    Parameters
    ----------
    variant : {"improved", "paper"}
    random_state : int
    n_components : int
        ``K``, the number of Gaussians (default 8, both variants).
    max_iter : int
        EM iterations for a full fit (scikit-learn default 100): both fits of the paper
        variant, the shared reference model of the improved one.
    refine_iterations : int
        Improved only: EM iterations that describe each cloud, started from the shared model.
    covariance_floor : float
        Improved only: ``reg_covar = (covariance_floor * rms_radius)**2``, as a fraction of
        the reference's RMS distance to its centroid.
    **params
        The common ones; see :mod:`app.core.detectors.base`.
    """

    method: ClassVar[str] = "gmm"
    _score_draws: ClassVar[bool] = False  # EM from a seed or a shared start, then the EMD

    _specs: ClassVar[dict[str, ParamSpec]] = {
        "n_components": ParamSpec("int", 1, 256),
        "max_iter": ParamSpec("int", 1, 10_000),
        "refine_iterations": ParamSpec("int", 1, 10_000),
        "covariance_floor": ParamSpec("float", 0.0, 1.0),
    }
    _variant_defaults: ClassVar[dict[str, dict[str, Any]]] = {
        "improved": {
            "n_components": 8,
            "max_iter": 100,
            "refine_iterations": 1,
            "covariance_floor": 0.03,
        },
        # The paper's cold EM fits cost ~20x the improved refinements: fewer, smaller fits
        # keep detect() within ~1-2 s of CPU at 200k points.
        "paper": {"n_components": 8, "max_iter": 100, "max_points": 2000, "n_resamples": 10},
    }

    def _seed(self) -> int:
        return self.random_state % (2**32)

    def _reg_covar(self, reference: NDArray[np.float64]) -> float:
        if self.variant == "paper":
            return 1e-6
        centred = reference - reference.mean(axis=0)
        rms_radius = float(np.sqrt(np.mean(np.sum(centred**2, axis=1))))
        return max(1e-6, (self.params["covariance_floor"] * rms_radius) ** 2)

    def _context(
        self,
        reference: NDArray[np.float64],
        scan: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> dict[str, Any]:
        n_components = self.params["n_components"]
        smallest = min(reference.shape[0], scan.shape[0])
        if smallest < 2 * n_components:
            raise InputError(
                f"the GMM detector with n_components={n_components} needs at least "
                f"{2 * n_components} points per cloud, got {smallest}"
            )
        reg_covar = self._reg_covar(reference)
        context: dict[str, Any] = {"reg_covar": reg_covar}
        if self.variant == "improved":
            reference_model = fit_mixture(
                reference,
                n_components,
                seed=self._seed(),
                reg_covar=reg_covar,
                max_iter=self.params["max_iter"],
            )
            context["reference_weights"] = reference_model.weights
            context["refinement_start"] = MixtureStart.from_mixture(reference_model)
        return context

    def _score(
        self,
        first: NDArray[np.float64],
        second: NDArray[np.float64],
        context: dict[str, Any],
        rng: np.random.Generator,
        is_resample: bool,
    ) -> float:
        n_components = self.params["n_components"]
        max_iter = self.params["max_iter"]
        reg_covar = context["reg_covar"]
        seed = self._seed()
        if self.variant == "paper":
            model_a, model_b = (
                fit_mixture(points, n_components, seed=seed, reg_covar=reg_covar, max_iter=max_iter)
                for points in (first, second)
            )
            theta_a, theta_b = parameter_vectors(model_a), parameter_vectors(model_b)
            ground = euclidean_ground_distances(theta_a, theta_b)
            return earth_movers_distance(model_a.weights, model_b.weights, ground).distance

        # Both sets are described by the same short EM refinement of one shared model (fitted
        # to the reference): identical sets give identical models, and only what the data
        # moves, moves. Calibration resamples go through exactly the same steps.
        (_, means_a, covariances_a), (_, means_b, covariances_b) = (
            refine_mixture(
                points,
                context["refinement_start"],
                reg_covar=reg_covar,
                max_iter=self.params["refine_iterations"],
            )
            for points in (first, second)
        )
        ground = bures_wasserstein_distances(means_a, covariances_a, means_b, covariances_b)
        # Weights: the shared model's mixing probabilities on both sides. How many points
        # fall in each component after the refinement depends on the sampling pattern
        # (viewpoint, lidar rings), while what a change does to the geometry shows in the
        # components' means and covariances.
        weights = context["reference_weights"]
        return earth_movers_distance(weights, weights, ground).distance

"""The GPLVM log-likelihood objective and its gradients (paper Eq. 6).

    L = -d/2 log|K| - 1/2 tr(K^-1 S),      S = Z Z^T

Only the ``N x N`` Gram matrix ``S`` of the mean-subtracted observations and the number
of values ``d`` per material enter. :class:`Likelihood` holds ``S``, ``d`` and the
:class:`~.kernel.Kernel` (the model's data and hyperparameters) and evaluates ``L`` of
latent points with its gradients with respect to the points and to the hyperparameters;
the optimisers use its unchecked ``_value``/``_value_grad`` on points in units of the length
scale (``u = x / l``, :meth:`Likelihood.in_units`). :func:`log_likelihood` and
:func:`log_likelihood_grad` are the same as functions.
"""

from __future__ import annotations

import math
import numbers
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from .kernel import Kernel, check_points, check_positive, factorise


def check_gram(S, check_psd=True) -> np.ndarray:
    """Return S as a symmetric float64 array, or raise ValueError saying what is wrong."""
    try:
        S = np.array(S, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"Gram matrix `S` must be a real numeric array: {e}") from None
    if S.ndim != 2 or S.shape[0] != S.shape[1]:
        raise InputError(f"Gram matrix `S` must be square (N x N), got shape {S.shape}")
    n = S.shape[0]
    if n < 2:
        raise InputError(f"need at least 2 materials to fit a manifold, `S` is {n} x {n}")
    if not np.all(np.isfinite(S)):
        bad = np.argwhere(~np.isfinite(S))[0]
        raise InputError(
            f"Gram matrix `S` has a non-finite entry ({S[tuple(bad)]}) at {tuple(bad)}"
        )
    scale = np.abs(S).max()
    asym = np.abs(S - S.T).max()
    if asym > 1e-8 * scale:
        raise InputError(
            f"Gram matrix `S` is not symmetric (max |S - S^T| = {asym:.3g}, max |S| = {scale:.3g})"
        )
    S = 0.5 * (S + S.T)
    if check_psd and scale > 0:
        ev = np.linalg.eigvalsh(S)
        if ev[0] < -1e-8 * max(ev[-1], 0.0) or ev[-1] <= 0:
            raise InputError(
                f"Gram matrix `S` is not positive semi-definite (eigenvalues from {ev[0]:.3g} to "
                f"{ev[-1]:.3g}); it must be Z Z^T of the mean-subtracted observations"
            )
    return S


def check_d(d) -> float:
    if isinstance(d, (bool, np.bool_)) or not isinstance(d, numbers.Real):
        raise InputError(f"`d` (number of values per material) must be an integer >= 1, got {d!r}")
    d = float(d)
    if not math.isfinite(d) or d < 1 or d != round(d):
        raise InputError(f"`d` (number of values per material) must be an integer >= 1, got {d!r}")
    return d


def objective(logdet, trace, d) -> float | np.ndarray:
    """``L`` from ``log|K|`` and ``tr(K^-1 S)``."""
    return -0.5 * d * logdet - 0.5 * trace


class Likelihood:
    """``L(X)`` of Eq. 6 for the Gram matrix ``S`` of ``d`` values per material.

    Parameters
    ----------
    S : (N, N) array_like
        Gram matrix ``Z Z^T`` of the mean-subtracted observations.
    d : int
        Number of values per material (columns of Z).
    kernel : Kernel, optional
        ``l`` and ``mu > 0`` (default ``Kernel()``).

    Raises
    ------
    InputError
        On an invalid ``S``, ``d`` or ``mu = 0``.
    """

    def __init__(self, S, d, kernel=None, _checked=False) -> None:
        kernel = Kernel() if kernel is None else kernel
        if not _checked:
            S, d = check_gram(S), check_d(d)
            check_positive("noise", kernel.noise)
        self.S, self.d, self.kernel = S, d, kernel
        self._unit = kernel.in_units()

    @property
    def n(self) -> int:
        return self.S.shape[0]

    def in_units(self) -> Likelihood:
        """The same objective of points in units of the length scale (``L(u l)``, ``l = 1``)."""
        return Likelihood(self.S, self.d, self.kernel.in_units(), _checked=True)

    def _latent(self, X) -> np.ndarray:
        return check_points("latent", X, n=self.n)

    # -- public, checked
    def __call__(self, X) -> float:
        """``L`` at latent points ``X`` (N, q)."""
        return self._value(self._latent(X) / self.kernel.length_scale)

    def gradient(self, X) -> tuple:
        """``L`` and ``dL/dX`` (N, q).

        With ``G = K^-1 S K^-1 - d K^-1``, ``dL/dx_i = -sum_j G_ij K_ij (x_i - x_j) / l^2``.
        """
        l = self.kernel.length_scale
        L, grad_u = self._value_grad(self._latent(X) / l)
        return L, grad_u / l

    def gradient_theta(self, X) -> tuple:
        """``L`` and ``dL/dtheta`` (2,) for the hyperparameters ``(l, mu)`` (:attr:`Kernel.theta`):
        ``dL/dtheta_k = 1/2 tr(G dK/dtheta_k)`` with ``G`` as in :meth:`gradient`.
        """
        X = self._latent(X)
        K = self.kernel._K(X)
        f = factorise(K)
        K_inv = f.inverse()
        KS = K_inv @ self.S
        G = KS @ K_inv - self.d * K_inv
        dK = self.kernel.dK_dtheta(X)
        return objective(f.logdet, float(np.trace(KS)), self.d), 0.5 * np.einsum("ij,kji->k", G, dK)

    # -- unchecked, in units of the length scale (the optimisers' inner loops)
    def _penalty(self, U) -> float:
        """What a penalised objective takes off ``L`` (:class:`~.stress.PenalisedLikelihood`): 0."""
        return 0.0

    def _value(self, U) -> float:
        f = factorise(self._unit._K(U))
        return float(objective(f.logdet, float(np.trace(f.solve(self.S))), self.d))

    def _value_grad(self, U) -> tuple:
        """L and dL/dU for latent points in units of the length scale."""
        K = self._unit._K(U)
        f = factorise(K)
        K_inv = f.inverse()
        KS = K_inv @ self.S
        L = objective(f.logdet, float(np.trace(KS)), self.d)
        # dL = 1/2 tr(G dK) with G = K_inv S K_inv - d K_inv; dK_ij/du_i = -E_ij (u_i - u_j)
        G = KS @ K_inv - self.d * K_inv
        W = G * K
        W[np.diag_indices_from(W)] = 0.0
        grad = W @ U - W.sum(axis=1)[:, None] * U
        return L, grad

    def _hessp(self, U, V) -> np.ndarray:
        """``d/dt dL/dU (U + t V)`` at ``t = 0``: the Hessian of L times the direction ``V``
        (N, q), in units of the length scale, exactly.

        With ``A = K^-1``, ``B = A S A``, ``G = B - d A``, ``E`` the off-diagonal of K and
        ``dE_ij = -E_ij (u_i - u_j).(v_i - v_j)``: ``dG = d (A dE) A - M - M^T`` with
        ``M = (A dE) B``, that is ``dG = P + P^T`` with ``P = (A dE) (d A / 2 - B)`` (``A dE A``
        is symmetric), and the gradient's ``W = G o E`` changes by ``dG o E + G o dE``.
        The factorisation at ``U`` is kept for the next product at the same points.
        """
        c = self._curvature(U)
        diff = np.einsum("ik,ik->i", U, V)
        UV = U @ V.T
        dE = c.E * (UV + UV.T - diff[:, None] - diff[None, :])  # -E_ij (u_i - u_j).(v_i - v_j)
        P = (c.A @ dE) @ c.C
        dW = (P + P.T) * c.E + c.G * dE  # E's diagonal is 0: so is dW's
        return dW @ U - dW.sum(axis=1)[:, None] * U + c.W @ V - c.Wsum[:, None] * V

    def _curvature(self, U) -> _Curvature:
        """``A``, ``C = d A / 2 - B``, ``G``, ``E``, ``W`` and its row sums of :meth:`_hessp` at
        ``U`` (the last one kept).
        """
        key = U.tobytes()
        cached = getattr(self, "_cache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        K = self._unit._K(U)
        A = factorise(K).inverse()
        B = A @ self.S @ A
        B = 0.5 * (B + B.T)
        E = K.copy()
        E[np.diag_indices_from(E)] = 0.0
        G = B - self.d * A
        W = G * E
        c = _Curvature(A, 0.5 * self.d * A - B, G, E, W, W.sum(axis=1))
        self._cache = (key, c)
        return c


class _Curvature(NamedTuple):
    A: np.ndarray
    C: np.ndarray  # d A / 2 - B
    G: np.ndarray
    E: np.ndarray
    W: np.ndarray
    Wsum: np.ndarray


def _likelihood(S, d, length_scale, noise) -> Likelihood:
    S, d = check_gram(S), check_d(d)
    kernel = Kernel(check_positive("length_scale", length_scale), check_positive("noise", noise))
    return Likelihood(S, d, kernel, _checked=True)


def log_likelihood(latent, S, d, length_scale=1.0, noise=1e-4) -> float:
    """Log-likelihood ``L = -d/2 log|K| - 1/2 tr(K_inv S)`` of latent points (Eq. 6).

    ``Likelihood(S, d, Kernel(length_scale, noise))(latent)``.

    Parameters
    ----------
    latent : (N, q) array_like
        Latent points, one per material.
    S : (N, N) array_like
        Gram matrix ``Z Z^T`` of the mean-subtracted observations.
    d : int
        Number of values per material (columns of Z).
    length_scale, noise : float
        ``l > 0`` and ``mu > 0`` of the covariance function.

    Raises
    ------
    NotPositiveDefiniteError
        If K cannot be factorised (a ``numpy.linalg.LinAlgError``).
    ValueError
        On invalid input.
    """
    return _likelihood(S, d, length_scale, noise)(latent)


def log_likelihood_grad(latent, S, d, length_scale=1.0, noise=1e-4) -> tuple[float, np.ndarray]:
    """Log-likelihood and its analytic gradient with respect to the latent points.

    ``Likelihood(S, d, Kernel(length_scale, noise)).gradient(latent)``; same parameters as
    :func:`log_likelihood`.

    Returns
    -------
    L : float
    grad : (N, q) ndarray
    """
    return _likelihood(S, d, length_scale, noise).gradient(latent)

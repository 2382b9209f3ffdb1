"""A stress term that asks latent distances to follow given distances between the materials.

The GPLVM likelihood (Eq. 6) places materials by their tables' covariance; two materials that
look alike can end up far apart with others between them. The optional stress term of the
layout fit asks the latent distances ``r_ij = |x_i - x_j|`` of chosen pairs to be proportional
to target distances ``d_ij`` (e.g. perceptual distances between the tables), as metric
multidimensional scaling does, with the scale fitted::

    sigma(X) = min_s sum_ij w_ij (r_ij - s d_ij)^2 / sum_ij w_ij r_ij^2
             = 1 - a^2 / (b c),   a = sum w r d,  b = sum w r^2,  c = sum w d^2

(Kruskal's normalised stress with the best scale ``s = a / c``; sums over pairs ``i < j``).
``sigma`` is 0 when the distances of the chosen pairs are exactly proportional and at most 1;
it does not change when the latent points are scaled, so it shapes the layout without fixing
its size (the likelihood does that against the length scale). The pairs ``w_ij = 1`` are every
pair, or each material with its ``k`` nearest by the target distance (either way round).

The fit maximises ``L(X) - lambda (d N / 2) sigma(X)``: ``L / (d N / 2)`` is the
log-likelihood per value and material, so ``lambda`` means the same at any table resolution
and number of materials. With ``dr_ij / dx_i = (x_i - x_j) / r_ij``::

    d sigma / d r_ij = 2 w_ij (a / (b c)) (a r_ij / b - d_ij)
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .._util.checks import finite
from ..errors import InputError

if TYPE_CHECKING:
    from typing import Any


__all__ = ["Stress", "StressTerm", "neighbour_mask"]


def _check_neighbours(k) -> int | None:
    if k is None:
        return None
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, numbers.Integral) or k < 1:
        raise InputError(
            f"`stress_neighbours` must be an integer >= 1 (nearest materials per material) "
            f"or None (every pair), got {k!r}"
        )
    return int(k)


@dataclass(frozen=True)
class Stress:
    """The stress term's hyperparameters: its weight ``lambda`` and the pairs it covers.

    Attributes
    ----------
    weight : float
        ``lambda >= 0``; 0: no stress term (the plain GPLVM fit).
    neighbours : int or None
        Each material's ``k`` nearest materials by the target distance; None: every pair.
    """

    weight: float = 0.0
    neighbours: int = None

    def __post_init__(self) -> None:
        weight = finite("`stress` (the stress term's weight)", self.weight, 0.0)
        object.__setattr__(self, "weight", weight)
        object.__setattr__(self, "neighbours", _check_neighbours(self.neighbours))

    @property
    def active(self) -> bool:
        """Whether the term is on (``weight > 0``)."""
        return self.weight > 0

    def term(self, distances, n, d) -> StressTerm:
        """The :class:`StressTerm` of target ``distances`` (N, N) in a fit of ``n`` materials of
        ``d`` values each.
        """
        D = check_distances(distances, n)
        return StressTerm(D, neighbour_mask(D, self.neighbours), self.weight * 0.5 * d * n)


def check_distances(distances, n) -> np.ndarray:
    """The target distances as a symmetric (N, N) float64 array with a zero diagonal, or raise."""
    try:
        D = np.array(distances, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"stress `distances` must be a real numeric array: {e}") from None
    if D.shape != (n, n):
        raise InputError(
            f"stress `distances` must be N x N for the N = {n} materials, got shape {D.shape}"
        )
    if not np.isfinite(D).all() or (D < 0).any():
        bad = D[~np.isfinite(D) | (D < 0)][0]
        raise InputError(
            f"stress `distances` must be finite and >= 0, got {bad}: give the tables' distances "
            "(presets.stress_distances) or fit with stress=0.0"
        )
    if np.abs(D - D.T).max() > 1e-8 * max(D.max(), 1e-300):
        raise InputError("stress `distances` must be symmetric (D[i, j] == D[j, i])")
    D = 0.5 * (D + D.T)
    np.fill_diagonal(D, 0.0)
    if not D.max() > 0:
        raise InputError(
            "stress `distances` are all 0 (the tables look alike everywhere the distance "
            "looks): there is nothing to lay out by; fit with stress=0.0 (--stress 0)"
        )
    return D


def neighbour_mask(D, k=None) -> np.ndarray:
    """``w`` (N, N) of 0/1, symmetric, zero diagonal: pairs where either is among the other's ``k``
    nearest by ``D`` (ties broken by index); ``k`` None or ``>= N - 1``: every pair.
    """
    n = len(D)
    W = np.ones((n, n)) - np.eye(n)
    if k is None or k >= n - 1:
        return W
    order = np.argsort(D + np.diag(np.full(n, np.inf)), axis=1, kind="stable")[:, :k]
    W = np.zeros((n, n))
    W[np.repeat(np.arange(n), k), order.ravel()] = 1.0
    return np.maximum(W, W.T)


class StressTerm:
    """``sigma(X)`` (module doc) of targets ``D`` over pairs ``W``, and its weight in the objective
    (``coefficient``: ``lambda d N / 2``).
    """

    def __init__(self, D, W, coefficient) -> None:
        self.D, self.W, self.coefficient = D, W, float(coefficient)
        self._c = float((W * D * D).sum()) / 2.0

    def value(self, X) -> float:
        """``sigma`` at latent points ``X`` (N, q)."""
        return self._value_grad(X, grad=False)[0]

    def value_grad(self, X) -> tuple[float, np.ndarray]:
        """``sigma`` and ``d sigma / dX`` (N, q)."""
        return self._value_grad(X, grad=True)

    def _geometry(self, X) -> tuple:
        """``r``, ``a``, ``b`` and ``d sigma / d r_ij / r_ij`` at ``X`` (the last one kept)."""
        key = X.tobytes()
        cached = getattr(self, "_cache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        diff = X[:, None, :] - X[None, :, :]
        r = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
        a = float((self.W * r * self.D).sum()) / 2.0
        b = float((self.W * r * r).sum()) / 2.0
        g = None
        if b > 0:
            # d sigma / d r_ij over r_ij (each pair once: the full matrix sums both halves)
            with np.errstate(divide="ignore", invalid="ignore"):
                g = np.where(
                    r > 0, 2.0 * self.W * (a / (b * self._c)) * (a * r / b - self.D) / r, 0.0
                )
        out = (r, a, b, g)
        self._cache = (key, out)
        return out

    def _value_grad(self, X, grad) -> tuple[Any, Any]:
        r, a, b, g = self._geometry(X)
        if not b > 0:
            return 1.0, np.zeros_like(X)
        sigma = 1.0 - a * a / (b * self._c)
        if not grad:
            return sigma, None
        return sigma, g.sum(axis=1)[:, None] * X - g @ X

    def hessp(self, X, V) -> np.ndarray:
        """``d/dt d sigma / dX (X + t V)`` at ``t = 0`` (N, q), exactly where no two points
        coincide (pairs at distance 0 contribute nothing, as to the gradient).

        With ``g_ij = 2 w_ij s (a / b - d_ij / r_ij)``, ``s = a / (b c)``, the gradient is
        ``sum_j g_ij (x_i - x_j)``; along ``V``, ``dr_ij = (x_i - x_j).(v_i - v_j) / r_ij``,
        ``da = sum w d dr``, ``db = sum 2 w r dr`` (pairs once) and
        ``dg_ij = 2 w_ij (ds (a / b - d_ij / r_ij) + s (d(a / b) + d_ij dr_ij / r_ij^2))``.
        """
        r, a, b, g = self._geometry(X)
        if not b > 0:
            return np.zeros_like(X)
        inv, W2, W2D, W2r, base, quad, gsum = self._curvature(X)
        xv = np.einsum("ik,ik->i", X, V)
        XV = X @ V.T
        dr = (xv[:, None] + xv[None, :] - XV - XV.T) * inv
        da = float(np.vdot(W2D, dr)) / 4.0
        db = float(np.vdot(W2r, dr)) / 2.0
        c = self._c
        s = a / (b * c)
        dab = (da * b - a * db) / (b * b)
        ds = dab / c
        # dg = 2 w (ds (a / b - d / r) + s (d(a / b) + d dr / r^2)), zero where r = 0
        dg = ds * base + (s * dab) * W2 + s * (quad * dr)
        return dg.sum(axis=1)[:, None] * X - dg @ X + gsum[:, None] * V - g @ V

    def _curvature(self, X) -> tuple:
        """What :meth:`hessp` needs at ``X`` besides :meth:`_geometry` (the last one kept):
        ``1 / r`` (0 where ``r = 0``), ``2 w`` where ``r > 0``, ``2 w d``, ``2 w r``,
        ``2 w (a / b - d / r)``, ``2 w d / r^2`` and the row sums of ``g``.
        """
        key = X.tobytes()
        cached = getattr(self, "_hcache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        r, a, b, g = self._geometry(X)
        with np.errstate(divide="ignore"):
            inv = np.where(r > 0, 1.0 / r, 0.0)
        W2 = np.where(r > 0, 2.0 * self.W, 0.0)
        W2D = W2 * self.D
        out = (inv, W2, W2D, W2 * r, W2 * (a / b - self.D * inv), W2D * inv * inv, g.sum(axis=1))
        self._hcache = (key, out)
        return out

    def penalty(self, X) -> float:
        """The amount taken off the likelihood: ``lambda (d N / 2) sigma(X)``."""
        return self.coefficient * self.value(X)


class PenalisedLikelihood:
    """``L(U) - coefficient sigma(U)`` for the optimisers, in units of the length scale (``sigma``
    does not change with the units); ``likelihood``: a :class:`~.likelihood.Likelihood` in units.
    """

    def __init__(self, likelihood, term) -> None:
        self.likelihood, self.term = likelihood, term
        self.S, self.d, self.kernel = likelihood.S, likelihood.d, likelihood.kernel

    @property
    def n(self) -> int:
        return self.likelihood.n

    def _penalty(self, U):
        return self.term.penalty(U)

    def _value(self, U) -> float:
        return self.likelihood._value(U) - self.term.penalty(U)

    def _hessp(self, U, V) -> np.ndarray:
        return self.likelihood._hessp(U, V) - self.term.coefficient * self.term.hessp(U, V)

    def _value_grad(self, U) -> tuple:
        L, g = self.likelihood._value_grad(U)
        s, gs = self.term.value_grad(U)
        return L - self.term.coefficient * s, g - self.term.coefficient * gs

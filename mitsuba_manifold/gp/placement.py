"""One new latent point under the GPLVM likelihood, the other points fixed (paper Sec. 3, Eq. 6).

A material added to a fitted manifold gets the latent point ``x`` that maximises

    L(x) = -d/2 log|K'| - 1/2 tr(K'^-1 S')

over the one new point, the fitted points ``X`` and the hyperparameters held: ``S'`` is the
Gram matrix of all N + 1 mean-subtracted feature tables (the new one last) and ``K'`` the
covariance matrix of the N + 1 points. With ``K`` of the fixed points, ``k = k(x)`` and the
blocks ``S' = [[A, a], [a^T, alpha]]``, the Schur complement ``s = 1 + mu - k^T K^-1 k`` gives

    log|K'| = log|K| + log s
    tr(K'^-1 S') = tr(K^-1 A) + (k^T P k - 2 k^T r + alpha) / s,   P = K^-1 A K^-1, r = K^-1 a

so each evaluation (and its gradient, through ``dk/dx = -k (x - x_j) / l^2``) costs
O(N^2) after one factorisation of ``K``. Several starts are tried (L-BFGS-B from each);
the best point found is returned.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.optimize

from ..errors import InputError
from .kernel import Kernel, check_points, factorise
from .likelihood import check_d, check_gram

if TYPE_CHECKING:
    from typing import Any


@dataclass
class Placement:
    """:func:`place_point`: the new point and the log-likelihood of all N + 1 points there."""

    x: np.ndarray
    log_likelihood: float
    n_evaluations: int


class OnePoint:
    """``L(x)`` of Eq. 6 as a function of the last of N + 1 latent points (see the module docstring).

    Parameters
    ----------
    latent : (N, q) array
        The fixed points.
    S : (N + 1, N + 1) array
        Gram matrix of the N + 1 mean-subtracted feature tables, the new material last.
    d : int
        Values per table.
    kernel : Kernel
    """

    def __init__(self, latent, S, d, kernel) -> None:
        self.X = check_points("latent", latent)
        n = len(self.X)
        S = check_gram(S, check_psd=False)
        if S.shape != (n + 1, n + 1):
            raise InputError(
                f"`S` must be the ({n + 1}, {n + 1}) Gram matrix of the N + 1 tables, "
                f"got shape {S.shape}"
            )
        self.d, self.kernel = check_d(d), kernel
        f = factorise(kernel.K(self.X))
        K_inv = f.inverse()
        A, a, self.alpha = S[:n, :n], S[:n, n], float(S[n, n])
        self.K_inv = K_inv
        self.P = K_inv @ A @ K_inv
        self.r = K_inv @ a
        self.const = -0.5 * d * f.logdet - 0.5 * float(np.sum(K_inv * A))
        self.n_evaluations = 0

    def value_grad(self, x) -> tuple[float, Any]:
        """``L`` and ``dL/dx`` (q,) at the new point ``x``."""
        self.n_evaluations += 1
        x = np.asarray(x, dtype=np.float64)
        k = self.kernel.K(x[None], self.X)[0]
        dk = -k[:, None] * (x[None] - self.X) / self.kernel.length_scale**2  # (N, q)
        v = self.K_inv @ k
        s = 1.0 + self.kernel.noise - k @ v
        if s <= 0:
            return -np.inf, np.zeros_like(x)
        Pk = self.P @ k
        g = k @ Pk - 2.0 * k @ self.r + self.alpha
        ds = -2.0 * v @ dk
        dg = 2.0 * (Pk - self.r) @ dk
        L = self.const - 0.5 * self.d * np.log(s) - 0.5 * g / s
        dL = -0.5 * self.d * ds / s - 0.5 * (dg / s - g * ds / s**2)
        return float(L), dL


def place_point(latent, S, d, starts, *, length_scale=1.0, noise=1e-4, max_iter=200) -> Placement:
    """The latent point of material N (the last row of ``S``) with the N points ``latent`` fixed.

    Parameters
    ----------
    latent : (N, q) array
        The fitted latent points (not changed).
    S : (N + 1, N + 1) array
        Gram matrix of the N + 1 mean-subtracted feature tables, the new material last.
    d : int
        Values per table (the ``d`` of Eq. 6).
    starts : (M, q) array
        Starting points for the new one (e.g. its projection, its closest materials' points).
    length_scale, noise : float
        The kernel's ``l`` and ``mu`` (those of the fit).

    Returns
    -------
    Placement
    """
    one = OnePoint(latent, S, d, Kernel(length_scale, noise))
    starts = np.atleast_2d(np.asarray(starts, dtype=np.float64))
    if starts.shape[1] != one.X.shape[1] or not np.isfinite(starts).all():
        raise InputError(
            f"`starts` must be finite points of {one.X.shape[1]} coordinates, got shape {starts.shape}"
        )
    scale = float(d)  # L is of order d: keep the optimiser's numbers near 1

    def f(x) -> tuple:
        value, grad = one.value_grad(x)
        return -value / scale, -grad / scale

    best = None
    for x0 in starts:
        res = scipy.optimize.minimize(
            f,
            x0,
            jac=True,
            method="L-BFGS-B",
            options={"maxiter": max_iter, "gtol": 1e-10, "ftol": 1e-14},
        )
        if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
            best = res
    return Placement(best.x.copy(), float(-best.fun * scale), one.n_evaluations)

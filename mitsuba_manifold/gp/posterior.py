"""The Gaussian process conditioned on fixed latent points (paper Eq. 1-4), from one factorisation of K.

With ``K`` the covariance of the latent points ``X`` and ``k(x)`` the cross-covariance of a
point ``x`` with them (Eq. 3)::

    b(x)        = K^-1 k(x)                      (Eq. 4: z(x) = b(x)^T Z)
    sigma^2(x)  = c(x, x) - k(x)^T K^-1 k(x)     (Eq. 2)

:class:`Posterior` factorises ``K`` once (:meth:`Kernel.factorise`) and gives ``b``, its
Jacobian ``K^-1 dk/dx``, the variance and its gradient. The interpolant of Eq. 4
(:class:`~mitsuba_manifold.manifold.interpolant.GaussianProcessWeights`) and
:class:`~mitsuba_manifold.manifold.model.Manifold` share it. Points ``x`` are ``(M, q)``
float64 arrays already checked by the caller.
"""

from __future__ import annotations

import numpy as np

from .kernel import Kernel, check_points, factorise


class Posterior:
    """``K``, its factorisation and the GP's predictions at new points.

    Parameters
    ----------
    X : (N, q) array_like
        Latent points.
    kernel : Kernel, optional
        Covariance function (default ``Kernel()``: ``l = 1``, ``mu = 1e-4``).

    Raises
    ------
    NotPositiveDefiniteError
        If ``K`` cannot be factorised (coincident points, ``mu`` too small).
    """

    def __init__(self, X, kernel=None) -> None:
        self.X = check_points("latent", X)
        self.kernel = Kernel() if kernel is None else kernel
        self.K = self.kernel._K(self.X)
        self.factor = factorise(self.K)

    @property
    def n(self) -> int:
        return len(self.X)

    def inverse(self) -> np.ndarray:
        """``K^-1`` (symmetrised)."""
        return self.factor.inverse()

    def condition_number(self) -> float:
        """2-norm condition number of ``K``."""
        ev = np.linalg.eigvalsh(self.K)
        return float(ev[-1] / ev[0])

    def weights(self, x) -> np.ndarray:
        """``b(x) = K^-1 k(x)`` (M, N) of the smooth kernel (Eq. 4 away from the training points)."""
        return self.factor.solve(self.kernel.cross(x, self.X).T).T

    def weights_jacobian(self, x) -> np.ndarray:
        """``db/dx = K^-1 dk/dx`` (M, N, q)."""
        dk = self.kernel.dK_dx(x, self.X)
        m, n, q = dk.shape
        db = self.factor.solve(dk.transpose(1, 0, 2).reshape(n, m * q))
        return db.reshape(n, m, q).transpose(1, 0, 2)

    def variance(self, x) -> np.ndarray:
        """``c(x, x) - k^T K^-1 k`` (M,) (Eq. 2), with the noise term ``mu delta(x, x_i)`` in ``k``
        where ``x`` is a latent point (the variance is then 0).
        """
        k = self.kernel.cross(x, self.X, exact=True)
        return 1.0 + self.kernel.noise - np.einsum("mn,mn->m", k, self.factor.solve(k.T).T)

    def variance_gradient(self, x) -> np.ndarray:
        """Gradient of the smooth part of :meth:`variance`: ``-2 (dk/dx)^T K^-1 k`` (M, q)."""
        k = self.kernel.cross(x, self.X)
        b = self.factor.solve(k.T).T
        return -2.0 * np.einsum("mnq,mn->mq", self.kernel.dK_dx(x, self.X, k), b)

"""The canonical pose of fitted latent points: one representative of the layouts the fit cannot tell apart.

The GPLVM likelihood (Eq. 6) sees the latent points only through the covariance matrix K,
whose entries depend on the distances ``|x_i - x_j|``; the layout's stress term
(:mod:`.stress`) sees the distances too. Any rigid motion of the points (translation,
rotation, reflection) leaves both unchanged, so a fit fixes the layout only up to one. The
rule that picks one pose of every layout (:func:`canonical_pose`):

1. translate so that the points' mean is the origin;
2. rotate onto the principal axes of the points, in order of decreasing variance (the
   eigenvectors of ``X^T X`` of the centred points);
3. reflect each axis so that the third moment of the points' coordinates along it,
   ``sum_i x_ik^3``, is positive; an axis whose third moment is below ``1e-6`` of
   ``sum_i |x_ik|^3`` (a symmetric spread) is signed so that the first point, in the order
   given, whose ``|x_ik|`` exceeds ``1e-6`` of the axis' largest has a positive coordinate.

The rule uses only the points' own geometry (and, for symmetric axes, their order), so two
fits that reach the same layout in different poses, or on different machines, are mapped to
the same coordinates. Axes of equal variance have no preferred direction; the rule is then
ill-defined, which fitted layouts of measured materials do not come near.
"""

from __future__ import annotations

import numpy as np

#: Relative size below which an axis' third moment counts as zero (a symmetric spread).
SYMMETRIC = 1e-6


def canonical_pose(X) -> np.ndarray:
    """``X`` (N, q) translated, rotated and reflected to the canonical pose (module doc).

    Returns
    -------
    (N, q) ndarray
        The posed points: mean zero, principal axes along the coordinate axes in order of
        decreasing variance, positive third moment along each (or, for a symmetric axis, the
        first clearly non-zero coordinate positive). Distances between the points are kept.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = X - X.mean(axis=0)
    lam, V = np.linalg.eigh(Y.T @ Y)
    Y = Y @ V[:, np.argsort(lam, kind="stable")[::-1]]
    third = np.sum(Y**3, axis=0)
    size = np.sum(np.abs(Y) ** 3, axis=0)
    sign = np.sign(third)
    for k in np.nonzero(~(np.abs(third) > SYMMETRIC * size))[0]:
        big = np.abs(Y[:, k]).max()
        first = np.nonzero(np.abs(Y[:, k]) > SYMMETRIC * big)[0]
        sign[k] = 1.0 if first.size == 0 else np.sign(Y[first[0], k])
    return Y * np.where(sign < 0, -1.0, 1.0)


def rigid_modes(X) -> np.ndarray:
    """An orthonormal basis ``Q`` ((N q, m) array) of the first-order rigid motions of ``X``:
    the ``q`` translations and the ``q (q - 1) / 2`` rotations ``x_i -> x_i + A x_i`` (``A``
    skew-symmetric, about the points' mean), as flattened ``(N, q)`` displacements.

    The objective does not change along them, so its gradient has no component there beyond
    rounding, and its Hessian at a stationary point sends them to zero: the optimisers take
    ``(I - Q Q^T)`` of the gradient and of Hessian products (the *projected* gradient) so that
    no step drifts along them.
    """
    n, q = X.shape
    Y = X - X.mean(axis=0)
    gens = []
    for k in range(q):
        t = np.zeros((n, q))
        t[:, k] = 1.0
        gens.append(t.ravel())
    for k in range(q):
        for j in range(k + 1, q):
            r = np.zeros((n, q))
            r[:, k], r[:, j] = -Y[:, j], Y[:, k]
            gens.append(r.ravel())
    G = np.stack(gens, axis=1)
    Q, R = np.linalg.qr(G)
    keep = np.abs(np.diag(R)) > 1e-12 * max(np.abs(np.diag(R)).max(), 1e-300)
    return Q[:, keep]

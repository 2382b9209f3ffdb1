"""Searching the latent space for the point that minimises an objective of the weights.

The matchers (a basis match, :mod:`mitsuba_manifold.basis.inverse.match`, and the starts of a render
match, :mod:`mitsuba_manifold.render.inverse.scan`) minimise ``E(x) = objective(w(x))
[+ prior * var(x)]`` over latent points ``x``. The objective is any callable
``objective(w) -> (value, dE/dw, ...)`` with a vectorised ``objective.batch(W) -> (values, ...)``;
the weights' analytic Jacobian (:meth:`Manifold.weights_jacobian`) chains ``dE/dw`` to
``dE/dx``. The pieces, shared by both:

- :func:`box`: the search box, the latent points' bounding box widened by ``MARGIN`` l;
- :func:`scan`: random points near the data (a training point plus a normal step of ``l / 2``),
  scored in one batch;
- :func:`start_points`: the best single material's point, then the best scanned points at
  least ``spread`` l apart;
- :func:`descend`: L-BFGS-B from one start (:func:`evaluator` gives SciPy its ``fun``).
"""

import numpy as np
from scipy import optimize

#: Margin of the search box around the latent points, in length scales.
MARGIN = 2.0


def box(manifold, margin=MARGIN):
    """The search box ``[(lo, hi)] * q``: the latent points' bounds widened by ``margin`` l."""
    lo = manifold.latent.min(axis=0) - margin * manifold.length_scale
    hi = manifold.latent.max(axis=0) + margin * manifold.length_scale
    return list(zip(lo, hi))


def evaluator(manifold, objective, prior=0.0):
    """SciPy's ``fun(x) -> (value, gradient)`` of ``objective(w(x)) + prior * var(x)``, and a
    one-element list counting its evaluations.
    """
    count = [0]

    def fun(x):
        count[0] += 1
        _, w = manifold.weights(x)
        err, gw = objective(w)[:2]
        grad = manifold.weights_jacobian(x).T @ gw
        if prior:
            err += prior * float(manifold.variance(x))
            grad = grad + prior * manifold.variance_gradient(x)
        return err, grad

    return fun, count


def descend(manifold, objective, prior, x0, bounds, max_iter):
    """L-BFGS-B from ``x0`` within ``bounds``: a dict of the start ``x0``, the point ``x``, its
    ``objective``, ``n_evaluations`` and SciPy's ``message``.
    """
    fun, count = evaluator(manifold, objective, prior)
    res = optimize.minimize(
        fun, x0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": max_iter}
    )
    return {
        "x0": np.asarray(x0, dtype=float),
        "x": res.x,
        "objective": float(res.fun),
        "n_evaluations": count[0],
        "message": str(res.message),
    }


def scan(manifold, objective, prior, bounds, n_points, seed=0):
    """``n_points`` random latent points near the data (a training point plus a normal step
    of ``l / 2``, clipped to ``bounds``), scored at once; returns ``(points (M, q), objectives (M,))``.
    """
    if n_points == 0:
        return np.zeros((0, manifold.q)), np.zeros(0)
    rng = np.random.default_rng(seed)
    X = manifold.latent[rng.integers(manifold.n, size=n_points)]
    X = X + 0.5 * manifold.length_scale * rng.standard_normal(X.shape)
    X = np.clip(X, *np.array(bounds).T)
    err = objective.batch(manifold.weights(X)[1])[0]
    if prior:
        err = err + prior * manifold.variance(X)
    return X, err


def start_points(manifold, best, X, err, k, spread=0.25):
    """``k`` starts: the latent point of training material ``best``, then the best scanned
    points ``X`` (objectives ``err``) at least ``spread * l`` apart (without scanned points:
    the training points nearest to ``best``). Training points are nudged by ``1e-6 l`` so
    that the descent starts on the smooth interpolant.
    """
    nudge = 1e-6 * manifold.length_scale / np.sqrt(manifold.q)
    if len(X) == 0:
        d = np.linalg.norm(manifold.latent - manifold.latent[best], axis=1)
        return [manifold.latent[i] + nudge for i in np.argsort(d, kind="stable")[:k]]
    chosen = [manifold.latent[best] + nudge]
    for i in np.argsort(err, kind="stable"):
        if len(chosen) == k:
            break
        if min(np.linalg.norm(X[i] - c) for c in chosen) >= spread * manifold.length_scale:
            chosen.append(X[i])
    return chosen

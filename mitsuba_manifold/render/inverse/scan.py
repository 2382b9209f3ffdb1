"""The starts of :func:`.match_render.match_render`: a cheap scan of the whole latent space.

Every training material is rendered alone (primal, ``scan_spp`` samples split over two renders
with independent seeds, the same seeds for every material). Near a set of materials the image
of a blend is close to the blend of their images, ``I(w) ~ sum_i w_i I_i`` (exact for the light
paths that meet the material once; what it misses is the material seeing itself), so the image
error of any latent point is a quadratic form in its weights and is estimated without rendering
(as :mod:`..basis.match` does on a basis), for the training materials, 8192 random points near
the data and the L-BFGS-B optima started from the best of them.

The two renders ``A`` and ``B`` make this estimate free of the renders' noise: for independent
renders ``E[(A - t)(B - t)] = (E[I] - t)^2`` (:class:`CrossMSE`), whereas the error of one render
``E[(A - t)^2]`` adds the render's variance, which at a few samples is much larger than the
differences between materials and largest for glossy and mirror-like ones: ranked by the error of
one 16-spp render, the scan put a matte or a wrong metallic material before the right glossy one
(the true point's main material ranked 30th for a target near ``ss440``). The estimate can be
negative (it is a difference); only its ranking is used.

The optima and the best single materials are then rendered again with the true light transport
at ``check_spp`` (two more independent renders each), ranked by the same unbiased error, and the
best ``starts`` of them, at least a quarter of a length scale apart, become Adam's starts. A start
at a training point is moved off it (:func:`start_near`: the convex weights are flat there).
"""

import time

import numpy as np

from ..._util.blas import one_thread
from ...basis.inverse import search as latent

#: Random latent points scored on the quadratic form (as ``basis.match``'s default scan).
SCAN_POINTS = 8192
#: Candidates closer than this (in length scales) are one candidate (rendered once).
SAME_POINT = 0.05
#: A candidate whose largest weight exceeds this sits on a training point (Adam starts off it).
AT_TRAINING_POINT = 0.999


class CrossMSE:
    """The relative MSE of the blend ``s sum_i w_i I_i`` estimated from two independent renders of
    every image, ``A`` and ``B`` (N, P): ``E = sum_p c_p (s A_p w - t_p)(s B_p w - t_p)`` (unbiased
    for the noise-free error), as a quadratic form ``s^2 w^T G w - 2 s w^T h + e0`` with
    ``G = (A C B^T + B C A^T) / 2``, ``h = (A + B) C t / 2``; ``s`` 1 or (``exposure_free``) the
    least-squares scale. The interface of :mod:`..basis.objectives` (``__call__``, ``batch``).
    """

    def __init__(self, A, B, target, c, exposure_free=False):
        A, B = np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64)
        target, c = np.asarray(target, dtype=np.float64), np.asarray(c, dtype=np.float64)
        G = (A * c) @ B.T
        self.G = 0.5 * (G + G.T)
        self.h = 0.5 * (A + B) @ (c * target)
        self.e0 = float(c @ (target * target))
        self.exposure_free = exposure_free

    def _scale(self, a, b):
        if not self.exposure_free:
            return np.ones_like(a)
        return np.where(a > 0, np.maximum(b / np.where(a > 0, a, 1.0), 0.0), 1.0)

    def __call__(self, w):
        """``(error, dE/dw, exposure)``."""
        w = np.asarray(w, dtype=np.float64)
        Gw = self.G @ w
        a, b = float(w @ Gw), float(w @ self.h)
        s = float(self._scale(np.array(a), np.array(b)))
        return s * s * a - 2.0 * s * b + self.e0, 2.0 * s * s * Gw - 2.0 * s * self.h, s

    def batch(self, W):
        """Errors and exposures of many weight vectors W (M, N) at once."""
        W = np.asarray(W, dtype=np.float64)
        a = ((W @ self.G) * W).sum(axis=1)
        b = W @ self.h
        s = self._scale(a, b)
        return s * s * a - 2.0 * s * b + self.e0, s


def _pixels(problem):
    """The loss's pixels of every view: ``(selections, target (P,), weights c (P,))``, ``c`` the
    loss weights divided by the number of views (the loss is the mean over the views).
    """
    sel = [w > 0 for _, w in problem.data]
    t = np.concatenate([t[s] for (t, _), s in zip(problem.data, sel)]).astype(np.float64)
    c = np.concatenate([w[s] for (_, w), s in zip(problem.data, sel)]) / len(problem.data)
    return sel, t, c


def _rows(problem, sel, x, spp, seed):
    """The primal renders of every view at ``x`` over the loss's pixels, one row (P,)."""
    _, images, _ = problem.evaluate(x, 1.0, spp, seed)
    return np.concatenate([im[s] for im, s in zip(images, sel)]).astype(np.float64)


def cross_error(problem, x, spp, seed, exposure_free=False):
    """The unbiased error (:class:`CrossMSE`) of the true render at ``x``: two renders of ``spp``
    samples with independent seeds (``seed`` and ``seed + 5003``).
    """
    sel, t, c = _pixels(problem)
    a, b = _rows(problem, sel, x, spp, seed), _rows(problem, sel, x, spp, seed + 5003)
    return float(CrossMSE(a[None], b[None], t, c, exposure_free)(np.ones(1))[0])


def scan(problem, opts, check_spp):
    """Rank the training materials and choose Adam's starts (see the module docstring).

    Returns a dict: ``ranked`` ``[(error, index)]`` (every training material, scan estimate),
    ``starts`` ``[(label, x0 for Adam, x of the candidate)]`` (``opts.starts`` of them at most),
    ``candidates`` (every candidate checked: label, x, scan estimate, checked error) and
    ``time_s``.
    """
    t0 = time.perf_counter()
    m = problem.manifold
    sel, t, c = _pixels(problem)
    spp = max(1, int(opts.scan_spp) // 2)
    A = np.stack([_rows(problem, sel, m.latent[i], spp, opts.seed + 11) for i in range(m.n)])
    B = np.stack([_rows(problem, sel, m.latent[i], spp, opts.seed + 5014) for i in range(m.n)])
    obj = CrossMSE(A, B, t, c, opts.exposure)
    single = obj.batch(np.eye(m.n))[0]
    ranked = sorted(zip(single.tolist(), range(m.n)))
    bounds = latent.box(m)
    X, err = latent.scan(m, obj, 0.0, bounds, SCAN_POINTS, seed=opts.seed)
    k = max(4, 2 * int(opts.starts))
    with one_thread():
        runs = [
            latent.descend(m, obj, 0.0, x0, bounds, 100)
            for x0 in latent.start_points(m, ranked[0][1], X, err, k)
        ]
    cand = [
        ("blend scan", r["x"], r["objective"]) for r in sorted(runs, key=lambda r: r["objective"])
    ]
    cand += [("material " + m.names[i], m.latent[i], e) for e, i in ranked[:2]]
    checked = []
    for label, x, e in cand:
        if any(np.linalg.norm(x - y) < SAME_POINT * m.length_scale for _, y, _, _ in checked):
            continue
        checked.append(
            (
                label,
                np.asarray(x, dtype=np.float64),
                float(e),
                cross_error(problem, x, check_spp, opts.seed + 23, opts.exposure),
            )
        )
    checked.sort(key=lambda r: r[3])
    starts = []
    for label, x, _, _ in checked:
        if len(starts) == int(opts.starts):
            break
        if all(np.linalg.norm(x - y) >= 0.25 * m.length_scale for _, _, y in starts):
            starts.append((label, adam_start(m, x, ranked), x))
    return {
        "ranked": ranked,
        "starts": starts,
        "time_s": time.perf_counter() - t0,
        "candidates": [
            {"start": lab, "x": x.tolist(), "scan_error": e, "checked_error": ce}
            for lab, x, e, ce in checked
        ],
    }


def adam_start(manifold, x, ranked):
    """``x``, or a start near it when ``x`` sits on a training point (:func:`start_near`)."""
    w = np.asarray(manifold.weights(x)[1])
    i = int(np.argmax(w))
    return (
        start_near(manifold, i, ranked)
        if w[i] > AT_TRAINING_POINT
        else np.asarray(x, dtype=np.float64)
    )


def start_near(manifold, i, ranked, t=0.3):
    """A start near training material ``i``, off its training point (where the Shepard weights
    are flat): ``t`` of the way towards the best-ranked of its 3 latent neighbours, so that both
    materials' weights move with ``x`` (:func:`.ad.jitter` when it has no neighbour).
    """
    from ..plugin import ad

    d = np.linalg.norm(manifold.latent - manifold.latent[i], axis=1)
    d[i] = np.inf
    near = set(np.argsort(d)[:3].tolist())
    j = next((k for _, k in ranked if k in near and d[k] > 1e-6), None)
    if j is None:
        return ad.jitter(manifold.latent[i], manifold)
    return manifold.latent[i] + t * (manifold.latent[j] - manifold.latent[i])

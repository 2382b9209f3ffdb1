"""Which cross terms a full-GI basis holds, and their part of a blend.

With full-GI images ``F_i`` (material ``i`` alone) the blend ``base + sum_i w_i F_i`` is exact
at every training material; for paths with two vertices on the material, the blended
material ``f_w = sum_i w_i f_i`` gives ``L2(w) = sum_ij w_i w_j L2_ij`` (``L2_ij`` symmetric:
one vertex with ``i``, the other with ``j``), and for affine weights (``sum_i w_i = 1``)

    L2(w) = sum_i w_i L2_ii + sum_{i<j} w_i w_j C_ij,   C_ij = 2 L2_ij - L2_ii - L2_jj,

so adding the stored ``C_ij`` makes the blend exact for those paths (paper Sec. 5.2 leaves
this second-order term out). ``C_ii = 0``. A basis stores the generalisation to every level,
``C_ij = 4 R_m - 2 R_i - 2 R_j`` (``R``: ``L2+`` images, ``m`` the pair's midpoint material,
:mod:`mitsuba_manifold.render.integrators.multisplats`): for two-vertex paths the term above,
and for paths touching the material three or more times it makes the blend exact at the pair's
midpoint too (a quadratic through the ends and the midpoint of the segment). A pair is stored
when some point of the explored
region (the training points, the midpoints of every material and its latent neighbours,
random points of the latent box) blends both with ``|w_i w_j| >= tol`` (before pruning by
default: pruning only drops small weights and rescales the others by about ``1 +- prune``, so
the pairs of the pruned blends are among these, up to that rescaling).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

#: Smallest weight product of a stored pair.
CROSS_TOL = 1e-3
#: Latent neighbours of each material whose midpoints are explored.
NEIGHBOURS = 6


def explored_points(manifold, random=200, neighbours=NEIGHBOURS, seed=0) -> np.ndarray:
    """Latent points standing for the explored region: training points, midpoints of each with
    its ``neighbours`` nearest, and ``random`` uniform points of the latent bounding box.
    """
    lat = np.asarray(manifold.latent, dtype=np.float64)
    d = np.linalg.norm(lat[:, None] - lat[None], axis=-1)
    near = np.argsort(d, axis=1)[:, 1 : neighbours + 1]
    mids = 0.5 * (lat[:, None] + lat[near]).reshape(-1, lat.shape[1])
    lo, hi = lat.min(0), lat.max(0)
    box = np.random.default_rng(seed).uniform(lo, hi, size=(int(random), lat.shape[1]))
    return np.concatenate([lat, mids, box])


def select_pairs(
    manifold, names, tol=CROSS_TOL, prune=None, points=None
) -> tuple[list[tuple], dict[str, object]]:
    """Pairs ``(name_i, name_j)`` (manifold order, ``i < j``) among ``names`` whose weight
    product reaches ``tol`` at some explored point (:func:`explored_points`, or ``points``);
    ``prune``: of the weights first (:meth:`Manifold.prune`, slow: an exact table error per
    point), default none (see the module).

    Returns
    -------
    pairs : list of (str, str)
    stats : dict
        ``points``, ``pairs``, ``materials_per_point`` (median kept, or with weight ``>= tol``
        without pruning), ``left_weight`` (the
        largest ``|w_i w_j|`` of a pair not stored), ``products`` (each pair's largest ``|w_i w_j|``).
    """
    if not tol > 0:
        raise InputError(f"`tol` must be > 0, got {tol}")
    pts = explored_points(manifold) if points is None else np.atleast_2d(np.asarray(points, float))
    index = {n: k for k, n in enumerate(manifold.names)}
    wanted = np.zeros(manifold.n, bool)
    wanted[[index[n] for n in names]] = True
    best = np.zeros((manifold.n, manifold.n))
    kept = []
    for w in np.atleast_2d(manifold.weights(pts)[1]):
        if prune is None:
            keep = np.flatnonzero(np.abs(w) >= tol)
            wk = w[keep]
        else:
            keep, wk, _ = manifold.prune(w, prune)
        kept.append(len(keep))
        ok = wanted[keep]
        keep, wk = np.asarray(keep)[ok], np.asarray(wk)[ok]
        prod = np.abs(np.multiply.outer(wk, wk))
        best[np.ix_(keep, keep)] = np.maximum(best[np.ix_(keep, keep)], prod)
    iu = np.triu_indices(manifold.n, 1)
    chosen = best[iu] >= tol
    pairs = [(manifold.names[i], manifold.names[j]) for i, j, c in zip(*iu, chosen) if c]
    left = best[iu][~chosen]
    return pairs, {
        "points": len(pts),
        "pairs": len(pairs),
        "materials_per_point": float(np.median(kept)),
        "left_weight": float(left.max()) if left.size else 0.0,
        "products": [float(v) for v in best[iu][chosen]],
    }


def cross_weights(names, weights, pairs) -> tuple[np.ndarray, np.ndarray, float]:
    """``w_i w_j`` of the stored ``pairs`` (a dict ``(a, b) -> row``) among the kept materials
    ``names`` with ``weights``: ``(rows, products)``, and the largest product of a pair not stored.
    """
    rows, prods, missing = [], [], 0.0
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            p = float(weights[a] * weights[b])
            row = pairs.get((names[a], names[b]), pairs.get((names[b], names[a])))
            if row is None:
                missing = max(missing, abs(p))
            else:
                rows.append(row)
                prods.append(p)
    return np.array(rows, dtype=np.intp), np.array(prods, dtype=np.float32), missing

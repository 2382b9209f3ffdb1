"""Pruning a combination of tables by magnitude, with its exact L2 error.

A combination ``sum_i w_i table_i`` over N materials reads N tables; most weights
contribute little. What a weight contributes is ``|w_i| |table_i|``, not ``|w_i|``: a tiny
weight on a spiky table (specular peaks of 1e4) can matter more than a large one on a dull
table. :func:`prune` drops the materials of smallest contribution for as long as the table
changes by at most a given fraction of its L2 norm, the kept weights rescaled to the same
sum (so the combination stays affine). The change of every candidate is computed exactly
from the Gram matrix ``G = T T^T`` of the raw tables: with ``delta`` the change of the
weights, ``|delta^T T|^2 = delta^T G delta``.
"""

import numpy as np

from ..data import gram

#: Default pruning budget: largest relative L2 change of the table, for ``Manifold.prune``,
#: the ``manifold_brdf`` plugin, blends and the explorer.
DEFAULT_PRUNE = 1e-2


def raw_gram(tables, block=gram.BLOCK):
    """``T T^T`` (float64) of float32 tables ``(N, d)``, by blocks of values (:func:`gram.gram`)."""
    return gram.gram(tables, "raw", centre=False, block=block).S


def errors(w, kept, G):
    """Relative L2 change of ``w^T T`` for each row of the boolean matrix ``kept`` (M, N)."""
    kept = np.atleast_2d(kept)
    s = np.where(kept, w, 0.0).sum(axis=1)
    scale = np.divide(w.sum(), s, out=np.zeros_like(s), where=np.abs(s) > 0)
    delta = np.where(kept, w * scale[:, None], 0.0) - w
    num = np.maximum(((delta @ G) * delta).sum(axis=1), 0.0)   # BLAS, not einsum's loop
    den = float(w @ G @ w)
    if den > 0:
        return np.sqrt(num / den)
    return np.where(num > 0, np.inf, 0.0)


def error(w, keep, G):
    """:func:`errors` of keeping only the materials ``keep``."""
    kept = np.zeros(len(w), dtype=bool)
    kept[np.asarray(keep, dtype=int)] = True
    return float(errors(w, kept, G)[0])


def prune(w, G, budget):
    """Materials to keep so that the table changes by at most ``budget`` (relative L2).

    Drops materials in increasing order of contribution ``|w_i| sqrt(G_ii)`` (zero weights
    first); among the prefixes of that order, the longest whose exact error is within the
    budget. At least one material is kept.

    Returns
    -------
    keep : ndarray of int (sorted)
    w_kept : ndarray
        ``w[keep]`` rescaled to sum to ``sum(w)``.
    dropped : float
        ``sum |w_i|`` over the dropped materials.
    """
    n = len(w)
    order = np.argsort(np.abs(w) * np.sqrt(np.maximum(np.diag(G), 0.0)), kind="stable")
    k = int(np.count_nonzero(w == 0))
    if budget > 0:
        drop_first = np.tril(np.ones((n, n), dtype=bool), -1)   # row k drops order[:k]
        kept = ~drop_first[:, np.argsort(order)]
        ok = np.flatnonzero(errors(w, kept, G) <= budget)
        if ok.size:
            k = max(k, int(ok.max()))
    k = min(k, n - 1)
    keep = np.sort(order[k:])
    w_kept = w[keep]
    if abs(w_kept.sum()) > 0:
        w_kept = w_kept * (w.sum() / w_kept.sum())
    return keep, w_kept, float(np.abs(w).sum() - np.abs(w[keep]).sum())


def weighted_sum(rows, weights, size, chunk=1 << 18):
    """``sum_k weights[k] * rows[k]`` in float32, one read of each row.

    Loops over chunks of bins outside and rows inside, so the accumulator and the scaled
    chunk stay in cache and no full-size temporary is made.
    """
    rows = [np.asarray(r).reshape(-1) for r in rows]
    weights = np.asarray(weights, dtype=np.float32)
    out = np.zeros(size, dtype=np.float32)
    tmp = np.empty(min(chunk, size), dtype=np.float32)
    for start in range(0, size, chunk):
        acc = out[start:start + chunk]
        t = tmp[:len(acc)]
        for row, wk in zip(rows, weights):
            np.multiply(row[start:start + chunk], wk, out=t)
            acc += t
    return out

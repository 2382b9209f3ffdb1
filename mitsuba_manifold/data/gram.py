"""The Gram matrix of a stack of tables: the one place it is computed (paper Sec. 3).

The GPLVM sees the measured tables only through ``S = Z Z^T`` (``Z``: each material's table
in a feature space, minus the mean table); pruning needs ``G = T T^T`` of the raw tables and
the space metrics the uncentred ``F F^T`` of a feature space, and the "image" pruning rule
the cosine-weighted ``T diag(q) T^T`` (``q``: each bin's ``cos(theta_i) cos(theta_o) dw_i dw_o``).
:func:`gram` computes any of them in one pass over blocks of values: each block is converted
to float64 once (into a buffer its worker reuses), the products accumulate in float64 and
``Z`` (or ``F``) is never held in float64 as a whole. ``T diag(q) T^T`` is the product
``(T sqrt(q)) (T sqrt(q))^T`` of parts of a block (``q >= 0``; ``(T q) T^T`` otherwise).
Centring each block by its own column means (rather than centring the finished Gram matrix)
keeps the small entries accurate next to chrome-like peaks of 1e4.

The blocks' products are computed by worker threads (NumPy's products and element-wise
operations run without the interpreter lock), each on one BLAS thread
(:func:`~.._util.blas.one_thread`), and added up in the order of the blocks: the result
depends on the tables and ``block`` only, not on the number of workers.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..errors import FormatError

#: Feature transforms: ``raw`` (reflectance, the paper's), ``log`` (``log(1 + rho)``) and
#: ``coslog`` (``log(1 + rho cos(theta_i) cos(theta_o))``, needs the bins' cosines).
FEATURES = ("raw", "log", "coslog")
#: Values per block (columns of the ``(N, d)`` stack).
BLOCK = 1 << 16
#: Values per part of a block in the weighted product ``T diag(q) T^T``.
WEIGHTED_PART = 1 << 13
#: Most worker threads of one :func:`gram` (fewer on a machine of fewer cores): each holds a
#: float64 block ``(N, block)``.
MAX_WORKERS = 4


@dataclass
class Gram:
    """Result of :func:`gram`.

    Attributes
    ----------
    S : (N, N) float64
        ``Z Z^T`` of the mean-subtracted features (``centre=True``) or ``F F^T``.
    mean : (d,) float32 or None
        The mean table in the feature space (``centre=True`` only).
    raw : (N, N) float64 or None
        ``T T^T`` of the raw tables (``raw=True`` only).
    weighted : (N, N) float64 or None
        ``T diag(q) T^T`` of the raw tables (``weights=q`` only).
    sums : (N, 3) float64 or None
        ``sum_b q_b T_c(b)``: each table's channel ``c`` summed with the weights ``q``
        (``weights=q`` only; with the albedo weights, the albedos).
    """

    S: np.ndarray
    mean: np.ndarray = None
    raw: np.ndarray = None
    weighted: np.ndarray = None
    sums: np.ndarray = None


def transform(block, features, cos=None) -> np.ndarray:
    """Features of a block of table values (float64 ``(N, b)``), in place.

    ``cos``: the ``(b,)`` cosine weights of the block's bins (``coslog`` only).
    """
    if features == "raw":
        return block
    if features == "log":
        return np.log1p(np.maximum(block, 0.0, out=block), out=block)
    if features == "coslog":
        if cos is None:
            raise FormatError("`features` 'coslog' needs the cosine weights of the bins (`cos`)")
        np.maximum(block, 0.0, out=block)
        return np.log1p(np.multiply(block, cos, out=block), out=block)
    raise FormatError(f"`features` must be one of {FEATURES}, got {features!r}")


def workers_for(n_blocks) -> int:
    """Worker threads for ``n_blocks`` blocks: one per core the process may run on (at most
    :data:`MAX_WORKERS`), none idle.
    """
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_WORKERS, n_blocks))


def gram(
    tables, features="raw", centre=True, raw=False, cos=None, block=BLOCK, weights=None
) -> Gram:
    """Gram matrices of the rows of ``tables`` in one pass (see the module docstring).

    Parameters
    ----------
    tables : (N, d) array
        Tables as rows (float32, RGB-concatenated: ``d = 3 * bins``).
    features : {"raw", "log", "coslog"}
        Transform of the values before the products.
    centre : bool
        Subtract the mean table (in the feature space) first: ``S = Z Z^T`` and the mean.
    raw : bool
        Also ``T T^T`` of the untransformed tables, from the same blocks.
    cos : (bins,) array, optional
        Per-bin ``cos(theta_i) cos(theta_o)`` for ``coslog`` (the same for each channel).
    block : int
        Values per block.
    weights : (bins,) array, optional
        Per-bin weights ``q`` (the same for each channel): also ``T diag(q) T^T`` of the raw
        tables and each table's channels summed with the weights (:attr:`Gram.sums`), from
        the same blocks.

    Returns
    -------
    Gram
    """
    if features not in FEATURES:
        raise FormatError(f"`features` must be one of {FEATURES}, got {features!r}")
    from .._util.blas import one_thread

    n, d = tables.shape
    bins = d // 3
    block = int(block)
    mean = np.empty(d, dtype=np.float32) if centre else None
    weights = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if weights is not None and (weights.size != bins or bins == 0):
        raise FormatError(f"`weights` must hold one value per bin ({bins}), got {weights.size}")
    root = None if weights is None or np.any(weights < 0) else np.sqrt(weights)
    buffers = threading.local()  # each worker's float64 block and weighted part, reused

    def products(start) -> tuple:
        """The block at ``start``: its products ``(G, C, S)`` and weighted sums (None where
        not asked).
        """
        width = min(block, d - start)
        if getattr(buffers, "z", None) is None:
            buffers.z = np.empty(n * min(block, d))
            buffers.zw = np.empty(n * min(block, WEIGHTED_PART)) if weights is not None else None
        z = buffers.z[: n * width].reshape(n, width)
        np.copyto(z, tables[:, start : start + width], casting="unsafe")
        G = z @ z.T if raw else None
        bins_of = np.arange(start, start + width) % bins
        C, sums = None, None
        if weights is not None:  # each channel's part of the block with its bins' weights
            sums = np.zeros((n, 3))
            for c in range(start // bins, min(3, -(-(start + width) // bins))):
                lo, hi = max(start, c * bins) - start, min(start + width, (c + 1) * bins) - start
                sums[:, c] = z[:, lo:hi] @ weights[bins_of[lo:hi]]
            C = np.zeros((n, n))  # in parts of the block: the weighted copy is small
            for lo in range(0, width, WEIGHTED_PART):
                hi = min(width, lo + WEIGHTED_PART)
                zw = buffers.zw[: n * (hi - lo)].reshape(n, hi - lo)
                if root is not None:  # (T sqrt(q)) (T sqrt(q))^T: a syrk, half of (T q) T^T
                    np.multiply(z[:, lo:hi], root[bins_of[lo:hi]], out=zw)
                    C += zw @ zw.T
                else:
                    C += np.multiply(z[:, lo:hi], weights[bins_of[lo:hi]], out=zw) @ z[:, lo:hi].T
        z = transform(z, features, None if cos is None else cos[bins_of])
        if centre:
            m = z.mean(axis=0)
            mean[start : start + width] = m
            z -= m
        return G, C, z @ z.T, sums

    starts = range(0, d, block)
    S = np.zeros((n, n))
    G = np.zeros((n, n)) if raw else None
    C = None if weights is None else np.zeros((n, n))
    W = None if weights is None else np.zeros((n, 3))
    # Small products (N x block), one BLAS thread per worker: the workers keep the cores busy
    # between the products too, and no BLAS thread waits on another one's core.
    with one_thread():
        pool = ThreadPoolExecutor(workers_for(len(starts)), "gram")
        try:
            for g, c, s, w in pool.map(products, starts):  # summed in the order of the blocks
                S += s
                if raw:
                    G += g
                if c is not None:
                    C += c
                    W += w
        finally:  # on an error or Ctrl-C, only the blocks already started are finished
            pool.shutdown(cancel_futures=True)
    sym = lambda M: None if M is None else 0.5 * (M + M.T)
    return Gram(sym(S), mean, sym(G), sym(C), W)

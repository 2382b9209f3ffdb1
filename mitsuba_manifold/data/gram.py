"""The Gram matrix of a stack of tables: the one place it is computed (paper Sec. 3).

The GPLVM sees the measured tables only through ``S = Z Z^T`` (``Z``: each material's table
in a feature space, minus the mean table); pruning needs ``G = T T^T`` of the raw tables and
the space metrics the uncentred ``F F^T`` of a feature space, and the "image" pruning rule
the cosine-weighted ``T diag(q) T^T`` (``q``: each bin's ``cos(theta_i) cos(theta_o) dw_i dw_o``).
:func:`gram` computes any of them in one pass over blocks of values: each block is converted to float64 once, the
products accumulate in float64 and ``Z`` (or ``F``) is never held in float64 as a whole.
Centring each block by its own column means (rather than centring the finished Gram
matrix) keeps the small entries accurate next to chrome-like peaks of 1e4.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import FormatError

#: Feature transforms: ``raw`` (reflectance, the paper's), ``log`` (``log(1 + rho)``) and
#: ``coslog`` (``log(1 + rho cos(theta_i) cos(theta_o))``, needs the bins' cosines).
FEATURES = ("raw", "log", "coslog")
#: Values per block (columns of the ``(N, d)`` stack).
BLOCK = 1 << 16


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
    """

    S: np.ndarray
    mean: np.ndarray = None
    raw: np.ndarray = None
    weighted: np.ndarray = None


def transform(block, features, cos=None):
    """Features of a block of table values (float64 ``(N, b)``), in place where possible.

    ``cos``: the ``(b,)`` cosine weights of the block's bins (``coslog`` only).
    """
    if features == "raw":
        return block
    if features == "log":
        return np.log1p(np.maximum(block, 0.0, out=block), out=block)
    if features == "coslog":
        if cos is None:
            raise FormatError("`features` 'coslog' needs the cosine weights of the bins (`cos`)")
        return np.log1p(np.maximum(block, 0.0, out=block) * cos, out=block)
    raise FormatError(f"`features` must be one of {FEATURES}, got {features!r}")


def gram(tables, features="raw", centre=True, raw=False, cos=None, block=BLOCK, weights=None):
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
        tables, from the same blocks.

    Returns
    -------
    Gram
    """
    if features not in FEATURES:
        raise FormatError(f"`features` must be one of {FEATURES}, got {features!r}")
    from .._util.blas import one_thread

    n, d = tables.shape
    bins = d // 3
    mean = np.empty(d, dtype=np.float32) if centre else None
    S = np.zeros((n, n))
    G = np.zeros((n, n)) if raw else None
    C = None if weights is None else np.zeros((n, n))
    weights = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if weights is not None and weights.size != bins:
        raise FormatError(f"`weights` must hold one value per bin ({bins}), got {weights.size}")
    # Small products (N x block): one BLAS thread is as fast as two on an idle machine and
    # much faster when another process competes for the cores.
    with one_thread():
        for start in range(0, d, block):
            z = np.array(tables[:, start : start + block], dtype=np.float64)
            if raw:
                G += z @ z.T
            bins_of = np.arange(start, start + z.shape[1]) % bins
            if C is not None:
                C += (z * weights[bins_of]) @ z.T
            w = None if cos is None else cos[bins_of]
            z = transform(z, features, w)
            if centre:
                m = z.mean(axis=0)
                mean[start : start + block] = m
                z -= m
            S += z @ z.T
    sym = lambda M: None if M is None else 0.5 * (M + M.T)
    return Gram(sym(S), mean, sym(G), sym(C))

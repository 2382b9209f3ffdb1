"""The Gram matrix of a stack of tables: the one place it is computed (paper Sec. 3).

The GPLVM sees the measured tables only through ``S = Z Z^T`` (``Z``: each material's table
in a feature space, minus the mean table); pruning needs ``G = T T^T`` of the raw tables and
the space metrics the uncentred ``F F^T`` of a feature space, and the "image" pruning rule
the cosine-weighted ``T diag(q) T^T`` (``q``: each bin's ``cos(theta_i) cos(theta_o) dw_i dw_o``).
:func:`gram` computes any of them in one pass over chunks of columns: each chunk is converted
to float64 once into a buffer small enough to stay in the processor's cache while it is
transformed, centred and multiplied, the products (BLAS ``syrk`` through NumPy's ``z @ z.T``)
accumulate in float64, and ``Z`` (or ``F``) is never held in float64 as a whole. Centring
each chunk by its own column means (rather than centring the finished Gram matrix) keeps the
small entries accurate next to chrome-like peaks of 1e4.

The chunks are shared out in contiguous runs among worker threads (NumPy's products and
element-wise operations run without the interpreter lock), each on one BLAS thread
(:func:`~.._util.blas.one_thread`) with its own sums, added up in worker order at the end: the
result depends on the tables, ``block`` and the number of workers only.
"""

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..errors import FormatError

#: Feature transforms: ``raw`` (reflectance, the paper's), ``log`` (``log(1 + rho)``) and
#: ``coslog`` (``log(1 + rho cos(theta_i) cos(theta_o))``, needs the bins' cosines).
FEATURES = ("raw", "log", "coslog")
#: Default ``block`` of :func:`gram`: None, the columns of a chunk of :data:`CHUNK_BYTES`.
BLOCK = None
#: Bytes of one float64 chunk ``(N, block)`` when ``block`` is None: it stays in a core's cache.
CHUNK_BYTES = 1 << 22
#: Most worker threads of one :func:`gram` (fewer on a machine of fewer cores).
MAX_WORKERS = 8


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
        ``sum_b q_b T_c(b)``: each table's channels ``c`` summed with the weights ``q``
        (``weights=q`` only; with the albedo weights, the albedos).
    """

    S: np.ndarray
    mean: np.ndarray = None
    raw: np.ndarray = None
    weighted: np.ndarray = None
    sums: np.ndarray = None


def transform(block, features, cos=None):
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


def chunks(d, bins, block):
    """``(start, stop)`` column ranges of at most ``block`` values, none across a channel's end
    (a multiple of ``bins``), so that each chunk's bins are one slice ``start % bins ...``.
    """
    edges = sorted({0, d} | ({bins, 2 * bins} if 0 < bins < d else set()))
    return [
        (s, min(hi, s + block)) for lo, hi in zip(edges, edges[1:]) for s in range(lo, hi, block)
    ]


def workers_for(n_chunks):
    """Worker threads for ``n_chunks`` chunks: one per core the process may run on (at most
    :data:`MAX_WORKERS`), none idle.
    """
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_WORKERS, n_chunks))


class _Sums:
    """One worker's running sums over its chunks (see :func:`gram`)."""

    def __init__(self, n, raw, weighted):
        self.S = np.zeros((n, n))
        self.G = np.zeros((n, n)) if raw else None
        self.C = np.zeros((n, n)) if weighted else None
        self.sums = np.zeros((n, 3)) if weighted else None


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
        Also ``T T^T`` of the untransformed tables, from the same chunks.
    cos : (bins,) array, optional
        Per-bin ``cos(theta_i) cos(theta_o)`` for ``coslog`` (the same for each channel).
    block : int, optional
        Values per chunk (None: :data:`CHUNK_BYTES` of float64 per chunk).
    weights : (bins,) array, optional
        Per-bin weights ``q`` (the same for each channel): also ``T diag(q) T^T`` of the raw
        tables and their channels' ``q``-weighted sums, from the same chunks.

    Returns
    -------
    Gram
    """
    if features not in FEATURES:
        raise FormatError(f"`features` must be one of {FEATURES}, got {features!r}")
    from .._util.blas import one_thread

    n, d = tables.shape
    bins = d // 3
    weights = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if weights is not None and weights.size != bins:
        raise FormatError(f"`weights` must hold one value per bin ({bins}), got {weights.size}")
    if (weights is not None or cos is not None) and d != 3 * bins:
        raise FormatError(
            f"`tables` rows of {d} values are not 3 channels of bins; pass RGB-concatenated tables"
        )
    if block is None:
        block = max(256, CHUNK_BYTES // (8 * max(n, 1)))
    # (T sqrt(q)) (T sqrt(q))^T is a syrk, half the work of (T q) T^T; negative weights need the latter.
    root = None if weights is None or np.any(weights < 0) else np.sqrt(weights)
    mean = np.empty(d, dtype=np.float32) if centre else None
    parts = chunks(d, bins, int(block))
    n_workers = workers_for(len(parts))
    runs = np.array_split(np.arange(len(parts)), n_workers)

    def work(run):
        acc = _Sums(n, raw, weights is not None)
        size = max((parts[i][1] - parts[i][0] for i in run), default=0)
        buf = np.empty(n * size)
        scaled = np.empty(n * size) if weights is not None else None
        for i in run:
            start, stop = parts[i]
            k, off = stop - start, start % bins if bins else 0
            z = buf[: n * k].reshape(n, k)
            np.copyto(z, tables[:, start:stop])
            if raw:
                acc.G += z @ z.T
            if weights is not None:
                w = weights[off : off + k]
                acc.sums[:, start // bins] += z @ w
                zq = scaled[: n * k].reshape(n, k)
                if root is not None:
                    acc.C += np.multiply(z, root[off : off + k], out=zq) @ zq.T
                else:
                    acc.C += np.multiply(z, w, out=zq) @ z.T
            z = transform(z, features, None if cos is None else cos[off : off + k])
            if centre:
                m = z.mean(axis=0)
                mean[start:stop] = m
                z -= m
            acc.S += z @ z.T
        return acc

    # Each worker on one BLAS thread: its products are small (N x block), and a worker's
    # thread is its core's.
    with one_thread():
        if n_workers == 1:
            done = [work(runs[0])]
        else:
            with ThreadPoolExecutor(n_workers, thread_name_prefix="gram") as pool:
                done = list(pool.map(work, runs))

    def total(field):
        parts_ = [getattr(a, field) for a in done]
        if parts_[0] is None:
            return None
        out = parts_[0]
        for p in parts_[1:]:
            out += p
        return out if field == "sums" else 0.5 * (out + out.T)

    return Gram(total("S"), mean, total("G"), total("C"), total("sums"))

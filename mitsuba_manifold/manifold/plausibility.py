"""Physical plausibility of a combination of tables, and the best plausible one beyond the data.

A material ``sum_i w_i table_i`` with weights outside the simplex (some ``w_i < 0``) can go
beyond the measured materials: brighter, shinier, more saturated. It stays a plausible BRDF
while (1) no bin is negative and (2) its directional albedo ``a(theta_i) = int f cos(theta_o)
dw_o`` is at most 1 at every incidence. Both are linear in the weights:
:class:`DirectionalAlbedo` integrates a table over outgoing directions at a set of
incidences (a fixed quadrature, a gather of bins), so ``a(w) = sum_i w_i a_i``.

:func:`plausible_weights` finds affine weights (summing to 1) over a few candidate materials
that minimise the RMS of ``log(1 + rho) - log(1 + rho_target)`` (the projection's error,
:mod:`.projection`) under both conditions, in three steps: a constrained least-squares
solve (SLSQP) with non-negativity at the searched bins and the albedo bound at the
quadrature's incidences; the bins of the whole table that the solve left negative added
as constraints and solved again (a few rounds); and last the exact guarantee: the result
is moved toward a plausible start (a convex combination) by the largest step that keeps
every bin of the full table non-negative and every directional albedo at most 1 (both
conditions are linear, so that step is a ratio per bin).

:class:`StepLimit` holds the default interpolant's continuation beyond the data to a
plausible material: the largest step from convex weights along a direction of affine weights
that a cheap sufficient condition (ratios of pairs of tables) and the albedo bound allow.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.optimize

from .._util.atomic import atomic_write
from .._util.cache import key_hash
from .._util.float32 import weights32
from ..data import merl
from ..data.database import database_cache

if TYPE_CHECKING:
    from typing import Any


#: Incidences of the directional albedo bound (degrees, midpoints up to 89).
N_INCIDENCE = 16
#: Outgoing quadrature: elevations x azimuths (midpoints).
N_THETA, N_PHI = 24, 48


class DirectionalAlbedo:
    """Directional albedo of tables of resolution ``dims`` at :data:`N_INCIDENCE` incidences.

    ``a(theta_i) = int f(theta_i, w_o) cos(theta_o) dw_o`` by the midpoint rule over
    ``N_THETA x N_PHI`` outgoing directions, each looked up in its MERL bin; ``theta_i``
    (radians) replaces the default incidences.
    """

    def __init__(
        self, dims, n_incidence=N_INCIDENCE, n_theta=N_THETA, n_phi=N_PHI, theta_i=None
    ) -> None:
        self.dims = tuple(int(v) for v in dims)
        self.theta_i = (
            (np.arange(n_incidence) + 0.5) / n_incidence * np.radians(89.0)
            if theta_i is None
            else np.asarray(theta_i, dtype=np.float64)
        )
        to = (np.arange(n_theta) + 0.5) / n_theta * (np.pi / 2)
        po = (np.arange(n_phi) + 0.5) / n_phi * (2 * np.pi)
        TO, PO = np.meshgrid(to, po, indexing="ij")
        wo = np.stack([np.sin(TO) * np.cos(PO), np.sin(TO) * np.sin(PO), np.cos(TO)], -1).reshape(
            -1, 3
        )
        self.weight = (
            (np.cos(TO) * np.sin(TO)).reshape(-1) * (np.pi / 2 / n_theta) * (2 * np.pi / n_phi)
        )
        idx = []
        for t in self.theta_i:
            wi = np.broadcast_to(np.array([np.sin(t), 0.0, np.cos(t)]), wo.shape)
            idx.append(merl.flat_index(wi, wo, self.dims))
        self.index = np.array(idx)  # (n_incidence, n_out)
        self.bins = int(np.prod(self.dims))

    def of(self, tables) -> np.ndarray:
        """Directional albedos ``(M, 3, n_incidence)`` of flat RGB tables ``(M, 3 * bins)`` (or one)."""
        tables = np.atleast_2d(tables)
        out = np.empty((len(tables), 3, len(self.theta_i)))
        for c in range(3):
            vals = tables[:, c * self.bins + self.index]  # (M, n_inc, n_out)
            out[:, c] = vals.astype(np.float64) @ self.weight
        return out


@dataclass
class Plausible:
    """:func:`plausible_weights`: the weights over all training materials and what they reach.

    Attributes
    ----------
    weights : (N,) ndarray
        Affine weights (sum 1), zero outside the candidates; some may be negative.
    error : float
        RMS of ``log(1 + rho) - log(1 + rho_target)`` over all bins.
    min_value : float
        Smallest value of the combined table (>= 0).
    max_albedo : float
        Largest directional albedo over incidences and channels (<= 1).
    shrink : float
        Share of the constrained solve kept by the final guarantee (1: none needed).
    """

    weights: np.ndarray
    error: float
    min_value: float
    max_albedo: float
    shrink: float


def _log_rms(blend, y) -> float:
    r = np.log1p(np.maximum(blend, 0.0)) - y
    return float(np.sqrt(np.mean(r * r, dtype=np.float64)))


#: The constrained solve of :func:`plausible_weights`: solves, constraints added per solve,
#: iterations per solve, non-negativity constraints of the first solve.
ROUNDS, MAX_ADD, MAX_ITER, N_CONSTRAINED = 3, 2000, 100, 1024


def plausible_weights(
    tables,
    target,
    candidates,
    start,
    albedo,
    *,
    bins,
    affine=True,
) -> Plausible:
    """Best plausible affine combination of the ``candidates`` rows of ``tables`` for ``target``.

    Parameters
    ----------
    tables : (N, d) array
        Training tables (float32, flat RGB).
    target : (d,) array
    candidates : array of int
        Rows combined.
    start : (N,) array
        Convex weights of a plausible material (the latent projection's): the solve starts
        there and the final guarantee moves toward it.
    albedo : DirectionalAlbedo
    bins : array of int
        Searched bins (the objective); :data:`N_CONSTRAINED` of them, evenly spaced, are the
        first non-negativity constraints; each of at most :data:`ROUNDS` solves (SLSQP,
        :data:`MAX_ITER` iterations) adds the :data:`MAX_ADD` most negative bins of the whole
        table to them.
    affine : bool
        Weights summing to 1 (else any sum: the combination may also scale the tables).

    Returns
    -------
    Plausible
    """
    cand = np.asarray(candidates)
    n = len(tables)
    T = tables[np.ix_(cand, bins)].astype(np.float64)  # (k, b)
    y = np.log1p(np.maximum(np.asarray(target, dtype=np.float64)[bins], 0.0))
    A = albedo.of(tables[cand]).reshape(len(cand), -1)  # (k, 3 n_inc)
    w0 = np.asarray(start, dtype=np.float64)[cand]
    w0 = w0 / w0.sum() if w0.sum() > 0 else np.full(len(cand), 1.0 / len(cand))
    scale = 1.0 / len(bins)

    def f(w) -> tuple[float, Any]:
        blend = w @ T
        pos = np.maximum(blend, 0.0)
        r = np.log1p(pos) - y
        g = np.where(blend > 0, 2.0 * r / (1.0 + pos), 0.0) * scale
        return float(r @ r) * scale, T @ g

    extra = T[:, :: max(1, len(bins) // N_CONSTRAINED)]
    w = w0.copy()
    full_rows = tables[cand]
    for _ in range(ROUNDS):
        C = extra
        cons = [
            {"type": "ineq", "fun": lambda w, C=C: w @ C, "jac": lambda w, C=C: C.T},
            {"type": "ineq", "fun": lambda w: 1.0 - w @ A, "jac": lambda w: -A.T},
        ]
        if affine:
            cons.append(
                {"type": "eq", "fun": lambda w: w.sum() - 1.0, "jac": lambda w: np.ones_like(w)}
            )
        res = scipy.optimize.minimize(
            f,
            w,
            jac=True,
            method="SLSQP",
            constraints=cons,
            options={"maxiter": MAX_ITER, "ftol": 1e-12},
        )
        w = res.x if np.all(np.isfinite(res.x)) else w
        full = weights32(w) @ full_rows
        neg = np.flatnonzero(full < 0)
        if len(neg) == 0:
            break
        worst = neg[np.argsort(full[neg])[:MAX_ADD]]
        extra = np.concatenate([extra, full_rows[:, worst].astype(np.float64)], axis=1)
    w, full, s = _step_back(w, w0, full_rows, A)
    weights = np.zeros(n)
    weights[cand] = w
    t_log = np.log1p(np.maximum(np.asarray(target, dtype=np.float32), 0.0))
    return Plausible(weights, _log_rms(full, t_log), float(full.min()), float((w @ A).max()), s)


def largest_plausible_step(base, full, albedo_start, albedo_end) -> float:
    """The largest ``s`` in [0, 1] for which ``start + s (end - start)`` has no negative value and
    no directional albedo above 1, ``start`` being plausible: ``base``, ``full`` the combined
    tables' values and ``albedo_start``, ``albedo_end`` their albedos at the two ends (linear in
    ``s``, so each bound is where one value reaches 0 or one albedo reaches 1).
    """
    s = 1.0
    neg = full < 0
    if neg.any():
        s = min(s, float(np.min(base[neg] / (base[neg] - full[neg]))))
    over = albedo_end > 1.0
    if over.any():
        s = min(
            s,
            float(np.min((1.0 - albedo_start[over]) / (albedo_end[over] - albedo_start[over]))),
        )
    return s


def _step_back(w, w0, full_rows, A) -> tuple[Any, Any, float]:
    """The exact guarantee of :func:`plausible_weights`: ``w0 + s (w - w0)`` with the largest
    ``s`` in [0, 1] for which no bin of the combination is negative (in float32, as rendered)
    and no directional albedo exceeds 1; returns the weights, the combination and ``s``.
    """
    base = weights32(w0) @ full_rows
    full = weights32(w) @ full_rows
    s = largest_plausible_step(base, full, w0 @ A, w @ A)
    s = max(0.0, s * (1 - 1e-6) if s < 1.0 else 1.0)
    w_end = w
    for _ in range(40):  # rounding of the float32 products: step back until no value is below 0
        w = w0 + s * (w_end - w0)
        full = weights32(w) @ full_rows
        if full.min() >= 0 or s == 0.0:
            break
        s = 0.0 if s < 1e-3 else s * 0.99
    return w, full, s


#: Relative slack of :class:`StepLimit`'s bound: room for the float32 rounding of a rendered table.
BOUND_SLACK = 1e-3
#: Convex weights above this share are summed by :class:`StepLimit` (the others only add).
SUPPORT_FLOOR = 1e-2


#: Tables read at once for their albedos and ratios (memory: two copies of this many tables).
TABLE_BLOCK = 8


class StepLimit:
    """The largest step ``s`` in [0, 1] for which ``w + s e`` is a plausible material.

    ``w`` are convex weights (a plausible material) and ``e`` a direction of affine weights
    (summing to 0). The table ``sum_i (w_i + s e_i) table_i`` must have no negative bin and
    its directional albedo must stay at most 1 (:class:`DirectionalAlbedo`; linear in ``s``,
    so its limit is a ratio). Non-negativity is held by a sufficient condition that needs no
    pass over the bins per point: with the domination ratios ``R_ij = min_b table_i[b] /
    table_j[b]`` (over the bins where ``table_j > 0``, so ``table_i >= R_ij table_j`` in every
    bin), a combination with coefficients ``c`` has no negative bin when, for each ``j`` with
    ``c_j < 0``,

        (1 - BOUND_SLACK) sum_{i: c_i > 0} c_i R_ij >= sum_{k: c_k < 0} |c_k|

    (the positive tables cover each negative one bin by bin, in proportion to its share of the
    negative weight). It is exact for two materials, never lets a negative bin through, and
    costs a product of small matrices per point; the largest ``s`` meeting it is found by
    bisection (it holds at ``s = 0``). The positive tables counted are those with ``e_i != 0``
    or ``w_i`` above :data:`SUPPORT_FLOOR` (the others only add); a ratio ``R_ij`` is computed
    (one pass over two tables) the first time a point needs it, and kept (with :attr:`store`,
    across processes); the tables themselves are read a block at a time and not kept.
    :data:`BOUND_SLACK` leaves room for the float32 rounding of a rendered table.

    Parameters
    ----------
    rows : callable
        ``rows(indices)``: the training tables of those materials, each ``(3 * bins,)`` (float32,
        flat RGB); called only for the materials a point sums, a few at a time.
    n : int
        The number of training materials.
    dims : tuple of int
        The tables' resolution.
    store : str or callable, optional
        File that keeps the ratios and albedos computed so far across processes (``.npz``,
        read at the first :meth:`step`, written atomically after a :meth:`step` that added
        some): name it by the tables' content (:func:`store_path`), since its values depend on
        nothing else. A callable is asked for the path at the first :meth:`step` (so that
        making a :class:`StepLimit`, at every manifold load, touches no file).
    """

    def __init__(self, rows, n, dims, store=None) -> None:
        self._rows = rows
        self.n = int(n)
        self.dims = tuple(int(v) for v in dims)
        self._albedo = np.full((self.n, 3 * N_INCIDENCE), np.nan)
        self._ratio: dict = {}
        self._store = store
        self.store = None  # its path, once the first step has asked for it
        self._stored = 0
        self._lock = threading.Lock()  # one step at a time: its store and caches are shared

    def _read_store(self) -> None:
        """The ratios and albedos kept in the store (a missing or foreign file: none)."""
        store, self._store = self._store, None
        if callable(store):
            store = store()
        self.store = None if store is None else os.fspath(store)
        if self.store is None or not os.path.exists(self.store):
            return
        try:
            with np.load(self.store) as f:
                ratio, albedo = f["ratio"], f["albedo"]
        except (OSError, ValueError, KeyError):
            return  # unreadable: computed again and written anew
        if ratio.shape != (self.n, self.n) or albedo.shape != self._albedo.shape:
            return
        i, j = np.nonzero(np.isfinite(ratio))
        self._ratio.update(zip(zip(i.tolist(), j.tolist()), ratio[i, j].tolist()))
        self._albedo = albedo.astype(np.float64)
        self._stored = self._known()

    def _known(self) -> int:
        return len(self._ratio) + int(np.isfinite(self._albedo[:, 0]).sum())

    def _write_store(self) -> None:
        if self.store is None or self._known() == self._stored:
            return
        ratio = np.full((self.n, self.n), np.nan)
        for (i, j), r in self._ratio.items():
            ratio[i, j] = r
        atomic_write(self.store, lambda f: np.savez(f, ratio=ratio, albedo=self._albedo))
        self._stored = self._known()

    def _tables(self, idx):
        """The tables of materials ``idx`` (float32), read in blocks of :data:`TABLE_BLOCK`."""
        idx = [int(i) for i in idx]
        for s in range(0, len(idx), TABLE_BLOCK):
            for t in self._rows(idx[s : s + TABLE_BLOCK]):
                yield np.asarray(t, dtype=np.float32)

    def albedos(self, idx) -> np.ndarray:
        """Directional albedos of materials ``idx``, ``(len(idx), 3 n_incidence)``."""
        idx = np.asarray(idx, dtype=int)
        missing = idx[np.isnan(self._albedo[idx, 0])]
        if len(missing):
            da = DirectionalAlbedo(self.dims)
            for s in range(0, len(missing), TABLE_BLOCK):
                block = missing[s : s + TABLE_BLOCK]
                self._albedo[block] = da.of(np.stack(list(self._tables(block)))).reshape(
                    len(block), -1
                )
        return self._albedo[idx]

    def ratios(self, rows, cols) -> np.ndarray:
        """``R_ij = min_b table_i[b] / table_j[b]`` for the pairs ``(rows, cols)`` (same shape)."""
        rows, cols = np.broadcast_arrays(np.asarray(rows), np.asarray(cols))
        pairs = list(zip(rows.ravel().tolist(), cols.ravel().tolist()))
        todo: dict = {}
        for i, j in sorted(set(p for p in pairs if p not in self._ratio)):
            if i == j:
                self._ratio[i, j] = 1.0
            else:
                todo.setdefault(j, set()).add(i)
        cols = sorted(todo)
        for s in range(0, len(cols), TABLE_BLOCK):  # a block of columns' divisors at a time
            block = cols[s : s + TABLE_BLOCK]
            divisors = []
            for j, tj in zip(block, self._tables(block)):
                on = tj > 0
                divisors.append((j, on, 1.0 / tj[on]))
            wanted = sorted({i for j in block for i in todo[j]})
            for i, ti in zip(wanted, self._tables(wanted)):  # each row table read once a block
                for j, on, inv in divisors:
                    if i in todo[j]:
                        r = float((ti[on] * inv).min()) if len(inv) else 1e30
                        self._ratio[i, j] = min(r, 1e30)
        return np.asarray([self._ratio[p] for p in pairs], dtype=np.float64).reshape(rows.shape)

    def step(self, w, e, iterations=40) -> np.ndarray:
        """The largest plausible step ``s`` (M,) of ``w + s e``; ``w`` convex (M, N), ``e`` (M, N).

        Tables are read a block at a time and let go at once (the albedos and ratios are kept).
        Threads take turns (the explorer's frames, maps and walks share one limit).
        """
        with self._lock:
            if self._store is not None:
                self._read_store()
            try:
                return self._step(np.atleast_2d(w), np.atleast_2d(e), iterations)
            finally:
                self._write_store()

    def _step(self, w, e, iterations) -> np.ndarray:
        # albedos: of the materials summed; the others' share counted at the most, 1
        summed = (w > SUPPORT_FLOOR) | (e != 0)
        idx = np.flatnonzero(summed.any(axis=0))
        A = self.albedos(idx)
        ws = np.where(summed[:, idx], w[:, idx], 0.0)
        a0 = ws @ A + (1.0 - ws.sum(axis=1))[:, None]
        da = e[:, idx] @ A
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(da > 0, (1.0 - a0) / da, np.inf)
        hi = np.clip(ratio.min(axis=1), 0.0, 1.0)
        lo = hi.copy()
        down = np.flatnonzero((e < 0).any(axis=1))  # points with a table that may go negative
        if len(down) == 0:
            return lo
        # padded per group of points of like sizes (support and negative tables, each rounded up
        # to a power of 2): one point with many tables does not pad every other point to its size
        sizes = [np.ceil(np.log2(np.maximum(m[down].sum(axis=1), 1))) for m in (summed, e < 0)]
        group = sizes[0] * 64 + sizes[1]
        for g in np.unique(group):
            rows = down[group == g]
            lo[rows] = self._bisect(w[rows], e[rows], summed[rows], hi[rows], iterations)
        return lo

    def _bisect(self, w, e, summed, hi, iterations) -> np.ndarray:
        """The largest step in ``[0, hi]`` (to ``hi / 2^iterations``) that leaves no table of the
        points ``w + s e`` negative (each table ``j`` covered by the ratios ``R_ij`` of those summed).
        """
        # each point's own tables: those it sums (support) and those that may go negative
        sup, sup_on = _rows_of(summed)
        down, down_on = _rows_of(e < 0)
        pair_on = sup_on[:, :, None] & down_on[:, None, :]
        Rp = np.zeros(pair_on.shape)
        Rp[pair_on] = self.ratios(
            np.broadcast_to(sup[:, :, None], pair_on.shape)[pair_on],
            np.broadcast_to(down[:, None, :], pair_on.shape)[pair_on],
        )
        Rp *= 1.0 - BOUND_SLACK  # (M, r, k)
        ws, es = [np.where(sup_on, np.take_along_axis(a, sup, 1), 0.0) for a in (w, e)]
        wd, ed = [np.where(down_on, np.take_along_axis(a, down, 1), 0.0) for a in (w, e)]

        def ok(s):
            cover = np.einsum("mr,mrk->mk", np.maximum(ws + s[:, None] * es, 0.0), Rp)
            owed = np.maximum(-(wd + s[:, None] * ed), 0.0)
            return ((owed <= 0) | (cover >= owed.sum(axis=1, keepdims=True))).all(axis=1)

        good = ok(hi)
        lo, top = np.where(good, hi, 0.0), hi.copy()
        todo = ~good
        for _ in range(iterations):
            if not todo.any():
                break
            mid = 0.5 * (lo + top)
            fine = ok(mid)
            lo = np.where(todo & fine, mid, lo)
            top = np.where(todo & ~fine, mid, top)
        return lo


def _rows_of(mask) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``mask`` (M, N), the columns where it holds, padded: ``(M, r)`` indices and
    whether each is one (``r`` the most of any row, at least 1).
    """
    r = max(int(mask.sum(axis=1).max()), 1)
    idx = np.argsort(~mask, axis=1, kind="stable")[:, :r]
    return idx, np.take_along_axis(mask, idx, 1)


def store_path(hashes, dims, database) -> str | None:
    """Where :class:`StepLimit` keeps the ratios and albedos of the tables with content hashes
    ``hashes`` at resolution ``dims``: ``plausibility-<key>.npz`` in the cache folder of
    ``database`` (:func:`~mitsuba_manifold.data.database.database_cache`, where its tables are
    cached); None without a hash for every table or a cache folder.
    """
    if not hashes or not all(isinstance(h, str) and h for h in hashes) or database is None:
        return None
    folder = database_cache(database)
    if folder is None:
        return None
    key = key_hash("x".join(str(int(v)) for v in dims), *hashes, length=32)
    return os.path.join(folder, f"plausibility-{key}.npz")

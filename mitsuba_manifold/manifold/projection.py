"""Projection of a measured table onto the manifold: the latent point whose material is closest.

The error is the RMS over bins of ``log(1 + rho(x)) - log(1 + rho)`` (``rho(x)``: the
interpolated table, clamped at 0 as the plugin does), the usual perceptual-ish distance
between MERL tables. On a random subsample of bins, points along the segments between the
few training materials closest to the target, and from each of them toward its nearest
latent neighbours (the blends the space offers around it), are scored in one batch; the
best of them start L-BFGS-B with the analytic gradient (the interpolant's Jacobian ``dw/dx``). The result
is measured on all bins and never worse than the closest training material itself.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from .._util.float32 import weights32
from ..data.sources import material_table
from ..errors import InputError
from .plausibility import DirectionalAlbedo, plausible_weights

#: Bins used by the search (the report uses all of them).
SEARCH_BINS = 1 << 15
#: Candidates of the plausible combination beyond the data: this many closest training materials.
BEYOND_CANDIDATES = 30


@dataclass
class Projection:
    """Best latent point for a table.

    Attributes
    ----------
    x : (q,) ndarray
        Latent point.
    error : float
        RMS over all bins of ``log(1 + rho(x)) - log(1 + rho)``.
    weights : (N,) ndarray
        Interpolation weights at ``x``.
    nearest : str
        The training material closest to the table.
    nearest_error : float
        Its error (same measure).
    negative_fraction : float
        Fraction of the interpolated table's values below 0 at ``x`` (clamped in the error).
    beyond : plausibility.Plausible or None
        With ``beyond=True`` (:func:`beyond`): the best plausible combination of the training
        tables, weights outside the interpolant's (affine or scaled, some negative), its
        error, smallest value and largest directional albedo. None otherwise.
    """

    x: np.ndarray
    error: float
    weights: np.ndarray
    nearest: str
    nearest_error: float
    negative_fraction: float
    beyond: object = None

    @property
    def best_error(self):
        """The smaller of :attr:`error` and the plausible combination's (when computed)."""
        return self.error if self.beyond is None else min(self.error, self.beyond.error)

    def to_json(self, table, names, top=5) -> dict:
        """The projection of ``table`` as JSON values: the point, its error, the nearest
        training material's, the negative fraction and the ``top`` largest weights (by
        magnitude, none that is 0) by the training materials' ``names``.
        """
        order = sorted(range(len(names)), key=lambda i: -abs(self.weights[i]))[:top]
        return {
            "table": table,
            "x": self.x.tolist(),
            "error": self.error,
            "nearest": self.nearest,
            "nearest_error": self.nearest_error,
            "negative_fraction": self.negative_fraction,
            "weights": {names[i]: float(self.weights[i]) for i in order if self.weights[i] != 0},
        }


def as_table(table, d, dims=None):
    """``table`` (array, or a material file or ``SET:NAME``, :func:`.sources.material_table`,
    tabulated at ``dims``) as a flat float32 array of ``d`` values.
    """
    if isinstance(table, (str, os.PathLike)):
        table = material_table(table, dims, what="table to project")[1]
    table = np.asarray(table, dtype=np.float32).reshape(-1)
    if table.size != d:
        raise InputError(
            f"table to project has {table.size} values; this manifold's tables have "
            f"{d} (dims {dims} x RGB)"
        )
    return table


def log_rms(blend, target_log):
    """RMS of ``log(1 + max(blend, 0)) - target_log`` along the last axis (float64 sums)."""
    r = np.log1p(np.maximum(blend, 0.0)) - target_log
    return np.sqrt(np.einsum("...i,...i->...", r, r, dtype=np.float64) / r.shape[-1])


def search_bins(d, n=SEARCH_BINS, seed=0):
    """Sorted random subset of ``n`` of ``d`` bins (all of them if ``d <= n``)."""
    if d <= n:
        return np.arange(d)
    return np.sort(np.random.default_rng(seed).choice(d, n, replace=False))


def candidates(latent, order, n_latent=6, steps=19):
    """Starting points: along the segments between the latent points ``order`` (the closest
    materials in table space) and from each of them toward its ``n_latent`` nearest latent
    neighbours, plus the points themselves.
    """
    t = np.linspace(0.05, 0.95, steps)[:, None]
    ends = [(a, b) for k, a in enumerate(order) for b in order[k + 1 :]]
    for a in order:
        near = np.argsort(np.linalg.norm(latent - latent[a], axis=1))[1 : n_latent + 1]
        ends += [(a, b) for b in near if (a, b) not in ends and (b, a) not in ends]
    return np.vstack([latent[a] + t * (latent[b] - latent[a]) for a, b in ends] + [latent[order]])


@dataclass(frozen=True)
class SearchOptions:
    """How :func:`project` searches the latent space.

    Parameters
    ----------
    n_nearest : int
        Candidate starts lie on the segments between this many closest training materials
        (closest on the searched bins) and from each of them toward its ``n_latent`` nearest
        latent neighbours.
    n_starts : int
        The best-scoring candidates that start L-BFGS-B.
    max_iter : int
        L-BFGS-B iterations of each start.
    n_latent : int
        Latent neighbours of each closest material that candidate segments lead to.
    """

    n_nearest: int = 4
    n_starts: int = 3
    max_iter: int = 100
    n_latent: int = 6


def project(
    interpolant,
    tables,
    target,
    names=None,
    bins=None,
    rows=None,
    *,
    search=None,
):
    """Best latent point of ``target`` on the manifold of ``interpolant`` over ``tables``.

    Parameters
    ----------
    interpolant : interpolant.Interpolant
        Weights ``w(x)`` and Jacobian over the N training materials.
    tables : (M, d) array
        Tables (float32); ``rows`` of them (default all) are the training tables, in the
        interpolant's order. Never copied.
    target : (d,) array
        The table to project.
    names : list of str, optional
        Material names (for :attr:`Projection.nearest`).
    bins : array of int, optional
        Bins searched (default :func:`search_bins`).
    rows : array of int, optional
        Rows of ``tables`` that are the training materials (default: all).
    search : SearchOptions, optional
        Starts and iterations of the latent search (default ``SearchOptions()``).

    Returns
    -------
    Projection
    """
    search = SearchOptions() if search is None else search
    tables = np.asarray(tables)
    rows = np.arange(len(tables)) if rows is None else np.asarray(rows)
    target = np.asarray(target, dtype=np.float32).reshape(-1)
    n, d = len(rows), tables.shape[1]
    if target.shape[0] != d:
        raise InputError(
            f"table to project has {target.shape[0]} values, the manifold's tables have {d}"
        )
    if not np.isfinite(target).all():
        raise InputError("table to project has NaN or Inf values")
    bins = search_bins(d) if bins is None else np.asarray(bins)
    T = tables[np.ix_(rows, bins)].astype(np.float64)
    y = np.log1p(np.maximum(target[bins].astype(np.float64), 0.0))
    own = log_rms(T, y)
    order = np.argsort(own)[: max(1, min(search.n_nearest, n))]
    X = interpolant.latent
    cand = candidates(X, order, search.n_latent)  # scored in one batch
    scores = log_rms(interpolant.weights(cand) @ T, y)
    best = (float(own[order[0]]), X[order[0]].copy())

    def f(x):
        w = interpolant.weights(x)
        blend = w @ T
        pos = blend > 0
        r = np.log1p(np.where(pos, blend, 0.0)) - y
        val = float(r @ r) / len(y)
        g = np.where(pos, 2.0 * r / (1.0 + np.where(pos, blend, 0.0)), 0.0) / len(y)
        return val, interpolant.jacobian(x).T @ (T @ g)

    for x0 in cand[np.argsort(scores)[: search.n_starts]]:
        res = scipy.optimize.minimize(
            f,
            x0,
            jac=True,
            method="L-BFGS-B",
            options={"maxiter": search.max_iter, "gtol": 1e-10, "ftol": 1e-12},
        )
        err = float(np.sqrt(max(res.fun, 0.0)))
        if err < best[0]:
            best = (err, res.x.copy())
    t_log = np.log1p(np.maximum(target, 0.0))
    # on all bins: the search's point against the closest materials themselves
    own_full = np.array(
        [log_rms(np.asarray(tables[rows[i]], dtype=np.float32), t_log) for i in order]
    )
    w = interpolant.weights(best[1])
    full = _blend(w, tables, rows)
    error = float(log_rms(full, t_log))
    k = int(np.argmin(own_full))
    x = best[1]
    if own_full[k] < error:
        x, error = X[order[k]].copy(), float(own_full[k])
        w = interpolant.weights(x)
        full = _blend(w, tables, rows)
    return Projection(
        x=x,
        error=error,
        weights=w,
        nearest=names[order[k]] if names is not None else str(order[k]),
        nearest_error=float(own_full[k]),
        negative_fraction=float((full < 0).mean()),
    )


def _blend(w, tables, rows, chunk=1 << 20):
    """``w @ tables[rows]`` in float32, by chunks of bins (no copy of the tables)."""
    full = np.zeros(len(tables), dtype=np.float32)
    full[rows] = weights32(w)
    w = full
    out = np.empty(tables.shape[1], dtype=np.float32)
    for s in range(0, tables.shape[1], chunk):
        out[s : s + chunk] = w @ tables[:, s : s + chunk]
    return out


def beyond(
    projection,
    tables,
    target,
    *,
    rows=None,
    bins=None,
    n_candidates=BEYOND_CANDIDATES,
    affine=False,
    albedo=None,
    dims=None,
):
    """The best physically plausible combination of training tables for ``target`` beyond the data.

    Weights over the ``n_candidates`` training materials closest to ``target`` (and those the
    latent projection ``projection`` uses) may leave the simplex: negative, and (unless
    ``affine``) not summing to 1, as long as the combined table has no negative bin and a
    directional albedo at most 1 at every incidence (:func:`plausibility.plausible_weights`,
    started from the projection's convex weights). Returns ``projection`` with
    :attr:`Projection.beyond` set; its weights are over all training materials (``rows``).
    """
    tables = np.asarray(tables)
    rows = np.arange(len(tables)) if rows is None else np.asarray(rows)
    target = np.asarray(target, dtype=np.float32).reshape(-1)
    bins = search_bins(tables.shape[1]) if bins is None else np.asarray(bins)
    own = log_rms(tables[np.ix_(rows, bins)], np.log1p(np.maximum(target[bins], 0.0)))
    cand = np.union1d(np.argsort(own)[:n_candidates], np.flatnonzero(projection.weights > 1e-4))
    if albedo is None:
        n_bins = tables.shape[1] // 3
        if dims is None:
            raise InputError("`dims` (the tables' resolution) is needed for the directional albedo")
        if int(np.prod(dims)) != n_bins:
            raise InputError(f"`dims` {tuple(dims)} do not match tables of {n_bins} bins")
        albedo = DirectionalAlbedo(dims)
    sub = tables[rows] if not np.array_equal(rows, np.arange(len(tables))) else tables
    start = np.asarray(projection.weights, dtype=np.float64)
    found = plausible_weights(sub, target, cand, start, albedo, bins=bins[::4], affine=affine)
    projection.beyond = found
    return projection

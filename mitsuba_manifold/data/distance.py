"""A perceptual distance between BRDF tables, after Pereira and Rusinkiewicz 2012 [PR12].

[PR12] T. Pereira, S. Rusinkiewicz: "Gamut mapping spatially varying reflectance with an
improved BRDF similarity metric", Computer Graphics Forum (Proc. EGSR) 31(4), 2012 — the
metric of the paper's Fig. 9. Its two perceptual ingredients are kept: the reflected
radiance ``f cos`` rather than the BRDF ``f`` is compared, and values are compressed by a
cube root (the lightness response, CIE L* ~ Y^(1/3)) before an L2 norm over directions.
This module's variant, documented so that it can be reproduced:

    d(f, g)^2 = 1/3 sum_c  int int  (cbrt(f_c cos_i cos_o) - cbrt(g_c cos_i cos_o))^2  dmu(w_i, w_o)

* ``cos_i cos_o`` (both cosines, unlike [PR12]'s one) keeps the integrand reciprocal, as
  the MERL tables are (one bin holds both ``(w_i, w_o)`` and ``(w_o, w_i)``);
* ``mu`` is the solid-angle measure ``dw_i dw_o`` over both hemispheres, written in the
  tables' half/difference coordinates as ``4 cos(theta_d) sin(theta_h) sin(theta_d)
  dtheta_h dphi_h dtheta_d dphi_d`` (``phi_h`` integrates out), normalised to total mass 1,
  so that ``d`` is an RMS over direction pairs in units of ``sr^(-1/3)``;
* [PR12]'s low-pass filtering of the BRDF by natural illumination statistics is left out
  (it needs a spherical convolution of every table); the cube root already keeps sharp
  highlights from dominating the norm as they do in plain L2.

``d`` is the Euclidean distance between the *features* ``sqrt(mu_b / 3) cbrt(f cos_i cos_o)``
of the bins ``b``: a metric (a pseudo-metric on tables that differ only below the horizon,
which carry no weight). :func:`brdf_distance` gives it between tables (broadcast, exact
differences), :func:`distance_matrix` between two stacks of tables (an ``(n, m)`` matrix
from blockwise Gram products). A :class:`Quadrature` on a coarser sub-grid of bins (a
``stride``) makes cheap estimates for searches; its error against the full grid is
measured by ``tools/bench.py fig9``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from . import merl

if TYPE_CHECKING:
    from collections.abc import Iterator
    from typing import Any


#: Bins per block in the blockwise products (memory: a block of float64 features per table).
BLOCK = 1 << 16


@functools.lru_cache(maxsize=8)
def _measure(dims) -> tuple[Any, np.ndarray]:
    """Per-bin ``mu`` (shape ``dims``, sum 1) and ``cos_i cos_o`` at the bin centres."""
    n_h, n_d, n_p = dims
    dth = np.diff((np.arange(n_h + 1) / n_h) ** 2 * (np.pi / 2))  # theta_h bins: uniform in sqrt
    th, td, pd = merl.bin_centres(dims)
    wi, wo = merl.directions(th, td, pd)
    above = merl.above_horizon(dims)
    cos = np.where(above, np.clip(wi[..., 2], 0, None) * np.clip(wo[..., 2], 0, None), 0.0)
    mu = np.where(above, np.cos(td) * np.sin(th) * np.sin(td) * dth[:, None, None], 0.0)
    return mu / mu.sum(), cos


@dataclass(frozen=True)
class Quadrature:
    """Bins and weights of the distance's integral: the full grid, or one bin per cell of a sub-grid.

    ``stride = (s_h, s_d, s_p)`` groups ``s_h x s_d x s_p`` neighbouring bins into a cell; the
    bin nearest the cell's middle among those above the horizon stands for it with the cell's
    whole measure. ``index``: flat indices into
    an RGB-concatenated row ``(3 * prod(dims),)`` (a :meth:`Database.stack` row);
    ``scale``: ``sqrt(mu / 3)`` per index; ``cos``: ``cos_i cos_o`` per index.
    """

    dims: tuple
    stride: tuple
    index: np.ndarray
    scale: np.ndarray
    cos: np.ndarray

    @classmethod
    def of(cls, dims, stride=(1, 1, 1)) -> Quadrature:
        dims = tuple(int(v) for v in dims)
        stride = tuple(int(s) for s in stride)
        if len(dims) != 3 or min(dims) < 1 or len(stride) != 3 or min(stride) < 1:
            raise InputError(
                f"`stride` must be 3 integers >= 1 for tables of 3 dimensions, got {stride} for {dims}"
            )
        mu, cos = _measure(dims)
        idx = np.indices(dims)
        cell = np.ravel_multi_index(
            tuple(i // s for i, s in zip(idx, stride)),
            tuple(-(-n // s) for n, s in zip(dims, stride)),
        ).ravel()
        mass = np.bincount(cell, weights=mu.ravel())
        # representative: the bin nearest the cell's middle among those with weight (above the horizon)
        off = sum(np.abs(i % s - (s - 1) / 2) for i, s in zip(idx, stride)).ravel()
        score = np.where(mu.ravel() > 0, off, np.inf)
        order = np.lexsort((score, cell))
        first = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
        flat = np.sort(first[np.isfinite(score[first])])
        w = mass[cell[flat]]
        bins = int(np.prod(dims))
        index = (np.arange(3)[:, None] * bins + flat[None]).ravel()
        scale = np.tile(np.sqrt(w / 3.0), 3)
        return cls(dims, stride, index, scale, np.tile(cos.ravel()[flat], 3))

    def blocks(self, size=BLOCK) -> Iterator[Any]:
        """The quadrature in consecutive pieces of ``size`` values (for blockwise sums)."""
        for s in range(0, self.size, size):
            part = slice(s, s + size)
            yield Quadrature(
                self.dims, self.stride, self.index[part], self.scale[part], self.cos[part]
            )

    @property
    def size(self) -> int:
        """Values per table used (3 channels times the bins kept)."""
        return self.index.size

    def features(self, rows) -> np.ndarray:
        """Features ``scale * cbrt(rows * cos)`` (float64) of flat rows ``(..., 3 * bins)`` or of
        rows already restricted to :attr:`index` ``(..., size)``.
        """
        rows = np.asarray(rows)
        if rows.shape[-1] != self.size:
            rows = rows[..., self.index]
        out = np.maximum(rows, 0.0) * self.cos  # float64, transformed in place
        return np.multiply(self.scale, np.cbrt(out, out=out), out=out)


def _flat(tables, dims) -> tuple[np.ndarray, Any]:
    """Tables as flat RGB-concatenated rows ``(..., 3 * bins)`` and their dims.

    Accepts channel-first tables ``(..., 3, n_h, n_d, n_p)`` (as :meth:`Database.reflectance`),
    channel-last ones ``(..., n_h, n_d, n_p, 3)`` (when ``dims`` says which axes are bins, or the
    last axis is the only one of size 3) and flat rows (``dims`` needed).
    """
    t = np.asarray(tables)
    if dims is not None:
        dims = tuple(int(v) for v in dims)
        if t.shape[-4:] == (3,) + dims:
            return t.reshape(t.shape[:-4] + (-1,)), dims
        if t.shape[-4:] == dims + (3,):
            return np.moveaxis(t, -1, -4).reshape(t.shape[:-4] + (-1,)), dims
        if t.shape[-1:] == (3 * int(np.prod(dims)),):
            return t, dims
        raise InputError(
            f"`tables` of shape {t.shape} do not hold tables of {dims} bins (3 channels)"
        )
    if t.ndim >= 4 and t.shape[-4] == 3:
        return t.reshape(t.shape[:-4] + (-1,)), tuple(t.shape[-3:])
    if t.ndim >= 4 and t.shape[-1] == 3:
        return np.moveaxis(t, -1, -4).reshape(t.shape[:-4] + (-1,)), tuple(t.shape[-4:-1])
    raise InputError(
        f"`tables` of shape {t.shape}: expected (..., 3, n_theta_h, n_theta_d, n_phi_d) "
        "tables, or flat rows with `dims`"
    )


def brdf_distance(a, b, dims=None, stride=(1, 1, 1)) -> float | np.ndarray:
    """The [PR12]-style distance (module doc) between tables ``a`` and ``b``, broadcast.

    Parameters
    ----------
    a, b : array_like
        Reflectance tables (1/sr): ``(..., 3, n_h, n_d, n_p)``, ``(..., n_h, n_d, n_p, 3)`` or
        flat rows ``(..., 3 * bins)`` with ``dims``; leading axes broadcast against each other.
    dims : 3 ints, optional
        ``(n_theta_h, n_theta_d, n_phi_d)``; needed for flat rows.
    stride : 3 ints
        Sub-grid of the quadrature (:class:`Quadrature`); ``(1, 1, 1)``: every bin.

    Returns
    -------
    float or ndarray
        ``d(a, b)`` over the broadcast leading axes (exact differences: 0 for equal tables).
    """
    d = _distance(*_pair(a, b, dims, stride))
    return float(d) if d.ndim == 0 else d


def _distance(fa, fb, quad) -> np.ndarray:
    """:func:`brdf_distance` of flat rows ``fa``, ``fb`` under the quadrature ``quad``."""
    total = np.zeros(np.broadcast_shapes(fa.shape[:-1], fb.shape[:-1]))
    for part in quad.blocks():
        diff = part.features(fa[..., part.index]) - part.features(fb[..., part.index])
        total += np.einsum("...k,...k->...", diff, diff)
    return np.sqrt(total)


def distance_matrix(A, B=None, dims=None, stride=(1, 1, 1)) -> np.ndarray:
    """``D[i, j] = d(A[i], B[j])`` for two stacks of tables (``B`` omitted: ``A`` with itself).

    ``A``: ``(n, ...)`` tables as :func:`brdf_distance` takes them (one leading axis), ``B``
    ``(m, ...)``. From Gram products of the features over blocks of bins (float64, centred per
    block); entries too small for the Gram's rounding are recomputed from differences, so equal
    tables are at exactly 0. Without ``B`` the matrix is symmetric with a zero diagonal.
    """
    same = B is None
    fa, fb, quad = _pair(A, A if same else B, dims, stride)
    if fa.ndim != 2 or fb.ndim != 2:
        raise InputError(
            f"`A` and `B` must be stacks of tables (one leading axis), got leading shapes "
            f"{fa.shape[:-1]} and {fb.shape[:-1]}"
        )

    def parts():  # each block's features, computed once when A is compared with itself
        for p in quad.blocks():
            F = p.features(fa[:, p.index])
            yield F, F if same else p.features(fb[:, p.index])

    def exact(i, j) -> float:  # a table's distance to itself is 0 (the diagonal of A with itself)
        return 0.0 if same and i == j else float(_distance(fa[i], fb[j], quad))

    D = gram_distances(parts(), exact)
    if same:
        D = 0.5 * (D + D.T)
        np.fill_diagonal(D, 0.0)
    return D


def gram_distances(parts, exact=None, rtol=1e-9) -> np.ndarray:
    """Euclidean distances ``(n, m)`` between the rows of feature blocks ``parts`` (pairs ``(F, G)``
    of ``(n, k)`` and ``(m, k)`` arrays over the same columns), accumulated blockwise.

    ``|f - g|^2 = |f|^2 + |g|^2 - 2 f.g`` loses what is below ``rtol`` of the norms to rounding;
    such entries are recomputed by ``exact(i, j)`` (when given) or taken as 0.
    """
    D2, N2 = None, None
    for F, G in parts:
        same = G is F  # a block compared with itself: its squared norms once
        F, G = np.asarray(F, dtype=np.float64), np.asarray(G, dtype=np.float64)
        centre = F.mean(axis=0)
        f = F - centre
        nf = (f * f).sum(1)[:, None]
        g = G - centre
        ng = nf.reshape(1, -1) if same else (g * g).sum(1)[None]
        block = nf + ng - 2.0 * f @ g.T
        del F, G, f, g  # before the next block's features are made
        D2 = block if D2 is None else D2 + block
        N2 = nf + ng if N2 is None else N2 + nf + ng
    if D2 is None:
        raise InputError("no features to measure a distance over (every bin has zero weight)")
    small = D2 <= rtol * N2
    D = np.sqrt(np.maximum(D2, 0.0))
    for i, j in zip(*np.nonzero(small)):
        D[i, j] = exact(i, j) if exact is not None else 0.0
    return D


def _pair(a, b, dims, stride) -> tuple[Any, Any, Quadrature]:
    """Flat rows of ``a`` and ``b`` (same resolution) and the quadrature of ``stride``."""
    fa, da = _flat(a, dims)
    fb, db = _flat(b, dims if dims is not None or np.ndim(b) >= 4 else da)
    if da != db:
        raise InputError(f"`a` and `b` hold tables of different resolutions {da} and {db}")
    return fa, fb, Quadrature.of(da, stride)

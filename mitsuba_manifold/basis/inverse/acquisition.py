"""Acquisition of a material from photographs: the weights over the manifold's tables whose images
best explain the photos, as a constrained convex quadratic programme.

With one object that does not see itself, the image of a material ``sum_i w_i table_i`` is
exactly linear in the weights: ``I(w) = base + sum_i w_i I_i`` (``I_i``: training material ``i``
alone in the photo's scene, :mod:`mitsuba_manifold.render.inverse.acquire` renders them all in one pass).
Stacking every masked pixel and channel of every view as a row,

    minimise  sum_r c_r (A_r w + b_r - t_r)^2 + lam * s * |w - w_p|^2
    subject to  the plausibility of the material sum_i w_i table_i,

``c_r = 1 / (t_r^2 + eps)`` (the relative error :func:`imaging.metrics.rel_mse` of the photo,
``eps`` relative to the photo's mean square), ``s = trace(A^T C A) / N`` (so that ``lam`` has no
unit) and ``w_p`` a prior point (0 by default: a ridge).

The feasible sets:

- ``"nonneg"``: ``w >= 0`` (no bin can be negative) and a directional albedo at most 1 at every
  incidence and channel (:class:`~mitsuba_manifold.manifold.plausibility.DirectionalAlbedo`,
  linear in ``w``).
- ``"beyond"``: weights of either sign (combinations beyond the training materials' cone) with
  no negative bin of the combined table and the same albedo bound. Non-negativity is imposed on
  a sample of (bin, channel) values (:data:`CHECK_BINS` at random and, per material, the
  :data:`CHECK_PER_MATERIAL` where it holds the largest share of all tables), then on the full
  table: its most negative values join the constraints (:data:`FULL_ROUNDS` rounds) and a last
  step back toward the non-negative solution guarantees it exactly (:func:`guarantee`).
- ``"convex"``: ``w >= 0``, ``sum w = 1``.
- ``"plausible"`` (the default): ``beyond`` where the photo needs it, else ``nonneg``:
  both are cross-validated over held-out blocks of pixels and ``beyond`` is taken only when it
  lowers the held-out error by more than :data:`CV_MARGIN` (:func:`choose`); ``lam`` is the
  largest of :data:`CV_GRID` whose held-out error is within :data:`CV_TOLERANCE` of the best.

Each programme is a least-distance programme solved through SciPy's non-negative least squares
(:func:`quadratic_programme`); the data enter through the N x N matrix ``A^T C A``, so its cost
does not depend on the number of pixels once that is formed.

The latent-point search of the paper (:mod:`mitsuba_manifold.render.inverse.match_render`) stays
available as ``method="latent"``; the rendering layer runs it, not this module.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.linalg
import scipy.optimize

from ..._util.atomic import write_bytes
from ...errors import FormatError, InputError, NumericalError
from ...manifold.plausibility import DirectionalAlbedo, largest_plausible_step

#: The feasible sets of :class:`AcquireOptions` (``latent``: the paper's latent-point search).
METHODS = ("plausible", "beyond", "nonneg", "convex", "latent")
#: Relative floor of the data term's weights: ``eps = EPS_REL * mean(t^2)``.
EPS_REL = 0.01
#: Cross-validation: folds, the candidate regularisation weights, the side of a pixel block.
CV_FOLDS = 3
CV_GRID = (1e-4, 3e-4, 1e-3, 3e-3)
CV_BLOCK = 8
#: The cross-validation's choices: a weight's held-out error within ``1 + CV_TOLERANCE`` of the
#: best counts as as good (the largest such ``lam`` is taken); weights beyond the non-negative
#: ones are taken when they lower the held-out error by more than ``CV_MARGIN``.
CV_TOLERANCE = 0.01
CV_MARGIN = 0.1
#: (bin, channel) values sampled for the non-negativity constraints.
CHECK_BINS = 1 << 13
#: Per material: the values where it holds the largest share of all tables.
CHECK_PER_MATERIAL = 48
#: Rounds of full-table checks adding the most negative values to the constraints.
FULL_ROUNDS = 2
ADDED_PER_ROUND = 8192
#: Smallest ridge (relative): keeps ``H`` positive definite when the images are collinear.
JITTER = 1e-9
#: Bootstrap solves of the spread of near-equally good answers, and the warning thresholds:
#: relative spread (standard deviation / mean) of the albedo, and of the specular peak.
BOOTSTRAP = 8
WARN_ALBEDO_SPREAD = 0.1
WARN_PEAK_SPREAD = 0.5
#: Format tag of the result's JSON file.
FORMAT = "mitsuba-manifold acquisition 1"


@dataclass(frozen=True)
class AcquireOptions:
    """Settings of an acquisition (numpydoc-style; every field has a default).

    Parameters
    ----------
    method : {"plausible", "beyond", "nonneg", "convex", "latent"}
        The feasible set of the weights (module docstring); ``latent``: the paper's search of one
        latent point by differentiable rendering (slow; for comparison).
    regularisation : float, optional
        ``lam`` of the ridge; default: chosen by cross-validation over held-out pixel blocks.
        Given with ``method="plausible"``, nothing is cross-validated: the wider set, ``beyond``,
        is solved with it.
    spp : int
        Samples per pixel of the training materials' images in the photo's scene (one pass).
    seed : int
        Seed of those renders.
    max_depth : int, optional
        Path depth of those renders (default: the scene's integrator's).
    bootstrap : int
        Bootstrap solves for the report's spread (0: none).
    render_spp : int
        Samples per pixel of the acquired material's and the best single material's renders
        (0: none).
    progress : bool
        Progress bar.
    basis_cache : str, optional
        Folder keeping the training materials' images of a scene (keyed by the scene file, the
        manifold, the image size, ``spp``, ``seed`` and ``max_depth``): a second photo in the same
        scene skips their render.
    """

    method: str = "plausible"
    regularisation: float | None = None
    spp: int = 64
    seed: int = 0
    max_depth: int | None = None
    bootstrap: int = BOOTSTRAP
    render_spp: int = 128
    progress: bool = True
    basis_cache: str | None = None

    def check(self) -> AcquireOptions:
        """The options, or an :class:`InputError` naming the first unusable one."""
        if self.method not in METHODS:
            raise InputError(f"`method` must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.regularisation is not None:
            r = self.regularisation
            if (
                isinstance(r, bool)
                or not isinstance(r, (int, float))
                or not (math.isfinite(r) and r >= 0)
            ):
                raise InputError(f"`regularisation` must be a number >= 0 or None, got {r!r}")
        for name, low in (("spp", 1), ("seed", 0), ("bootstrap", 0), ("render_spp", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                raise InputError(f"`{name}` must be an integer >= {low}, got {v!r}")
        if self.max_depth is not None and (
            isinstance(self.max_depth, bool) or not isinstance(self.max_depth, (int, np.integer))
        ):
            raise InputError(f"`max_depth` must be an integer or None, got {self.max_depth!r}")
        return self


@dataclass
class LinearPhotos:
    """The photos as a linear model of the weights: rows are (pixel, channel) of every view's mask.

    Attributes
    ----------
    A : (R, N) ndarray
        Training material ``i``'s image at each row (column ``i``).
    base : (R,) ndarray
        What reaches the row without touching the material (lights seen directly).
    t : (R,) ndarray
        The photos.
    block : (R,) ndarray of int
        Pixel block of each row (the cross-validation's unit; distinct across views).
    view : (R,) ndarray of int
        View of each row.
    """

    A: np.ndarray
    base: np.ndarray
    t: np.ndarray
    block: np.ndarray
    view: np.ndarray

    def check(self) -> LinearPhotos:
        """The model, or an :class:`InputError` where it cannot be fitted."""
        if len(self.t) == 0:
            raise InputError("the masks select no pixel: nothing to acquire from")
        if not (np.isfinite(self.A).all() and np.isfinite(self.t).all()):
            raise InputError("the photos or the training materials' images hold NaN or Inf values")
        return self

    def weights(self) -> np.ndarray:
        """The data term's weights ``c_r = 1 / (t_r^2 + eps)``, ``eps = EPS_REL mean(t^2)``."""
        t = np.maximum(self.t, 0.0)
        eps = EPS_REL * max(float(np.mean(t * t)), 1e-30)
        return 1.0 / (t * t + eps)

    def normal_equations(self, rows=None) -> tuple:
        """``(H, g, e0)`` of the data term ``w^T H w - 2 g^T w + e0`` over ``rows`` (default all),
        each divided by the rows' total weight (the weighted mean over those rows).
        """
        c = self.weights()
        A, r, c = (
            (self.A, self.t - self.base, c)
            if rows is None
            else (self.A[rows], (self.t - self.base)[rows], c[rows])
        )
        total = float(c.sum())
        Ac = A * (c / total)[:, None]
        return Ac.T @ A, Ac.T @ r, float((c / total) @ (r * r))

    def relative_error(self, w, rows=None) -> float:
        """Relative RMSE of the model at ``w`` against the photos over ``rows``, weighted as the data term."""
        H, g, e0 = self.normal_equations(rows)
        return float(np.sqrt(max(w @ H @ w - 2 * g @ w + e0, 0.0)))


@dataclass
class Constraints:
    """The plausibility of ``sum_i w_i table_i`` as linear constraints on ``w``.

    Attributes
    ----------
    albedo : (N, K) ndarray
        Directional albedo of every training material at the incidences and channels of
        :class:`DirectionalAlbedo` (``K = 3 x incidences``): ``w @ albedo <= 1``.
    check : (N, M) ndarray
        The training tables at :data:`CHECK_BINS` sampled (bin, channel) values: ``w @ check >= 0``.
    peak : (N, 3) ndarray
        Each table near the specular peak (mean of the bins at ``theta_h = 0``, ``theta_d`` 0
        and 30 degrees), the report's measure of gloss.
    """

    albedo: np.ndarray
    check: np.ndarray
    peak: np.ndarray
    sample: np.ndarray = None

    def add(self, values, index) -> Constraints:
        """The constraints with the (bin, channel) values ``index`` of the tables added
        (``values``: ``(N, len(index))``).
        """
        return Constraints(
            self.albedo,
            np.concatenate([self.check, np.asarray(values, dtype=np.float64)], axis=1),
            self.peak,
            None if self.sample is None else np.concatenate([self.sample, index]),
        )

    @classmethod
    def of(cls, table, n, dims, seed=0) -> Constraints:
        """From ``table(i) -> flat float32 RGB table`` of each of the ``n`` materials (two passes).

        The sampled values: :data:`CHECK_BINS` at random, and for every material the
        :data:`CHECK_PER_MATERIAL` (bin, channel) values where it holds the largest share of
        the sum of all tables (where a negative weight on it is the first to make a bin
        negative).
        """
        from ...data import merl

        da = DirectionalAlbedo(dims)
        bins = int(np.prod(dims))
        total = np.zeros(3 * bins, np.float32)
        for i in range(n):
            total += np.asarray(table(i), dtype=np.float32).reshape(-1)
        floor = np.float32(1e-3 * max(float(total.mean()), 1e-30))
        rng = np.random.default_rng(seed)
        picked = [rng.choice(3 * bins, size=min(CHECK_BINS, 3 * bins), replace=False)]
        s30 = np.sin(np.radians(30.0))
        wi = np.array([[0.0, 0.0, 1.0], [s30, 0.0, np.sqrt(1 - s30 * s30)]])
        wo = np.array([[0.0, 0.0, 1.0], [-s30, 0.0, np.sqrt(1 - s30 * s30)]])
        peak_bins = merl.flat_index(wi, wo, tuple(dims))
        albedo, peak = [], []
        for i in range(n):
            t = np.asarray(table(i), dtype=np.float32).reshape(-1)
            albedo.append(da.of(t[None])[0].reshape(-1))
            peak.append([t[c * bins + peak_bins].mean() for c in range(3)])
            share = t / (total + floor)
            k = min(CHECK_PER_MATERIAL, share.size - 1)
            picked.append(np.argpartition(-share, k)[:k])
        sample = np.unique(np.concatenate(picked))
        check = np.empty((n, len(sample)))
        for i in range(n):
            check[i] = np.asarray(table(i), dtype=np.float32).reshape(-1)[sample]
        return cls(np.array(albedo), check, np.array(peak), sample)


def combined(w, table, n) -> np.ndarray:
    """``sum_i w_i table_i`` over the full tables in float32 (as rendered), one table at a time."""
    out = None
    for i in range(n):
        if w[i] == 0:
            continue
        t = np.asarray(table(i), dtype=np.float32).reshape(-1)
        out = np.zeros(t.size, np.float32) if out is None else out
        out += np.float32(w[i]) * t
    return out


@dataclass
class Solution:
    """One solve: weights, the regularisation used, and whether the full-table guarantee stepped back."""

    w: np.ndarray
    regularisation: float
    shrink: float = 1.0


def quadratic_programme(H, g, G, h) -> np.ndarray:
    """``argmin_w w^T H w - 2 g^T w`` subject to ``G w >= h`` (``H`` positive definite).

    Solved as a least-distance programme through non-negative least squares (Lawson and Hanson,
    *Solving Least Squares Problems*, 1974, ch. 23): with ``H = L L^T`` and ``u = L^T w - L^{-1} g``
    the problem is ``min |u|`` subject to ``M u >= d`` (``M = G L^{-T}``, ``d = h - M L^{-1} g``),
    whose solution is ``u = -r_{1:n} / r_{n+1}`` for the residual ``r = E y - e_{n+1}`` of the
    NNLS problem ``min_{y >= 0} |E y - e_{n+1}|``, ``E = [M^T; d^T]`` (SciPy's ``nnls``).
    Raises :class:`NumericalError` when the constraints admit no point.
    """
    n = len(g)
    L = np.linalg.cholesky(H)
    Linv_T = scipy.linalg.solve_triangular(L, np.eye(n), lower=True).T
    f = scipy.linalg.solve_triangular(L, g, lower=True)
    M = G @ Linv_T
    d = h - M @ f
    E = np.vstack([M.T, d[None, :]])
    rhs = np.zeros(n + 1)
    rhs[-1] = 1.0
    y, _ = scipy.optimize.nnls(E, rhs, maxiter=50 * E.shape[1])
    r = E @ y - rhs
    if abs(r[-1]) < 1e-12:
        raise NumericalError(
            "the acquisition's constraints admit no material (infeasible programme)"
        )
    return Linv_T @ (-r[:n] / r[-1] + f)


def _constraints(cons, method, n) -> tuple:
    """``(G, h)`` of ``method``'s feasible set ``G w >= h``."""
    rows = [-cons.albedo.T]
    bound = [-np.ones(cons.albedo.shape[1])]
    if method in ("nonneg", "convex"):
        rows.append(np.eye(n))
        bound.append(np.zeros(n))
    if method == "convex":
        rows += [np.ones((1, n)), -np.ones((1, n))]
        bound += [np.ones(1), -np.ones(1)]
    if method == "beyond":
        rows.append(cons.check.T)
        bound.append(np.zeros(cons.check.shape[1]))
    return np.vstack(rows), np.concatenate(bound)


def solve(H, g, cons, method, lam, prior=None) -> np.ndarray:
    """The weights minimising the regularised data term ``w^T H w - 2 g^T w + lam s |w - prior|^2``
    (``s = trace(H) / N``) under ``method``'s constraints (for ``plausible``: non-negativity on
    the sampled bins; :func:`guarantee` makes it hold on the full table).
    """
    n = len(g)
    prior = np.zeros(n) if prior is None else np.asarray(prior, dtype=np.float64)
    s = max(float(np.trace(H)) / n, 1e-300)
    lam = max(float(lam), JITTER)
    G, h = _constraints(cons, method, n)
    return quadratic_programme(H + lam * s * np.eye(n), g + lam * s * prior, G, h)


def combined_pair(w, v, table, n) -> tuple:
    """:func:`combined` of two weight vectors in one pass over the tables."""
    a = b = None
    for i in range(n):
        if w[i] == 0 and v[i] == 0:
            continue
        t = np.asarray(table(i), dtype=np.float32).reshape(-1)
        if a is None:
            a, b = np.zeros(t.size, np.float32), np.zeros(t.size, np.float32)
        a += np.float32(w[i]) * t
        b += np.float32(v[i]) * t
    return a, b


def guarantee(w, start, table, n, albedo) -> tuple:
    """``start + s (w - start)`` with the largest ``s`` in [0, 1] for which every bin of the full
    combined table is non-negative (in float32, as rendered) and no directional albedo exceeds 1;
    ``start`` must satisfy both (a non-negative solution). ``table(i)``: material ``i``'s flat
    float32 table. Returns ``(weights, s)``.
    """
    w = np.asarray(w, dtype=np.float64)
    start = np.asarray(start, dtype=np.float64)
    if np.all(w >= 0):
        return w, 1.0
    full, base = combined_pair(w, start, table, n)
    s = largest_plausible_step(base, full, start @ albedo, w @ albedo)
    s = max(0.0, s * (1 - 1e-4)) if s < 1.0 else 1.0
    return start + s * (w - start), s


def solve_beyond(H, g, cons, lam, table, n, progress=None) -> tuple:
    """:func:`solve` with ``method="beyond"`` made to hold on the full tables: up to
    :data:`FULL_ROUNDS` times, the full combination is formed and its :data:`ADDED_PER_ROUND`
    most negative values join the constraints; then :func:`guarantee` (toward the non-negative
    solution). Returns ``(weights, share of the last step kept, constraints)``.
    """
    w = solve(H, g, cons, "beyond", lam)
    for _ in range(FULL_ROUNDS):
        if np.all(w >= 0):
            break
        full = combined(w, table, n)
        neg = np.flatnonzero(full < 0)
        if progress is not None:
            progress()
        if len(neg) == 0:
            break
        worst = neg[np.argsort(full[neg])[:ADDED_PER_ROUND]]
        values = np.stack(
            [np.asarray(table(i), dtype=np.float32).reshape(-1)[worst] for i in range(n)]
        )
        cons = cons.add(values, worst)
        w = solve(H, g, cons, "beyond", lam)
    start = solve(H, g, cons, "nonneg", lam)
    w, shrink = guarantee(w, start, table, n, cons.albedo)
    return w, shrink, cons


def solve_programme(photos, cons, feasible, lam, table, n) -> tuple:
    """``(weights, s, constraints)`` of the programme on ``photos`` (:class:`LinearPhotos`) over
    the feasible set ``feasible`` with ridge ``lam``: :func:`solve_beyond` for ``beyond`` (``s``,
    the full-table guarantee's share of the step; the constraints grown by its rounds), else
    :func:`solve` (``s = 1``). ``table(i)``: material ``i``'s flat table.
    """
    H, g, _ = photos.normal_equations()
    if feasible == "beyond":
        return solve_beyond(H, g, cons, lam, table, n)
    return solve(H, g, cons, feasible, lam), 1.0, cons


def answer_warnings(spread, step, what="these photos") -> list:
    """Warnings of an acquired answer: albedo or gloss not identifiable from ``what`` (its
    bootstrap :class:`Spread` beyond :data:`WARN_ALBEDO_SPREAD`, :data:`WARN_PEAK_SPREAD`; none
    without a spread) and a full-table guarantee that kept less than 99% of the ``step`` beyond
    the non-negative solution.
    """
    warnings = []
    if spread is not None and spread.albedo_spread > WARN_ALBEDO_SPREAD:
        warnings.append(
            f"the albedo is not identifiable from {what}: near-equally good answers differ "
            f"by {100 * spread.albedo_spread:.0f}% (relative standard deviation)"
        )
    if spread is not None and spread.peak_spread > WARN_PEAK_SPREAD:
        warnings.append(
            f"the gloss is not identifiable from {what}: the specular peak of near-equally "
            f"good answers differs by {100 * spread.peak_spread:.0f}%"
        )
    if step < 0.99:
        warnings.append(
            f"the plausibility guarantee on the full table kept {100 * step:.0f}% of the step "
            "beyond the non-negative solution"
        )
    return warnings


def _folds(block, k, seed) -> np.ndarray:
    """Fold of every row: blocks of pixels assigned at random to ``k`` folds."""
    ids = np.unique(block)
    rng = np.random.default_rng(seed)
    fold_of = dict(zip(ids.tolist(), rng.permutation(len(ids)) % k))
    return np.array([fold_of[b] for b in block.tolist()])


def cross_validate(
    photos, cons, method, grid=CV_GRID, folds=CV_FOLDS, seed=0, progress=None, tolerance=0.0
):
    """``(chosen lam, [(lam, held-out relative RMSE)])`` over held-out pixel blocks: the largest
    ``lam`` whose held-out error is within ``1 + tolerance`` of the smallest (the smoothest answer
    the held-out pixels cannot tell from the best).

    ``method="beyond"`` is cross-validated on the sampled-bin constraints (the full-table
    guarantee changes little and costs a pass over the tables).
    """
    fold = _folds(photos.block, folds, seed)
    parts = [(photos.normal_equations(fold != k), fold == k) for k in range(folds)]
    scores = []
    for lam in grid:
        err = 0.0
        for (H, g, _), held in parts:
            w = solve(H, g, cons, method, lam)
            err += photos.relative_error(w, held) ** 2
        scores.append((float(lam), float(np.sqrt(err / folds))))
        if progress is not None:
            progress()
    low = min(s[1] for s in scores)
    best = max(lam for lam, e in scores if e <= (1.0 + tolerance) * low)
    return best, scores


def choose(photos, cons, method, seed=0, progress=None) -> tuple:
    """``(feasible set, lam, {set: cross-validation scores})`` of an acquisition.

    ``method="plausible"``: both the non-negative weights and the weights beyond them
    (``beyond``) are cross-validated; ``beyond`` is taken only when its held-out error is below
    ``1 - CV_MARGIN`` times the non-negative weights' (the photo needs a material beyond the
    training materials' cone). ``lam``: the largest within :data:`CV_TOLERANCE` of the best.
    """
    sets = ("nonneg", "beyond") if method == "plausible" else (method,)
    found = {}
    for m in sets:
        found[m] = cross_validate(
            photos, cons, m, seed=seed, progress=progress, tolerance=CV_TOLERANCE
        )
    if method != "plausible":
        return method, found[method][0], {method: found[method][1]}
    low = {m: min(e for _, e in found[m][1]) for m in sets}
    pick = "beyond" if low["beyond"] < (1.0 - CV_MARGIN) * low["nonneg"] else "nonneg"
    return pick, found[pick][0], {m: found[m][1] for m in sets}


@dataclass
class Spread:
    """How different the near-equally good answers are (a bootstrap over pixel blocks).

    ``albedo`` / ``peak``: mean and relative spread of the normal-incidence directional albedo
    (RGB; standard deviation over mean) and of the specular-peak value (RGB, 1/sr; standard
    deviation over the mean peak plus the diffuse level albedo / pi) over the bootstrap solutions;
    ``effective_rank``: eigenvalues of the data term's ``A^T C A`` above 1e-6 of the largest
    (how many directions of the N weights the photos determine).
    """

    albedo: list
    albedo_spread: float
    peak: list
    peak_spread: float
    effective_rank: int
    solutions: int


def spread(photos, cons, method, lam, w, n, seed=0, progress=None) -> Spread:
    """The :class:`Spread` of ``n`` bootstrap solves (resampled pixel blocks) around ``w``."""
    H, _, _ = photos.normal_equations()
    ev = np.linalg.eigvalsh(H)
    rank = int(np.sum(ev > 1e-6 * max(ev.max(), 1e-300)))
    rng = np.random.default_rng(seed + 17)
    ids = np.unique(photos.block)
    sols = [np.asarray(w)]
    c = photos.weights()
    for _ in range(n):
        pick = rng.choice(ids, size=len(ids), replace=True)
        counts = np.bincount(np.searchsorted(ids, pick), minlength=len(ids))
        mult = counts[np.searchsorted(ids, photos.block)].astype(np.float64)
        cw = c * mult
        total = float(cw.sum())
        Ac = photos.A * (cw / total)[:, None]
        sols.append(solve(Ac.T @ photos.A, Ac.T @ (photos.t - photos.base), cons, method, lam))
        if progress is not None:
            progress()
    sols = np.array(sols)
    a = sols @ cons.albedo.reshape(len(w), 3, -1)[:, :, 0]
    p = sols @ cons.peak
    level = np.abs(p.mean(axis=0)) + np.abs(a.mean(axis=0)) / np.pi + 1e-12  # peak over diffuse
    peak_spread = float(np.max(p.std(axis=0) / level))
    albedo_spread = float(np.max(a.std(axis=0) / (np.abs(a.mean(axis=0)) + 1e-12)))
    return Spread(
        a.mean(0).tolist(), albedo_spread, p.mean(0).tolist(), peak_spread, rank, len(sols)
    )


@dataclass
class Acquisition:
    """An acquired material and what the photos say about it (written with :meth:`write`).

    Attributes
    ----------
    names : list of str
        The manifold's training materials.
    w : list of float
        The weights (render them with ``manifold_brdf``'s ``weights``).
    method : str
        The method asked for; ``feasible``: the set the weights were found in.
    x : list of float or None
        The latent point, where the weights are those of one (``latent`` and ``convex`` methods:
        the nearest point's weights are not the acquired ones, so it is None otherwise).
    error : float
        Relative RMSE of the acquired material's images against the photos over the masks.
    single : dict
        The best single training material: ``name``, ``error`` (same measure).
    regularisation : float
    cross_validation : dict
        Feasible set -> ``[[lam, held-out error], ...]``.
    coverage : dict
        Which outgoing and incident directions the masked pixels show (per view).
    spread : dict
        :class:`Spread` as a dict, or None.
    warnings : list of str
    time_s : float
    timings : dict
        Seconds of each stage.
    views : list of dict
        Scene, target, mask and sensor of each photo.
    manifold : str
        The manifold's path.
    renders : list of str
        Files of the acquired material's renders, one per view (where written).
    """

    names: list
    w: list
    method: str
    error: float
    single: dict
    x: list | None = None
    feasible: str = ""
    regularisation: float = 0.0
    cross_validation: dict = field(default_factory=dict)
    coverage: dict = field(default_factory=dict)
    spread: dict | None = None
    warnings: list = field(default_factory=list)
    time_s: float = 0.0
    timings: dict = field(default_factory=dict)
    views: list = field(default_factory=list)
    manifold: str = ""
    renders: list = field(default_factory=list)

    @property
    def weights(self) -> dict:
        """Every training material's name -> weight."""
        return dict(zip(self.names, [float(v) for v in self.w]))

    def top_weights(self, k=10) -> list:
        """The ``k`` largest weights by magnitude, ``[(name, weight)]``."""
        order = np.argsort(-np.abs(np.asarray(self.w)))[:k]
        return [(self.names[i], float(self.w[i])) for i in order if self.w[i] != 0]

    def weights_text(self, tol=1e-6) -> str:
        """The weights as ``manifold_brdf``'s ``weights`` property (``name:w, ...``)."""
        return ", ".join(f"{n}:{v:.6g}" for n, v in zip(self.names, self.w) if abs(v) > tol)

    def snippet(self, manifold_path=None) -> str:
        """A Mitsuba XML ``manifold_brdf`` rendering this material (no pruning: every weight counts)."""
        path = manifold_path or self.manifold
        return (
            '<bsdf type="manifold_brdf" id="acquired">\n'
            f'    <string name="manifold" value="{path}"/>\n'
            f'    <string name="weights" value="{self.weights_text()}"/>\n'
            '    <float name="prune" value="0"/>\n'
            "</bsdf>\n"
        )

    def to_dict(self) -> dict:
        """JSON-ready: ``weights`` (name -> weight) and ``single`` (``name``) among the keys."""
        out = asdict(self)
        out.pop("w")
        out.pop("names")
        out["format"] = FORMAT
        out["weights"] = self.weights
        out["top_weights"] = self.top_weights()
        return out

    def write(self, path) -> str:
        """Write as JSON (atomically); returns ``path``."""
        write_bytes(os.fspath(path), json.dumps(self.to_dict(), indent=1) + "\n")
        return os.fspath(path)

    @classmethod
    def read(cls, path) -> Acquisition:
        """Read a file written by :meth:`write`, or a :class:`FormatError` naming what is wrong."""
        path = os.fspath(path)
        try:
            with open(path) as f:
                d = json.load(f)
        except (OSError, ValueError) as e:
            raise FormatError(f"{path}: not an acquisition JSON file ({e})") from None
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise FormatError(f"{path}: not an acquisition file (no format {FORMAT!r})")
        weights = d.pop("weights", None)
        if not isinstance(weights, dict) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in weights.values()
        ):
            raise FormatError(f"{path}: `weights` must map names to numbers")
        d.pop("format")
        d.pop("top_weights", None)
        known = {f for f in cls.__dataclass_fields__} - {"names", "w"}
        unknown = set(d) - known
        if unknown:
            raise FormatError(f"{path}: unknown keys {sorted(unknown)}")
        try:
            return cls(names=list(weights), w=[float(v) for v in weights.values()], **d)
        except (TypeError, ValueError) as e:  # a required key missing, a value of another kind
            raise FormatError(f"{path}: not a complete acquisition file ({e})") from None

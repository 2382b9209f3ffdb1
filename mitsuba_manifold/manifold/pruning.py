"""Pruning a combination of tables, with the exact change of what the image sees.

A combination ``sum_i w_i table_i`` over N materials reads N tables; most weights
contribute little. Pruning keeps a subset, the kept weights rescaled to the same sum (so
the combination stays affine), and bounds what the change does. Two rules:

``"image"`` (the default)
    Bounds what light sees. The change ``delta`` of the weights must keep (a) each albedo
    channel (bihemispherical albedo, linear in the weights: ``delta @ albedos``, exact)
    within ``ALBEDO_SHARE * budget`` of its value: the energy
    the material reflects of any smooth light; (b) the *cosine-weighted* L2 change of the
    table within ``budget`` of its norm, in the norm ``|f|^2 = sum_bins q f^2`` with ``q`` the
    bins' ``cos(theta_i) cos(theta_o) dw_i dw_o`` (the albedo quadrature weights,
    :func:`data.database.albedo_weights`): by Cauchy-Schwarz it bounds the change of the
    light reflected towards any viewer, averaged over viewers, for incident light of bounded
    energy; exact through ``C = T diag(q) T^T`` (``|delta^T T|_q^2 = delta^T C delta``);
    and (c) the raw L2 change within ``RAW_SHARE * budget`` (the ``"raw-l2"`` rule's bound,
    for the narrowest peaks). (a) does most of the work: any L2 norm, cosine-weighted too, is
    dominated by the spikiest tables' peaks, so (b) alone lets a dull material of small
    weight go and the albedo change by far more; (a) alone meets the image target at the
    benchmark's points; (b) and (c) bound what an albedo cannot see (where in angle the
    energy goes; without (c) a narrow peak of tiny weight can be dropped) at little cost in
    the materials kept (``docs/benchmarks.md``).
    The search (:func:`prune_image`) drops materials in the order of what dropping each
    alone would change (one vectorised pass over all prefixes of that order), then goes on
    greedily, each step dropping the material whose removal changes least (O(N) per step).

``"raw-l2"``
    Drops the materials of smallest contribution ``|w_i| |table_i|`` for as long as the raw
    table changes by at most ``budget`` of its L2 norm, exact from ``G = T T^T``
    (:func:`prune`). The raw norm is dominated by the specular peaks, so a dull material of
    small weight can be dropped even where it changes the albedo by much more than the
    budget.

The measurements behind the choice: ``tools/bench.py prune`` (``benchmarks/results/prune.json``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..data import gram

if TYPE_CHECKING:
    from typing import Any


#: Default pruning budget, for ``Manifold.prune``, the ``manifold_brdf`` plugin, blends and
#: the explorer: the largest relative cosine-weighted L2 change of the table ("image" rule) or
#: relative raw L2 change ("raw-l2").
DEFAULT_PRUNE = 1e-2
#: Pruning rules (see the module docstring) and the default one.
RULES = ("image", "raw-l2")
DEFAULT_RULE = "image"
#: The "image" rule's bound on each albedo channel's relative change, as a share of the budget.
ALBEDO_SHARE = 0.5
#: The "image" rule's bound on the raw table's relative L2 change, as a share of the budget
#: (``inf``: none): the ``"raw-l2"`` rule's bound, so that the narrow specular peaks (bins at
#: ``theta_h ~ 0``, of tiny solid angle, which a point light seen in a mirror-like highlight
#: evaluates directly) stay bounded too (its cost in materials kept: ``docs/benchmarks.md``).
RAW_SHARE = 1.0
#: Albedos below this count as this in the relative albedo change (a black channel).
ALBEDO_FLOOR = 1e-4
#: A step of the search is taken only below this fraction of the bounds (room for round-off).
_SAFETY = 1.0 - 1e-9


def raw_gram(tables, block=gram.BLOCK) -> np.ndarray:
    """``T T^T`` (float64) of float32 tables ``(N, d)``, by blocks of values (:func:`gram.gram`)."""
    return gram.gram(tables, "raw", centre=False, block=block).S


def cos_grams(tables, q, block=gram.BLOCK) -> tuple[np.ndarray, np.ndarray]:
    """``(T T^T, T diag(q) T^T)`` of float32 tables ``(N, 3 * bins)`` in one pass; ``q``: the
    ``(bins,)`` albedo quadrature weights (the cosine-weighted measure of each bin).
    """
    g = gram.gram(tables, "raw", centre=False, weights=q, block=block)
    return g.S, g.weighted


def _rescaled(w, kept):
    """``delta`` (M, N): the change of ``w`` when only the rows of ``kept`` are kept, rescaled."""
    kept = np.atleast_2d(kept)
    s = np.where(kept, w, 0.0).sum(axis=1)
    scale = np.divide(w.sum(), s, out=np.zeros_like(s), where=np.abs(s) > 0)
    return np.where(kept, w * scale[:, None], 0.0) - w


def errors(w, kept, G) -> np.ndarray:
    """Relative L2 change of ``w^T T`` for each row of the boolean matrix ``kept`` (M, N), in the
    norm of the Gram matrix ``G`` (raw ``T T^T`` or cosine-weighted ``T diag(q) T^T``).
    """
    delta = _rescaled(w, kept)
    num = np.maximum(((delta @ G) * delta).sum(axis=1), 0.0)  # BLAS, not einsum's loop
    den = float(w @ G @ w)
    if den > 0:
        return np.sqrt(num / den)
    return np.where(num > 0, np.inf, 0.0)


def albedo_changes(w, kept, albedos) -> np.ndarray:
    """Relative change ``|delta @ albedos| / max(|w @ albedos|, ALBEDO_FLOOR)`` of each albedo
    channel for each row of ``kept`` (M, N): ``(M, 3)``.
    """
    ref = np.maximum(np.abs(w @ albedos), ALBEDO_FLOOR)
    return np.abs(_rescaled(w, kept) @ albedos) / ref


def _mask(n, keep) -> np.ndarray:
    kept = np.zeros(n, dtype=bool)
    kept[np.asarray(keep, dtype=int)] = True
    return kept


def error(w, keep, G) -> float:
    """:func:`errors` of keeping only the materials ``keep``."""
    return float(errors(w, _mask(len(w), keep), G)[0])


def _result(w, keep) -> tuple[Any, Any, float]:
    keep = np.sort(np.asarray(keep, dtype=int))
    w_kept = w[keep]
    if abs(w_kept.sum()) > 0:
        w_kept = w_kept * (w.sum() / w_kept.sum())
    return keep, w_kept, float(np.abs(w).sum() - np.abs(w[keep]).sum())


def prune(w, G, budget) -> tuple[Any, Any, float]:
    """The ``"raw-l2"`` rule: materials to keep so that the raw table changes by at most
    ``budget`` (relative L2).

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
        drop_first = np.tril(np.ones((n, n), dtype=bool), -1)  # row k drops order[:k]
        kept = ~drop_first[:, np.argsort(order)]
        ok = np.flatnonzero(errors(w, kept, G) <= budget)
        if ok.size:
            k = max(k, int(ok.max()))
    k = min(k, n - 1)
    return _result(w, order[k:])


class _Search:
    """State of the greedy search of :func:`prune_image` over the non-zero weights ``w``.

    ``Cs`` (F, m, m): the Gram matrices of the F quadratic bounds, ``budgets`` (F,) their
    relative budgets; ``A`` (m, 3) the albedos, ``albedo_budget`` their relative budget.
    Keeps ``delta`` (the change of the weights), every ``C delta`` and the albedo change up to
    date, so that the bounds after dropping any one more material cost O(F N) for all
    candidates: with ``a = S / S'`` (sums of the kept weights before and after dropping j),
    ``b = a - 1`` and ``e = w_j s / S'``, ``delta' = a delta + b w - e e_j`` (rescaling included).
    """

    def __init__(self, w, Cs, budgets, A, albedo_budget) -> None:
        self.w, self.Cs, self.A = w, Cs, A
        self.s = w.sum()
        self.Cw = Cs @ w  # (F, m)
        self.wCw = np.maximum(self.Cw @ w, 0.0)  # (F,)
        self.wA = w @ A
        self.limit_q = np.asarray(budgets, dtype=np.float64) ** 2 * self.wCw
        self.limit_a = albedo_budget * np.maximum(np.abs(self.wA), ALBEDO_FLOOR)
        self.diag = np.diagonal(Cs, axis1=1, axis2=2)  # (F, m)

    def start(self, kept) -> None:
        """Set the state to keeping the boolean mask ``kept`` (exact, from scratch)."""
        self.kept = kept.copy()
        self.S = self.w[kept].sum()
        self.delta = _rescaled(self.w, kept)[0]
        self.Cd = self.Cs @ self.delta
        self.dCd = self.Cd @ self.delta
        self.dA = self.delta @ self.A

    def _shares(self, q, dA):
        """Largest share of its bound over the quadratic forms ``q`` (F, M) and the albedo changes (M, 3)."""
        lim = self.limit_q[:, None]
        share_q = np.where(
            lim > 0, np.maximum(q, 0.0) / np.where(lim > 0, lim, 1.0), np.where(q > 0, np.inf, 0.0)
        )
        return np.maximum(np.sqrt(share_q.max(axis=0)), np.max(np.abs(dA) / self.limit_a, axis=1))

    def scores(self) -> tuple[np.ndarray, np.ndarray, tuple]:
        """Largest share of its bound after dropping each kept material (and the updates)."""
        j = np.flatnonzero(self.kept)
        wj = self.w[j]
        S1 = self.S - wj
        ok = np.abs(S1) > 1e-12 * np.abs(self.w).sum()
        S1 = np.where(ok, S1, 1.0)
        a = self.S / S1
        b, e = a - 1.0, wj * self.s / S1
        dCw = (self.Cd @ self.w)[:, None]
        q = (
            a * a * self.dCd[:, None]
            + b * b * self.wCw[:, None]
            + e * e * self.diag[:, j]
            + 2 * a * b * dCw
            - 2 * a * e * self.Cd[:, j]
            - 2 * b * e * self.Cw[:, j]
        )
        dA = a[:, None] * self.dA + b[:, None] * self.wA - e[:, None] * self.A[j]
        share = np.where(ok, self._shares(q, dA), np.inf)
        return j, share, (a, b, e, q, dA)

    def run(self) -> np.ndarray:
        """Drop, one at a time, the material whose removal keeps the largest share smallest, while
        that share stays within the bounds and more than one material is kept.
        """
        while np.count_nonzero(self.kept) > 1:
            j, share, (a, b, e, q, dA) = self.scores()
            k = int(np.argmin(share))
            if not share[k] <= _SAFETY:
                break
            jj = j[k]
            self.delta = a[k] * self.delta + b[k] * self.w
            self.delta[jj] -= e[k]
            self.Cd = a[k] * self.Cd + b[k] * self.Cw - e[k] * self.Cs[:, jj]
            self.dCd, self.dA = q[:, k], dA[k]
            self.S -= self.w[jj]
            self.kept[jj] = False
        return self.kept

    def longest_prefix(self, order) -> int:
        """The largest k such that dropping ``order[:k]`` keeps every bound (0 when none does).

        All prefixes at once in O(F N^2) without a matrix product (the cores may be busy): over
        the kept set ``u`` of prefix k, ``u C u``, ``u C w``, ``sum u`` and ``u A`` are suffix
        sums along ``order``.
        """
        w, Cs = self.w[order], self.Cs[:, order][:, :, order]
        M = np.outer(w, w) * Cs

        def tail(v) -> np.ndarray:
            return np.cumsum(v[..., ::-1], axis=-1)[..., ::-1]

        uCu = tail(np.diagonal(M, axis1=1, axis2=2) + 2.0 * np.triu(M, 1).sum(axis=2))
        uCw, S = tail(w * self.Cw[:, order]), tail(w)
        c = np.divide(self.s, S, out=np.zeros_like(S), where=np.abs(S) > 0)  # as _rescaled
        q = c * c * uCu - 2.0 * c * uCw + self.wCw[:, None]
        dA = c[:, None] * tail((w[:, None] * self.A[order]).T).T - self.wA
        ok = self._shares(q, dA) <= _SAFETY
        return int(np.flatnonzero(ok).max()) if ok.any() else 0

    def exact(self) -> bool:
        """Whether the kept set keeps every bound, recomputed from scratch (a guard against the
        round-off of the updates).
        """
        delta = _rescaled(self.w, self.kept)[0]
        return bool(
            ((self.Cs @ delta) @ delta <= self.limit_q).all()
            and (np.abs(delta @ self.A) <= self.limit_a).all()
        )


def prune_image(
    w, C, albedos, budget, albedo_share=ALBEDO_SHARE, G=None, raw_share=RAW_SHARE
) -> tuple[np.ndarray, np.ndarray, float]:
    """The ``"image"`` rule: materials to keep so that each albedo channel changes by at most
    ``albedo_share * budget`` (relative), the cosine-weighted table by at most ``budget``
    (relative L2 in the norm of ``C = T diag(q) T^T``) and, with ``G = T T^T``, the raw table
    by at most ``raw_share * budget``; see the module docstring.

    Zero weights are dropped first (they change nothing); ``budget = 0`` keeps every
    non-zero weight. Among the others: the longest feasible prefix of the order of what
    dropping each alone would change, then greedy single drops while every bound holds.
    At least one material is kept (the first one when every weight is 0). Returns
    ``(keep, w_kept, dropped)`` as :func:`prune`.
    """
    w = np.asarray(w, dtype=np.float64)
    live = np.flatnonzero(w)
    if live.size <= 1 or budget <= 0:
        return _result(w, live if live.size else [0])
    forms, budgets = [C], [budget]
    if G is not None and raw_share is not None and np.isfinite(raw_share):
        forms.append(G)
        budgets.append(raw_share * budget)
    Cs = np.stack([F[np.ix_(live, live)] for F in forms])
    search = _Search(
        w[live], Cs, budgets, np.asarray(albedos, dtype=np.float64)[live], albedo_share * budget
    )
    every = np.ones(live.size, dtype=bool)
    search.start(every)
    order = np.argsort(search.scores()[1], kind="stable")
    kept = every.copy()
    kept[order[: search.longest_prefix(order)]] = False
    search.start(kept)
    search.run()
    return _result(w, live[search.kept] if search.exact() else live)


@dataclass(frozen=True)
class PruneReport:
    """What pruning kept and the bounds it reached (:meth:`Manifold.prune_report`).

    Attributes
    ----------
    rule : str
        ``"image"`` or ``"raw-l2"``.
    budget : float
        The ``prune`` budget the rule was given.
    albedo_budget, cos_budget, raw_budget : float or None
        The bounds it implies on the relative change of each albedo channel and the relative
        cosine-weighted and raw L2 changes of the table (None: not bounded by the rule).
    keep : tuple of int
        Materials kept; ``names`` their names (when known).
    n : int
        Materials in the combination.
    dropped : float
        ``sum |w_i|`` over the dropped materials.
    albedo_change : tuple of 3 float
        Relative change of each albedo channel (None without albedos).
    cos_error, raw_error : float
        Relative cosine-weighted and raw L2 changes of the table (None when not computed).
    """

    rule: str
    budget: float
    albedo_budget: object
    cos_budget: object
    raw_budget: object
    keep: tuple
    n: int
    dropped: float
    albedo_change: object = None
    cos_error: object = None
    raw_error: object = None
    names: tuple = ()

    @property
    def kept(self) -> int:
        """How many materials were kept."""
        return len(self.keep)

    @property
    def within(self) -> bool:
        """Whether every bound of the rule holds."""
        pairs = [
            (self.cos_error, self.cos_budget),
            (self.raw_error, self.raw_budget),
            (None if self.albedo_change is None else max(self.albedo_change), self.albedo_budget),
        ]
        return all(v <= bound for v, bound in pairs if v is not None and bound is not None)

    def __str__(self) -> str:
        parts = [
            f"{self.kept} of {self.n} materials kept ({self.rule} rule, budget {100 * self.budget:.3g}%)"
        ]

        def bound(b) -> str:
            return f" (<= {100 * b:.3g}%)" if b is not None else ""

        if self.albedo_change is not None:
            parts.append(
                "albedo change R/G/B "
                + "/".join(f"{100 * v:.2g}" for v in self.albedo_change)
                + "%"
                + bound(self.albedo_budget)
            )
        if self.cos_error is not None:
            parts.append(
                f"cosine-weighted table error {100 * self.cos_error:.3g}%{bound(self.cos_budget)}"
            )
        if self.raw_error is not None:
            parts.append(f"raw L2 error {100 * self.raw_error:.3g}%{bound(self.raw_budget)}")
        parts.append(f"dropped weight {self.dropped:.4g}")
        return ", ".join(parts)


def report(w, keep, rule, budget, G=None, C=None, albedos=None, names=None) -> PruneReport:
    """The :class:`PruneReport` of keeping ``keep`` of ``w`` under ``rule`` (exact errors from
    the Gram matrices given: raw ``G``, cosine-weighted ``C``; albedo changes from ``albedos``).
    """
    w = np.asarray(w, dtype=np.float64)
    kept = _mask(len(w), keep)
    keep = tuple(int(i) for i in np.flatnonzero(kept))
    alb = None if albedos is None else tuple(float(v) for v in albedo_changes(w, kept, albedos)[0])
    budget = float(budget)
    image = rule == "image"
    return PruneReport(
        rule=rule,
        budget=budget,
        albedo_budget=ALBEDO_SHARE * budget if image else None,
        cos_budget=budget if image else None,
        raw_budget=(RAW_SHARE * budget if np.isfinite(RAW_SHARE) else None) if image else budget,
        keep=keep,
        n=len(w),
        dropped=float(np.abs(w).sum() - np.abs(w[list(keep)]).sum()),
        albedo_change=alb,
        cos_error=None if C is None else float(errors(w, kept, C)[0]),
        raw_error=None if G is None else float(errors(w, kept, G)[0]),
        names=tuple(names[i] for i in keep) if names is not None else (),
    )


def weighted_sum(rows, weights, size, chunk=1 << 18) -> np.ndarray:
    """``sum_k weights[k] * rows[k]`` in float32, one read of each row.

    Loops over chunks of bins outside and rows inside, so the accumulator and the scaled
    chunk stay in cache and no full-size temporary is made.
    """
    rows = [np.asarray(r).reshape(-1) for r in rows]
    weights = np.asarray(weights, dtype=np.float32)
    out = np.zeros(size, dtype=np.float32)
    tmp = np.empty(min(chunk, size), dtype=np.float32)
    for start in range(0, size, chunk):
        acc = out[start : start + chunk]
        t = tmp[: len(acc)]
        for row, wk in zip(rows, weights):
            np.multiply(row[start : start + chunk], wk, out=t)
            acc += t
    return out

"""How good is the material space? Metrics of a fitted manifold as a space to move through.

* :func:`cross_validate` — held-out fidelity: K-fold cross-validation (fit on the rest, project
  each held-out table, :func:`projection.project`), against the nearest training material,
  PCA with k components in the same feature space and the mean material. The baselines come
  exactly, over all bins, from the Gram matrix of all N tables (any subset's centred Gram is
  a sub-block, centred).
* :func:`path_smoothness` — weights (and optionally tonemapped images) along latent segments
  between neighbours; the largest single step's share of the path's length.
* :func:`training_jump` — ``|w(x_i + eps) - e_i|_1`` at every training point.
* :func:`plausibility` — fraction of the latent box with albedo outside [0, 1], negative-bin
  fraction of random points of the box.

Every result is a small dataclass with ``as_dict()`` for JSON reports.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .._util.float32 import weights32
from ..data import gram
from . import projection

if TYPE_CHECKING:
    from typing import Any


#: Feature transforms of the fit (``coslog``: ``log(1 + rho cos(theta_i) cos(theta_o))``).
FEATURES = gram.FEATURES


class _Report:
    def as_dict(self) -> dict[str, Any]:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
        return out


# ------------------------------------------------------------------ features, Gram


def feature_gram(tables, features="log", cos=None, block=gram.BLOCK) -> np.ndarray:
    """Uncentred Gram matrix ``F F^T`` (float64) of the tables in a feature space (:func:`gram.gram`).

    ``tables``: ``(N, d)`` float32 (RGB-concatenated); ``cos``: ``(d / 3,)`` per-bin
    ``cos(theta_i) cos(theta_o)`` for ``coslog``.
    """
    return gram.gram(tables, features, centre=False, cos=cos, block=block).S


def centred(G, idx=None) -> np.ndarray:
    """Centred Gram ``H G H`` of the rows ``idx`` (default all): ``Z Z^T`` of that subset."""
    G = G if idx is None else G[np.ix_(idx, idx)]
    return G - G.mean(0)[None] - G.mean(1)[:, None] + G.mean()


def _cross(G, train, test):
    """``(Z_train z_t)`` for each test row: inner products after subtracting the training mean."""
    Gtt = G[np.ix_(train, train)]
    C = G[np.ix_(train, test)]
    return C - C.mean(0)[None] - Gtt.mean(1)[:, None] + Gtt.mean()


def baseline_errors(G, train, test, d, components=(2, 5)) -> dict[str, Any]:
    """RMS errors (over d values) of the held-out rows: nearest training row, mean, PCA-k.

    Exact, from the Gram matrix ``G`` (uncentred, all rows) of the feature space in which
    the error is measured.

    Returns
    -------
    dict of name -> (len(test),) array; ``nearest`` also gives ``nearest_index``.
    """
    train, test = np.asarray(train), np.asarray(test)
    diag = np.diag(G)
    dist2 = diag[train][:, None] + diag[test][None] - 2 * G[np.ix_(train, test)]
    j = dist2.argmin(axis=0)
    out = {
        "nearest": np.sqrt(np.maximum(dist2[j, np.arange(len(test))], 0) / d),
        "nearest_index": train[j],
    }
    Gtt = G[np.ix_(train, train)]
    zt2 = diag[test] - 2 * G[np.ix_(train, test)].mean(0) + Gtt.mean()
    out["mean"] = np.sqrt(np.maximum(zt2, 0) / d)
    lam, V = np.linalg.eigh(centred(G, train))
    lam, V = lam[::-1], V[:, ::-1]
    proj = V.T @ _cross(G, train, test)  # (n_train, n_test): sqrt(lam_k) * coefficient
    for k in components:
        keep = lam[:k] > 1e-12 * lam[0]
        c2 = (proj[:k][keep] ** 2 / lam[:k][keep, None]).sum(0)
        out[f"pca{k}"] = np.sqrt(np.maximum(zt2 - c2, 0) / d)
    return out


# --------------------------------------------------------------- cross-validation


@dataclass
class HeldOut(_Report):
    """Per held-out material: errors (RMS of log(1 + rho) differences over all bins)."""

    names: list
    error: np.ndarray
    nearest: np.ndarray
    pca_q: np.ndarray
    pca5: np.ndarray
    mean: np.ndarray
    negative_fraction: np.ndarray
    albedo_min: np.ndarray
    albedo_max: np.ndarray
    fit_s: float
    project_s: float
    fold: np.ndarray

    def fold_ratios(self) -> np.ndarray:
        """Median per-material ratio to the nearest training material, fold by fold: how the
        measure varies on sets of held-out materials of the size one check sees.
        """
        ratio = self.error / self.nearest
        return np.array([np.median(ratio[self.fold == f]) for f in np.unique(self.fold)])

    def summary(self) -> dict:
        ratio = self.error / self.nearest
        by_fold = self.fold_ratios()
        return {
            "fold_median_ratios": by_fold.tolist(),
            "worst_fold_median_ratio": float(by_fold.max()),
            "n": len(self.names),
            "median_error": float(np.median(self.error)),
            "worst_error": float(self.error.max()),
            "median_nearest": float(np.median(self.nearest)),
            "median_pca_q": float(np.median(self.pca_q)),
            "median_pca5": float(np.median(self.pca5)),
            "median_mean": float(np.median(self.mean)),
            "beats_nearest": float(np.mean(self.error < self.nearest * (1 - 1e-6))),
            "median_ratio_to_nearest": float(np.median(ratio)),
            "median_error_over_median_nearest": float(
                np.median(self.error) / np.median(self.nearest)
            ),
            "worst_ratio_to_nearest": float(ratio.max()),
            "beats_pca_q": float(np.mean(self.error < self.pca_q)),
            "beats_pca5": float(np.mean(self.error < self.pca5)),
            "median_negative_fraction": float(np.median(self.negative_fraction)),
            "worst_negative_fraction": float(self.negative_fraction.max()),
            "albedo_range": [float(self.albedo_min.min()), float(self.albedo_max.max())],
        }


#: Held-out folds of the cross-validation (:func:`folds`, :func:`cross_validate`).
FOLDS = 10


def folds(n, k=FOLDS, seed=0) -> list[np.ndarray]:
    """``k`` disjoint test folds covering ``range(n)`` (random, fixed seed)."""
    return np.array_split(np.random.default_rng(seed).permutation(n), k)


@dataclass(frozen=True)
class FoldSplit:
    """How :func:`cross_validate` splits the materials into test folds.

    Parameters
    ----------
    k : int
        Number of disjoint test folds.
    seed : int
        Seed of the random permutation the folds are cut from.
    only : tuple of int, optional
        Run only these folds (a quicker, partial estimate); None runs all ``k``.
    """

    k: int = FOLDS
    seed: int = 0
    only: tuple | None = None


def cross_validate(
    tables,
    names,
    fit,
    G_error,
    q,
    albedos,
    *,
    split=None,
    bins=None,
    progress=None,
) -> HeldOut:
    """K-fold held-out fidelity of a manifold configuration.

    Parameters
    ----------
    tables : (N, d) float32
        All tables, loaded once.
    names : list of str
        The N material names.
    fit : callable
        ``fit(train_indices) -> interpolant`` over the training rows (in that order).
    G_error : (N, N)
        Uncentred Gram of ``log(1 + rho)`` (the error's feature space) for the baselines.
    q : int
        Latent dimension (for PCA with k = q).
    albedos : (N, 3)
    split : FoldSplit, optional
        The folds (how many, their seed, which of them to run); default ``FoldSplit()``.
    bins : array of int, optional
        MERL bins the projection searches over (default :func:`projection.search_bins`).
    progress : callable, optional
        Called with each finished fold's index.
    """
    split = FoldSplit() if split is None else split
    n, d = tables.shape
    bins = projection.search_bins(d) if bins is None else bins
    rows: dict[str, list] = {
        f: [] for f in ("error", "negative_fraction", "albedo_min", "albedo_max")
    }
    base: dict[str, list] = {"nearest": [], "pca_q": [], "pca5": [], "mean": []}
    order, fold_of, fit_s, proj_s = [], [], 0.0, 0.0
    for fold, test in enumerate(folds(n, split.k, split.seed)):
        if split.only is not None and fold not in split.only:
            continue
        train = np.setdiff1d(np.arange(n), test)
        t0 = time.perf_counter()
        interp = fit(train)
        fit_s += time.perf_counter() - t0
        be = baseline_errors(G_error, train, test, d, components=sorted({q, 5}))
        for key, src in (
            ("nearest", "nearest"),
            ("pca_q", f"pca{q}"),
            ("pca5", "pca5"),
            ("mean", "mean"),
        ):
            base[key].append(be[src])
        t0 = time.perf_counter()
        for t in test:
            p = projection.project(interp, tables, tables[t], bins=bins, rows=train)
            a = p.weights @ albedos[train]
            rows["error"].append(p.error)
            rows["negative_fraction"].append(p.negative_fraction)
            rows["albedo_min"].append(float(a.min()))
            rows["albedo_max"].append(float(a.max()))
            order.append(t)
            fold_of.append(fold)
        proj_s += time.perf_counter() - t0
        if progress:
            progress(fold)
    return HeldOut(
        names=[names[i] for i in order],
        **{k_: np.asarray(v) for k_, v in rows.items()},
        **{k_: np.concatenate(v) for k_, v in base.items()},
        fit_s=fit_s,
        project_s=proj_s,
        fold=np.asarray(fold_of),
    )


# ------------------------------------------------------------------ smoothness


@dataclass
class Paths(_Report):
    """Largest single step's share of each path's length (weights and, if given, images)."""

    pairs: list
    weight_share: np.ndarray
    image_share: np.ndarray

    def summary(self) -> dict[str, float]:
        out = {
            "n_pairs": len(self.pairs),
            "worst_weight_share": float(self.weight_share.max()),
            "median_weight_share": float(np.median(self.weight_share)),
        }
        if self.image_share.size:
            out.update(
                worst_image_share=float(self.image_share.max()),
                median_image_share=float(np.median(self.image_share)),
            )
        return out


def neighbour_pairs(latent, n_pairs=20, seed=0, include=()) -> list[tuple]:
    """``n_pairs`` pairs (i, nearest latent neighbour of i), i random (fixed seed); ``include`` first."""
    nn = _nearest_neighbour(latent)
    pairs = [tuple(p) for p in include]
    for i in np.random.default_rng(seed).permutation(len(latent)):
        if len(pairs) >= n_pairs:
            break
        p = (int(i), int(nn[i]))
        if p not in pairs and p[::-1] not in pairs:
            pairs.append(p)
    return pairs


def all_neighbour_pairs(latent) -> list:
    """Every pair (i, nearest latent neighbour of i), each once, sorted: the pair set no seed chooses."""
    return sorted({tuple(sorted((i, int(j)))) for i, j in enumerate(_nearest_neighbour(latent))})


def _nearest_neighbour(latent):
    """Index of each latent point's nearest other point."""
    d2 = ((latent[:, None] - latent[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return d2.argmin(axis=1)


def step_share(steps) -> np.ndarray:
    """Largest step over the sum of steps (rows: paths)."""
    total = steps.sum(axis=-1)
    return np.where(total > 0, steps.max(axis=-1) / np.where(total > 0, total, 1), 0.0)


def path_smoothness(interpolant, pairs, steps=40, images=None, base=None, exposure=0.0) -> Paths:
    """Share of the largest of ``steps`` steps along each latent segment between a pair.

    Weight steps are ``|w_{k+1} - w_k|_1``; image steps the RMS over pixels of consecutive
    tonemapped sRGB blends ``base + sum_i w_i images_i`` (``images``: (N, H, W, 3)).
    """
    from ..imaging.io import srgb_encode

    X = interpolant.latent
    t = np.linspace(0.0, 1.0, steps + 1)[:, None]
    ws, ims = [], []
    for i, j in pairs:
        W = interpolant.weights(X[i] + t * (X[j] - X[i]))
        ws.append(np.abs(np.diff(W, axis=0)).sum(axis=1))
        if images is not None:
            flat = weights32(W) @ images.reshape(len(images), -1)
            if base is not None:
                flat += base.reshape(-1)
            enc = srgb_encode(flat * 2.0**exposure)
            ims.append(np.sqrt(np.mean(np.diff(enc, axis=0) ** 2, axis=1)))
    return Paths(
        pairs=[list(p) for p in pairs],
        weight_share=step_share(np.array(ws)),
        image_share=step_share(np.array(ims)) if ims else np.zeros(0),
    )


def training_jump(interpolant, eps=1e-6, seed=0) -> np.ndarray:
    """``|w(x_i + eps u) - e_i|_1`` for every training point (u a random unit direction)."""
    X = interpolant.latent
    u = np.random.default_rng(seed).normal(size=X.shape)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    W = interpolant.weights(X + eps * u)
    return np.abs(W - np.eye(len(X))).sum(axis=1)


# ---------------------------------------------------------------- plausibility


@dataclass
class Plausibility(_Report):
    """Albedo and negativity over the latent box (points' bounding box + margin)."""

    box_low: np.ndarray
    box_high: np.ndarray
    albedo_outside: float
    albedo_range: list
    negative_fraction: np.ndarray
    negative_weights: float

    def summary(self) -> dict:
        return {
            "albedo_outside_fraction": self.albedo_outside,
            "albedo_range": self.albedo_range,
            "median_negative_fraction": float(np.median(self.negative_fraction)),
            "worst_negative_fraction": float(self.negative_fraction.max()),
            "points_with_negative_weights": self.negative_weights,
        }


def latent_box(latent, margin=0.1) -> tuple:
    lo, hi = latent.min(0), latent.max(0)
    pad = margin * (hi - lo)
    return lo - pad, hi + pad


def plausibility(
    interpolant, albedos, tables, n_albedo=4096, n_tables=200, seed=0, chunk=1 << 18
) -> Plausibility:
    """Fraction of the box with any albedo channel outside [0, 1]; negative bins of random points."""
    lo, hi = latent_box(interpolant.latent)
    rng = np.random.default_rng(seed)
    if interpolant.q <= 2:
        side = int(round(np.sqrt(n_albedo)))
        g = [np.linspace(a, b, side) for a, b in zip(lo, hi)]
        P = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, interpolant.q)
    else:
        P = lo + rng.random((n_albedo, interpolant.q)) * (hi - lo)
    A = interpolant.weights(P) @ albedos
    outside = float(np.mean(((A < 0) | (A > 1)).any(axis=1)))
    X = lo + rng.random((n_tables, interpolant.q)) * (hi - lo)
    W = weights32(interpolant.weights(X))
    neg = np.zeros(n_tables)
    d = tables.shape[1]
    for s in range(0, d, chunk):
        neg += ((W @ tables[:, s : s + chunk]) < 0).sum(axis=1)
    return Plausibility(
        box_low=lo,
        box_high=hi,
        albedo_outside=outside,
        albedo_range=[float(A.min()), float(A.max())],
        negative_fraction=neg / d,
        negative_weights=float(np.mean((W < 0).any(axis=1))),
    )


def convex_blend(tables, target) -> np.ndarray:
    """Convex weights of the rows of ``tables`` whose blend is closest to ``target`` in log space.

    The weights ``w`` (each in [0, 1], summing to 1) minimise the mean of
    ``(log(1 + w @ tables) - target)**2`` over the bins where ``w @ tables`` is positive, by SLSQP
    from the first row alone; the first row alone is returned when the optimiser does no better.

    Parameters
    ----------
    tables : ndarray, shape (k, d)
        The tables (or the same bins of each) to blend.
    target : ndarray, shape (d,)
        ``log(1 + table)`` of the table to reach.

    Returns
    -------
    ndarray, shape (k,)
    """
    import scipy.optimize

    A = np.asarray(tables, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    k = len(A)

    def f(w) -> tuple[float, np.ndarray]:
        b = w @ A
        pos = b > 0
        r = np.log1p(np.where(pos, b, 0.0)) - y
        return float(r @ r) / len(y), A @ np.where(
            pos, 2.0 * r / (1.0 + np.where(pos, b, 0.0)), 0.0
        ) / len(y)

    w0 = np.eye(k)[0]
    res = scipy.optimize.minimize(
        f,
        w0,
        jac=True,
        method="SLSQP",
        bounds=[(0.0, 1.0)] * k,
        constraints=[{"type": "eq", "fun": lambda w: w.sum() - 1.0, "jac": lambda w: np.ones(k)}],
        options={"maxiter": 300, "ftol": 1e-12},
    )
    return res.x if res.fun <= f(w0)[0] else w0

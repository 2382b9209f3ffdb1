"""Paths through the material space that move evenly under a perceptual metric.

The paper (Sec. 6, Fig. 9) walks latent segments in 20 equal steps and measures, with the
perceptual distance of [PR12] (:mod:`mitsuba_manifold.data.distance`), how far each
interpolated material is from the two ends; it hopes for "perceptually uniform traversal".
The latent space is not that: with the default convex weights a material barely changes
near its own latent point and then changes quickly, and a segment between materials that
are far apart in latent space crosses others. :func:`path` offers four kinds:

``straight``
    The latent segment ``x(t) = (1 - t) a + t b`` at equal ``t`` (the paper's).
``uniform``
    The same segment at equal *perceptual* steps: dense samples, their cumulative
    perceptual length, inverted (:func:`reparameterise`).
``geodesic``
    A shortest path under the metric pulled back to latent space, staying where the data is:
    Dijkstra on a graph of latent samples laid along the segments between latent neighbours
    (edges weighted by the perceptual distance of their tables, :class:`LatentGraph`), then
    relaxed towards a discrete geodesic (the path energy minimised by L-BFGS with its
    analytic gradient, :func:`minimise_energy`) and re-parameterised at equal perceptual
    steps. The graph is built once per manifold and metric and its edges cached on disk
    (:mod:`latent_graph`).
``faithful``
    Fig. 9's reading made the aim: the geodesic's points moved so that each is as far from the
    two ends as its place along the path says (``d(a, x_k) = t_k d(a, b)`` and ``d(b, x_k) =
    (1 - t_k) d(a, b)`` in the least-squares sense), in even, short steps
    (:func:`faithful_objective`, :func:`faithful`): a morph that stays between its two materials
    instead of passing through a third that is far from both.

The metric on latent points is ``d(x, y) = d_PR12(table(x), table(y))`` with ``table(x) =
sum_i w_i(x) table_i`` (the manifold's weights, unpruned, clamped at 0 as the plugin does).
Searches use a :class:`~mitsuba_manifold.data.distance.Quadrature` on a sub-grid of bins
(:data:`SEARCH_STRIDE`: every 3rd ``theta_h`` bin, every 10th ``theta_d``, every 15th
``phi_d``: 8 010 values a table at MERL resolution, 1/546 of them; how close its distances
are to the full grid's is in ``docs/benchmarks.md``); ``tools/bench.py fig9`` measures the
paths on the full grid, ``tools/bench.py paths`` their speed.

Speed (an explorer scrubs paths): a path's products are small, so BLAS runs on one thread
(:func:`~mitsuba_manifold._util.blas.one_thread`); the sub-grid's table values and the graph's edges are cached on
disk by content hash (:mod:`latent_graph`), so a fresh process reads neither the tables
nor their hashes; :func:`even` evaluates only the points it adds.
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING

import numpy as np

from .._util.blas import one_thread
from .._util.float32 import weights32
from ..data.distance import Quadrature, gram_distances
from ..errors import InputError, UnavailableError
from . import latent_graph
from .latent_graph import LatentGraph

if TYPE_CHECKING:
    from typing import Any


KINDS = ("straight", "uniform", "geodesic", "faithful")
#: The kind ``Manifold.path``, ``blend.py --path``, the explorer and the main job's contact sheet
#: use: the one whose points stay between the two ends (the paper's Fig. 9 measures, ``tools/bench.py
#: fig9``); where the geodesic already does, it is the geodesic.
DEFAULT_KIND = "faithful"
#: Sub-grid of the searches (see the module doc; its Fig. 9 measures on the built-in database:
#: ``benchmarks/results/fig9_default.json``).
SEARCH_STRIDE = (3, 10, 15)
#: Table values below which the cube root's slope is capped (in :meth:`PathMetric.pullback`).
FLOOR = 1e-6
#: Samples of a segment when re-parameterising it by perceptual length.
DENSE = 129
#: Points a faithful path is relaxed at (at least; Fig. 9's 20 steps), and L-BFGS iterations.
FAITHFUL_POINTS, FAITHFUL_ITERATIONS = 21, 200
#: The :func:`fig9_gap` up to which a faithful path is the geodesic itself.
FAITHFUL_TOLERANCE = 0.1
#: Weight and power of the evenness term of :func:`faithful_objective`, and the weight of its length term.
EVENNESS, EVEN_POWER = 2e-3, 8
LENGTH = 0.01
#: Samples of a geodesic's candidates (compared by length, then refined where coarse by :func:`even`).
CHECK = 65

_METRICS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


class PathMetric:
    """The perceptual metric pulled back to the latent space of ``manifold``.

    ``features(X)`` are the :class:`Quadrature` features of the tables at latent points ``X``
    (their Euclidean distances are the [PR12]-style distances); ``distances(X, Y)`` the matrix
    of distances, in blocks of bins (any stride, the full grid included).

    On a sub-grid the metric holds only the tables' values at its bins, ``rows`` (N, size):
    read from the database's cache folder when a previous process made them
    (:func:`latent_graph.cached`, named by the manifold's content hash), so that neither the
    tables nor their hashes are read again; ``tables`` (the
    manifold's full ``(N, d)`` stack) skips the cache; ``rows`` (the tables already restricted to
    the sub-grid, e.g. the explorer's preview tables) skips both. Features are float32 (the
    combination ``w @ rows`` is float32 as the plugin's), sums of squares float64.
    """

    def __init__(self, manifold, stride=SEARCH_STRIDE, tables=None, rows=None) -> None:
        self._manifold = lambda: manifold  # :meth:`of` holds it weakly instead
        dims = tuple(manifold.record.dims)
        self.quad = Quadrature.of(dims, stride)
        self._small = self.quad.size * 4 <= 3 * int(np.prod(dims))
        if rows is not None:
            if not self._small or np.shape(rows) != (manifold.n, self.quad.size):
                raise InputError(
                    f"`rows` of shape {np.shape(rows)}: expected ({manifold.n}, {self.quad.size}),"
                    " the tables at the bins of a sub-grid"
                )
            self.rows = np.ascontiguousarray(rows, dtype=np.float32)
        elif not self._small:
            self.rows = manifold.tables() if tables is None else tables
        elif tables is not None:
            self.rows = self._pick(tables)
        else:
            self.rows = latent_graph.cached(
                self,
                "pathrows-v1",
                lambda: self._pick(manifold.tables()),
                shape=(manifold.n, self.quad.size),
                dtype=np.float32,
            )
        # F = scale cbrt(v cos) = coef cbrt(v): the per-bin constant once
        self.coef = (self.quad.scale * np.cbrt(self.quad.cos)).astype(np.float32)
        self._graph: LatentGraph | None = None

    def _pick(self, full) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(full)[:, self.quad.index], dtype=np.float32)

    @property
    def manifold(self) -> Any:  # a Manifold (model imports this module)
        """The :class:`~.model.Manifold` whose metric this is."""
        m = self._manifold()
        if m is None:
            raise UnavailableError(
                "the manifold of this path metric no longer exists; take paths from the "
                "manifold (Manifold.path), or keep the manifold while its metric is used"
            )
        return m

    @classmethod
    def of(cls, manifold, stride=SEARCH_STRIDE) -> PathMetric:
        """The metric of ``manifold`` for ``stride``, built once and kept while the manifold lives
        with the same materials (it holds the manifold weakly: the cache keeps no manifold alive;
        a material added since it was built makes a new one).
        """
        cache = _METRICS.setdefault(manifold, {})
        key = (tuple(int(s) for s in stride), manifold.n, tuple(manifold.names))
        if key not in cache:
            for old in [k for k in cache if k[1:] != key[1:]]:  # of the materials before an add
                del cache[old]
            metric = cls(manifold, key[0])
            metric._manifold = weakref.ref(manifold)
            cache[key] = metric
        return cache[key]

    def weights(self, X) -> np.ndarray:
        """The manifold's weights at latent points ``X`` as float32 operands (:func:`weights32`)."""
        return weights32(self.manifold.weights(np.atleast_2d(X)).w)

    def features(self, X) -> np.ndarray:
        """Features ``(M, size)`` float32 of the tables at latent points ``X`` (M, q) (sub-grids only)."""
        if not self._small:
            raise InputError(
                "features of every bin do not fit a search; use `distances` on the full grid"
            )
        V = self.weights(X) @ self.rows
        return np.cbrt(np.maximum(V, 0.0, out=V), out=V) * self.coef

    def distances(self, X, Y=None) -> np.ndarray:
        """``(M, K)`` perceptual distances between the tables at ``X`` and at ``Y`` (default ``X``)."""
        W = self.weights(X if Y is None else np.concatenate([np.atleast_2d(X), np.atleast_2d(Y)]))
        m = len(np.atleast_2d(X))

        def split(F) -> tuple:
            return (F, F) if Y is None else (F[:m], F[m:])

        if self._small:
            return gram_distances([split(self.quad.features(W @ self.rows))])
        # blocks of the full table are contiguous spans of its columns: multiply a view, then pick
        parts = (
            split(
                p.features(
                    (W @ self.rows[:, p.index[0] : p.index[-1] + 1])[:, p.index - p.index[0]]
                )
            )
            for p in self.quad.blocks()
        )
        return gram_distances(parts)

    def energy(self, X) -> tuple[float, Any]:
        """Discrete path energy ``E = sum_k |F(x_k+1) - F(x_k)|^2`` of the polyline ``X`` (M, q) and
        its gradient ``dE/dX`` (M, q), analytic (:meth:`pullback`).
        """
        V = self.weights(X) @ self.rows
        D = np.diff(np.cbrt(np.maximum(V, 0.0)) * self.coef, axis=0)
        G = np.zeros_like(V)
        G[:-1] -= 2.0 * D
        G[1:] += 2.0 * D
        return float(np.einsum("mk,mk->", D, D, dtype=np.float64)), self.pullback(X, G, V)

    def pullback(self, X, G, V=None) -> np.ndarray:
        """The gradient ``dE/dX`` (M, q) of a function ``E`` of the features at ``X`` (M, q), from
        its gradient ``G = dE/dF`` (M, size): the chain rule through the cube root, the table
        combination and the interpolant's Jacobian ``dw/dx`` (the cube root's slope capped where
        a table value is below :data:`FLOOR`). ``V``: the combined table values at ``X`` when known.
        """
        if V is None:
            V = self.weights(X) @ self.rows
        C = np.cbrt(np.maximum(V, 0.0))
        # dF/dv = coef / (3 cbrt(v)^2) where v > 0
        C = np.maximum(C, np.float32(FLOOR ** (1.0 / 3.0)), out=C)
        G = np.asarray(G, dtype=np.float32) * np.where(
            V > 0, self.coef / (3.0 * C * C), np.float32(0.0)
        )
        dW = (self.rows @ G.T).T.astype(
            np.float64
        )  # this order: faster than G @ rows.T in OpenBLAS
        J = self.manifold.weights_jacobian(X)
        return np.einsum("mn,mnq->mq", dW, J)

    def steps(self, X) -> np.ndarray:
        """Perceptual lengths of the ``M - 1`` steps of the polyline ``X``."""
        if self._small:
            return step_lengths(self.features(X))
        return np.diag(self.distances(X), 1).copy()

    def graph(self) -> LatentGraph:
        """The :class:`LatentGraph` of this metric (built on first use; its edges cached on disk)."""
        if self._graph is None:
            self._graph = LatentGraph.build(self)
        return self._graph


def step_lengths(F) -> np.ndarray:
    """Euclidean lengths of the steps between consecutive rows of ``F`` (sums in float64)."""
    D = np.diff(F, axis=0)
    return np.sqrt(np.einsum("mk,mk->m", D, D, dtype=np.float64))


def endpoint(manifold, v, what) -> np.ndarray:
    """A path end (material name or ``q`` numbers) as a latent point."""
    if isinstance(v, str):
        return manifold.latent[manifold.index(v)].copy()
    try:
        arr = np.asarray(v, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.size != manifold.q or not np.isfinite(arr).all():
        raise InputError(
            f"`{what}` {v!r:.60}: expected a material name or {manifold.q} finite numbers"
        )
    return arr


def reparameterise(X, lengths, steps) -> np.ndarray:
    """``steps`` points along the polyline ``X`` (M, q) at equal cumulative perceptual length.

    ``lengths``: the ``M - 1`` step lengths. Between samples the latent position is linear in
    the length (the polyline is dense enough that the metric is locally linear).
    """
    s = np.concatenate([[0.0], np.cumsum(lengths)])
    if s[-1] <= 0:
        return np.linspace(0, 1, steps)[:, None] * (X[-1] - X[0]) + X[0]
    return _at_length(X, s, np.linspace(0.0, s[-1], steps))


def even(metric, X, steps, fraction=0.1, passes=8, polish=20, F=None) -> np.ndarray:
    """``steps`` points along the polyline ``X`` at equal perceptual steps.

    The polyline is refined first: every piece longer than ``fraction`` of an even step is
    split at its latent midpoint (up to ``passes`` times), so that the metric is nearly linear
    on each piece where the material changes fast (a weight switching over a short latent
    distance), and its cumulative length is inverted (:func:`reparameterise`). Equal lengths
    along the path are not yet equal *steps* (distances between consecutive points) where the
    path turns back within a step, as it does passing a third material's latent point; up to
    ``polish`` rounds then rescale each step's share of the length by ``mean / step`` (the
    most even points seen are kept). ``F``: the features of ``X`` when known (on a sub-grid only
    the new midpoints are evaluated).
    """
    track = metric._small
    if track and F is None:
        F = metric.features(X)
    lengths = step_lengths(F) if track else metric.steps(X)
    for _ in range(passes):
        long = lengths > fraction * lengths.sum() / (steps - 1)
        if not long.any():
            break
        mids = 0.5 * (X[:-1][long] + X[1:][long])
        order = np.argsort(
            np.concatenate([np.arange(len(X)), np.flatnonzero(long) + 0.5]), kind="stable"
        )
        X = np.concatenate([X, mids])[order]
        if track:
            F = np.concatenate([F, metric.features(mids)])[order]
        lengths = step_lengths(F) if track else metric.steps(X)
    s = np.concatenate([[0.0], np.cumsum(lengths)])
    if s[-1] <= 0:
        return reparameterise(X, lengths, steps)
    return _polish(metric, X, s, steps, polish)


def _polish(metric, X, s, steps, rounds):
    """The most even ``steps`` points of up to ``rounds`` rescalings along ``X`` (lengths ``s``): :func:`even`."""
    u = np.linspace(0.0, 1.0, steps)
    best, best_spread = None, np.inf
    for _ in range(rounds + 1):
        P = _at_length(X, s, u * s[-1])
        c = metric.steps(P)
        spread = np.abs(c / c.mean() - 1).max()
        if spread < best_spread:
            best, best_spread = P, spread
        if spread < 1e-3 or not (c > 0).all():
            break
        du = np.diff(u) * (c.mean() / c) ** 0.5
        u = np.concatenate([[0.0], np.cumsum(du / du.sum())])
    return best


def _at_length(X, s, target) -> np.ndarray:
    """Points of the polyline ``X`` (cumulative lengths ``s``) at lengths ``target``, ends exact."""
    k = np.clip(np.searchsorted(s, target, side="right") - 1, 0, len(X) - 2)
    span = s[k + 1] - s[k]
    frac = np.clip(np.where(span > 0, (target - s[k]) / np.where(span > 0, span, 1), 0.0), 0, 1)
    out = X[k] + frac[:, None] * (X[k + 1] - X[k])
    out[0], out[-1] = X[0], X[-1]
    return out


def densify(X, n) -> np.ndarray:
    """``n`` points along the latent polyline ``X``, equally spaced in latent length."""
    seg = np.linalg.norm(np.diff(X, axis=0), axis=1)
    return reparameterise(X, seg, n) if seg.sum() > 0 else np.repeat(X[:1], n, axis=0)


def straight(xa, xb, steps) -> np.ndarray:
    """The latent segment from ``xa`` to ``xb`` at ``steps`` equal steps of ``t`` (``t = 0..1``), ends exact."""
    X = xa + np.linspace(0.0, 1.0, steps)[:, None] * (xb - xa)
    X[-1] = xb
    return X


def uniform(metric, xa, xb, steps, dense=DENSE) -> np.ndarray:
    """The latent segment at equal perceptual steps (``dense`` samples, arc-length inversion)."""
    return even(metric, straight(xa, xb, max(dense, steps)), steps)


def minimise_energy(metric, X, iterations=200) -> np.ndarray:
    """The polyline ``X`` with its interior points moved to minimise :meth:`PathMetric.energy`
    (L-BFGS; its minimisers are discrete geodesics at constant speed), ends fixed.
    """
    import scipy.optimize

    xa, xb, q = X[0], X[-1], X.shape[1]

    def fun(flat) -> tuple:
        Y = np.concatenate([xa[None], flat.reshape(-1, q), xb[None]])
        e, g = metric.energy(Y)
        return e, g[1:-1].ravel()

    res = scipy.optimize.minimize(
        fun, X[1:-1].ravel(), jac=True, method="L-BFGS-B", options={"maxiter": iterations}
    )
    return np.concatenate([xa[None], res.x.reshape(-1, q), xb[None]])


def geodesic(metric, xa, xb, steps, points=17, iterations=25, dense=CHECK) -> np.ndarray:
    """A shortest path from ``xa`` to ``xb``, at equal perceptual steps.

    Two starts, the latent segment and the shortest path through the :class:`LatentGraph`,
    each at ``points`` equal perceptual steps, relaxed by :func:`minimise_energy`; the
    shortest of the four paths (relaxed or not) under the metric, measured on ``dense``
    samples, wins (so a geodesic is never longer than the segment) and is spaced evenly by
    :func:`even`, which refines those samples where they are coarse.
    """
    best, best_length = None, np.inf
    for start in (straight(xa, xb, 2), metric.graph().shortest(metric, xa, xb)):
        X = even(metric, densify(start, dense), points)
        for cand in (X, minimise_energy(metric, X, iterations)):
            Xd = densify(cand, dense)
            Fd = metric.features(Xd)
            length = step_lengths(Fd).sum()
            if length < best_length:
                best, best_length = (Xd, Fd), length
    return even(metric, best[0], steps, F=best[1])


def faithful_objective(metric, X, evenness=EVENNESS, power=EVEN_POWER, length=LENGTH) -> tuple:
    """The objective of a faithful path ``X`` (M, q) from ``a = x_0`` to ``b = x_K`` (``K = M - 1``)
    and its gradient ``dE/dX`` (M, q), analytic (:meth:`PathMetric.pullback`; zero at the ends,
    which are held)::

        E = 1/K sum_k [(d(a, x_k) / d(a, b) - t_k)^2 + (d(b, x_k) / d(a, b) - (1 - t_k))^2]
            + evenness / K sum_k (s_k / s)^power + length K sum_k s_k^2 / d(a, b)^2

    with ``t_k = k / K``, ``s_k`` the perceptual step from ``x_k`` to ``x_k+1`` and ``s`` their
    mean: the first sum is the squared gap of the paper's Fig. 9 curves from its diagonals (each
    point as far from the ends as its place along the path says), the second keeps the steps
    even (a high power: it lets steps vary a little and forbids a jump), the third, the path
    energy over that of the straight chord (the square of the length ratio at even steps),
    keeps the path from zigzagging between points that each sit well.
    """
    V = metric.weights(X) @ metric.rows
    F = (np.cbrt(np.maximum(V, 0.0)) * metric.coef).astype(np.float64)
    K = len(X) - 1
    t = np.linspace(0.0, 1.0, K + 1)
    G = np.zeros_like(F)
    d = np.linalg.norm(F[-1] - F[0])
    value = 0.0
    for end, target in ((F[0], t), (F[-1], 1.0 - t)):
        diff = F - end
        dist = np.sqrt(np.einsum("mk,mk->m", diff, diff))
        r = dist / d - target
        value += float(r @ r) / K
        G += (2.0 * r / (K * d * np.maximum(dist, 1e-300)))[:, None] * diff
    D = np.diff(F, axis=0)
    s = np.sqrt(np.einsum("mk,mk->m", D, D)) + 1e-300
    u = s / s.mean()
    value += evenness * float(np.sum(u**power)) / K + length * K * float(s @ s) / d**2
    # d/ds_j of the evenness term: evenness power / S (u_j^(power-1) - mean(u^power)), S = sum s
    gs = (
        evenness * power / s.sum() * (u ** (power - 1) - np.mean(u**power))
        + 2 * length * K * s / d**2
    )
    gD = (gs / s)[:, None] * D
    G[:-1] -= gD
    G[1:] += gD
    G[[0, -1]] = 0.0  # the ends are held
    return value, metric.pullback(X, G, V)


def fig9_gap(F) -> float:
    """The largest gap of the paper's Fig. 9 curves from their diagonals for points of features
    ``F`` (M, size) from ``a = F[0]`` to ``b = F[-1]``: ``max_k |d(a, x_k) / d(a, b) - t_k|`` and
    ``|d(b, x_k) / d(a, b) - (1 - t_k)|``, ``t_k = k / (M - 1)``.
    """
    F = np.asarray(F, dtype=np.float64)
    t = np.linspace(0.0, 1.0, len(F))
    d = np.linalg.norm(F[-1] - F[0])
    if d <= 0:
        return 0.0
    gap_a = np.abs(np.linalg.norm(F - F[0], axis=1) / d - t).max()
    return float(max(gap_a, np.abs(np.linalg.norm(F - F[-1], axis=1) / d - (1 - t)).max()))


def faithful(
    metric, xa, xb, steps, iterations=FAITHFUL_ITERATIONS, tolerance=FAITHFUL_TOLERANCE
) -> np.ndarray:
    """A path from ``xa`` to ``xb`` whose every point is as far from the ends as its place along
    the path says, in even steps: the :func:`geodesic` at ``n = (steps - 1) k + 1`` points (the
    smallest ``k`` with ``n >= FAITHFUL_POINTS``) where its :func:`fig9_gap` is at most
    ``tolerance`` (it is faithful already, and the most even); otherwise its interior points
    moved to minimise :func:`faithful_objective` (L-BFGS, ends fixed), kept where that lowers the
    gap. Every ``k``-th point is returned: points of the relaxed path itself, each at its own
    place ``t``, so their gap is at most the whole path's.
    """
    import scipy.optimize

    steps = int(steps)
    k = max(1, -(-(FAITHFUL_POINTS - 1) // (steps - 1)))
    n = (steps - 1) * k + 1
    X = geodesic(metric, xa, xb, n)
    gap = fig9_gap(metric.features(X))
    if gap > tolerance:
        q = X.shape[1]

        def fun(flat) -> tuple:
            Y = np.concatenate([xa[None], flat.reshape(-1, q), xb[None]])
            e, g = faithful_objective(metric, Y)
            return e, g[1:-1].ravel()

        res = scipy.optimize.minimize(
            fun, X[1:-1].ravel(), jac=True, method="L-BFGS-B", options={"maxiter": iterations}
        )
        Y = np.concatenate([xa[None], res.x.reshape(-1, q), xb[None]])
        if fig9_gap(metric.features(Y)) < gap:
            X = Y
    return X[::k]


def path(manifold, a, b, steps=21, kind=DEFAULT_KIND, metric=None) -> np.ndarray:
    """``steps`` latent points from ``a`` to ``b`` (material names or latent points), of ``kind``.

    See the module doc for the kinds. ``metric``: a :class:`PathMetric` (default: the
    manifold's, on the search sub-grid, built once). Returns ``(steps, q)``; row 0 is ``a``'s
    latent point and the last row ``b``'s.
    """
    if kind not in KINDS:
        raise InputError(f"`kind` {kind!r} is not a path kind; use one of {', '.join(KINDS)}")
    if not isinstance(steps, (int, np.integer)) or isinstance(steps, bool) or steps < 2:
        raise InputError(f"`steps` must be an integer >= 2, got {steps!r}")
    xa, xb = endpoint(manifold, a, "a"), endpoint(manifold, b, "b")
    if kind == "straight" or np.array_equal(xa, xb):
        return straight(xa, xb, steps)
    with one_thread():
        metric = metric or PathMetric.of(manifold)
        kinds = {"uniform": uniform, "geodesic": geodesic, "faithful": faithful}
        return kinds[kind](metric, xa, xb, steps)


def latent_distance(manifold, x, y, stride=(1, 1, 1)) -> Any:
    """:meth:`Manifold.distance`: ``d`` between the tables at ``x`` and ``y`` (names, points or stacks)."""
    X, x_single = _points(manifold, x, "x")
    Y, y_single = _points(manifold, y, "y")
    D = PathMetric.of(manifold, stride).distances(X, Y)
    if x_single and y_single:
        return float(D[0, 0])
    if x_single or y_single:
        return D[0] if x_single else D[:, 0]
    return D


def _points(manifold, v, what) -> tuple[Any, bool]:
    """``v`` (a name, a point or a stack of points) as ``(M, q)`` and whether it was one."""
    if isinstance(v, str):
        return endpoint(manifold, v, what)[None], True
    arr = (
        np.asarray(v, dtype=np.float64)
        if not isinstance(v, (list, tuple)) or not v or not isinstance(v[0], str)
        else np.stack([endpoint(manifold, n, what) for n in v])
    )
    if arr.ndim == 1:
        return endpoint(manifold, arr, what)[None], True
    if arr.ndim != 2 or arr.shape[1] != manifold.q or not np.isfinite(arr).all():
        raise InputError(
            f"`{what}` must be a material name, {manifold.q} numbers or (M, {manifold.q}) points, "
            f"got shape {arr.shape}"
        )
    return arr, False

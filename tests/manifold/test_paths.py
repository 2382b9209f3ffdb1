"""Paths through the space: Manifold.distance, the straight, uniform, geodesic and faithful kinds."""

import os

import numpy as np
import pytest

from mitsuba_manifold.data import distance
from mitsuba_manifold.errors import InputError
from mitsuba_manifold.manifold import paths
from mitsuba_manifold.manifold.model import Manifold


@pytest.fixture(scope="module")
def m(small_manifold):
    """The default preset (convex Shepard weights), q = 2, on the 8 small materials."""
    return Manifold.load(small_manifold)


@pytest.fixture(scope="module")
def pair(m):
    """Two materials far apart in latent space (the segment between them crosses others)."""
    d = np.linalg.norm(m.latent[:, None] - m.latent[None], axis=-1)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    return m.names[i], m.names[j]


def test_manifold_distance_is_the_table_distance_of_the_interpolated_materials(m):
    rng = np.random.default_rng(0)
    x, y = m.latent[0] + 0.1 * rng.normal(size=m.q), m.latent[3] + 0.1 * rng.normal(size=m.q)
    tx = m.combine(m.weights(x).w, prune=0.0).table
    ty = m.combine(m.weights(y).w, prune=0.0).table
    assert m.distance(x, y) == pytest.approx(distance.brdf_distance(tx, ty), rel=1e-5)
    assert m.distance(x, x) == 0.0
    assert m.distance(x, y) == pytest.approx(m.distance(y, x), rel=1e-9)
    # names are their latent points; stacks give vectors and matrices
    assert m.distance(m.names[1], m.names[2]) == pytest.approx(
        m.distance(m.latent[1], m.latent[2]), rel=1e-9
    )
    D = m.distance(m.latent, m.latent)
    assert D.shape == (m.n, m.n) and np.all(np.diag(D) == 0.0)
    assert m.distance(m.latent, m.names[0]).shape == (m.n,)
    with pytest.raises(InputError, match="`x`"):
        m.distance([1.0] * (m.q + 1), m.names[0])
    with pytest.raises(InputError, match="unknown material"):
        m.distance("adamantium", m.names[0])


def test_straight_is_the_latent_segment(m, pair):
    X = m.path(*pair, steps=21, kind="straight")
    xa, xb = m.latent[m.index(pair[0])], m.latent[m.index(pair[1])]
    assert X.shape == (21, m.q)
    assert np.allclose(X, xa + np.linspace(0, 1, 21)[:, None] * (xb - xa))


def test_uniform_steps_are_equal_within_5_percent(m, pair):
    X = m.path(*pair, steps=21, kind="uniform")
    metric = paths.PathMetric.of(m)
    s = metric.steps(X)
    assert np.abs(s / s.mean() - 1).max() < 0.05, s / s.mean()
    # on the segment: every point is on the latent line from a to b, in order
    xa, xb = X[0], X[-1]
    t = (X - xa) @ (xb - xa) / np.dot(xb - xa, xb - xa)
    assert np.allclose(xa + t[:, None] * (xb - xa), X, atol=1e-9) and (np.diff(t) > 0).all()
    # the straight segment's steps are not even (what uniform fixes)
    s0 = metric.steps(m.path(*pair, steps=21, kind="straight"))
    assert s0.max() / s0.mean() > 1.2


def test_a_geodesic_is_never_longer_than_the_straight_segment(m):
    metric = paths.PathMetric.of(m)

    def length(X):
        Xd = paths.densify(X, 257)
        return metric.steps(Xd).sum()

    d = np.linalg.norm(m.latent[:, None] - m.latent[None], axis=-1)
    order = np.dstack(np.unravel_index(np.argsort(-d, axis=None), d.shape))[0]
    for i, j in [p for p in order if p[0] < p[1]][:3]:
        a, b = m.names[i], m.names[j]
        G = m.path(a, b, steps=21, kind="geodesic")
        assert np.array_equal(G[0], m.latent[i]) and np.array_equal(G[-1], m.latent[j])
        assert length(G) <= length(m.path(a, b, steps=2, kind="straight")) * (1 + 1e-3)
        s = metric.steps(G)
        assert s.max() / s.sum() < 0.1  # even steps along it too


def test_the_path_energy_gradient_is_the_derivative_of_the_energy(m):
    metric = paths.PathMetric.of(m)
    X = paths.straight(m.latent[0], m.latent[4], 7) + np.array([0.03, -0.02])
    e, g = metric.energy(X)
    h = 1e-5
    for k, c in [(2, 0), (3, 1), (5, 0)]:
        up, down = X.copy(), X.copy()
        up[k, c] += h
        down[k, c] -= h
        fd = (metric.energy(up)[0] - metric.energy(down)[0]) / (2 * h)
        # a component near zero is judged on the gradient's scale (the differences' rounding)
        assert g[k, c] == pytest.approx(fd, rel=0.05, abs=1e-3 * np.abs(g).max())


def test_reparameterise_inverts_the_cumulative_length():
    X = np.linspace(0, 1, 101)[:, None] ** 2 * np.array([[2.0, 0.0]])  # speed grows with t
    lengths = np.linalg.norm(np.diff(X, axis=0), axis=1)
    Y = paths.reparameterise(X, lengths, 11)
    assert np.allclose(np.diff(Y[:, 0]), 0.2, atol=1e-9)


def test_paths_between_points_and_the_errors(m, pair):
    x = m.latent[m.index(pair[0])] + 0.05
    X = m.path(x, pair[1], steps=5, kind="uniform")
    assert np.allclose(X[0], x) and X.shape == (5, m.q)
    assert np.allclose(m.path(x, x, steps=3, kind="geodesic"), x)
    with pytest.raises(InputError, match="`kind`"):
        m.path(*pair, kind="scenic")
    with pytest.raises(InputError, match="`steps`"):
        m.path(*pair, steps=1)
    with pytest.raises(InputError, match="`b`"):
        m.path(pair[0], [0.0] * (m.q + 2))
    assert paths.DEFAULT_KIND in paths.KINDS
    assert m.path(*pair, steps=4).shape == (4, m.q)  # the default kind


def test_rows_and_graph_are_cached_by_the_manifolds_content(small_manifold, tmp_path):
    """A fresh load reads the metric's rows and the graph's edges from the database's cache
    folder (named by a content hash) without reading the tables; they equal a cache-less build."""
    from mitsuba_manifold.manifold import latent_graph

    first = Manifold.load(small_manifold)
    metric = paths.PathMetric.of(first)
    built = metric.graph()
    fresh = Manifold.load(small_manifold)
    again = paths.PathMetric(fresh)
    assert fresh._tables is None  # rows from the cache: the tables were not read
    assert np.array_equal(again.rows, metric.rows)
    graph = latent_graph.LatentGraph.build(again)
    direct = latent_graph.LatentGraph.build(again, cache=False)
    assert fresh._tables is None
    assert np.array_equal(graph.nodes, direct.nodes) and np.array_equal(built.nodes, direct.nodes)
    assert abs(graph.graph - built.graph).max() == 0.0  # the cached edges, exactly
    assert (
        abs(graph.graph - direct.graph).max() <= 1e-6 * direct.graph.max()
    )  # float32 products' rounding
    # symmetric, every edge once: a latent segment's consecutive nodes are one edge of its distance
    assert abs(direct.graph - direct.graph.T).max() == 0.0
    i, j = direct.graph.nonzero()
    k = np.argmax(i != j)
    d = np.linalg.norm(
        np.diff(again.features(direct.nodes[[i[k], j[k]]]).astype(np.float64), axis=0)
    )
    assert direct.graph[i[k], j[k]] == pytest.approx(d + 1e-12, rel=1e-5)
    # another interpolant, another key; a moved database is not created by the cache
    other = Manifold.load(small_manifold)
    other.interpolant.taper = other.interpolant.taper * 2
    assert latent_graph.cache_key(paths.PathMetric(other), "x") != latent_graph.cache_key(
        again, "x"
    )
    other.database = str(tmp_path / "gone")
    assert latent_graph.cache_folder(other) is None and not os.path.exists(other.database)


def _fig9_gaps(metric, X):
    """Fig. 9's curves' largest gap from their diagonals and the largest step's share of the length."""
    D = metric.distances(X)
    t = np.linspace(0, 1, len(X))
    d = D[0, -1]
    gap = max(np.abs(D[0] / d - t).max(), np.abs(D[-1] / d - (1 - t)).max())
    s = np.diag(D, 1)
    return gap, s.max() / s.sum()


@pytest.fixture(scope="module")
def unstressed(small_db):
    """The same materials laid out without the stress term: the geodesic between the two
    furthest apart strays from Fig. 9's diagonals there."""
    return Manifold.fit(small_db, q=2, stress=0.0)


def test_a_faithful_path_keeps_each_point_where_its_place_says_in_even_steps(unstressed):
    """Between the two materials furthest apart in latent space, whose geodesic strays from
    Fig. 9's diagonals, the faithful path's points are closer to them (each as far from the ends
    as its place along the path says) and its steps stay even; its ends are the materials', other
    step counts read it; between the nearest two, whose geodesic is faithful already, it is the
    faithful path."""
    m = unstressed
    d = np.linalg.norm(m.latent[:, None] - m.latent[None], axis=-1)
    pair = [m.names[i] for i in np.unravel_index(np.argmax(d), d.shape)]
    metric = paths.PathMetric.of(m)
    gap_geodesic, _ = _fig9_gaps(metric, m.path(*pair, steps=21, kind="geodesic"))
    assert gap_geodesic > paths.FAITHFUL_TOLERANCE
    F = m.path(*pair, steps=21, kind="faithful")
    gap, largest = _fig9_gaps(metric, F)
    assert gap < 0.75 * gap_geodesic, (gap, gap_geodesic)
    assert largest < 0.1
    assert np.array_equal(F[0], m.latent[m.index(pair[0])])
    assert np.array_equal(F[-1], m.latent[m.index(pair[1])])
    F6 = m.path(*pair, steps=6, kind="faithful")
    assert F6.shape == (6, m.q) and np.allclose(F6, F[::4])
    # a step count that does not divide the relaxed points' reads points of a finer relaxed path,
    # each at its own place (no point between two of them, which could be another material)
    F20, F39 = (m.path(*pair, steps=s, kind="faithful") for s in (20, 39))
    assert F20.shape == (20, m.q) and np.array_equal(F20, F39[::2])
    assert _fig9_gaps(metric, F20)[0] <= _fig9_gaps(metric, F39)[0] + 1e-12
    d = np.linalg.norm(m.latent[:, None] - m.latent[None], axis=-1) + np.diag([np.inf] * m.n)
    near = [m.names[i] for i in np.unravel_index(np.argmin(d), d.shape)]
    G = m.path(*near, steps=21, kind="geodesic")
    assert _fig9_gaps(metric, G)[0] < paths.FAITHFUL_TOLERANCE
    assert np.array_equal(m.path(*near, steps=21, kind="faithful"), G)


def test_the_faithful_objective_gradient_is_its_derivative(m):
    metric = paths.PathMetric.of(m)
    X = paths.straight(m.latent[0], m.latent[4], 7) + np.array([0.03, -0.02])
    e, g = paths.faithful_objective(metric, X)
    h = 1e-4  # the objective is evaluated in float32: smaller steps difference its rounding
    for k, c in [(2, 0), (3, 1), (5, 0)]:
        up, down = X.copy(), X.copy()
        up[k, c] += h
        down[k, c] -= h
        fd = (
            paths.faithful_objective(metric, up)[0] - paths.faithful_objective(metric, down)[0]
        ) / (2 * h)
        assert g[k, c] == pytest.approx(fd, rel=0.05, abs=1e-4 * abs(e))


def test_path_weights_hold_no_subnormal_float32(m):
    """The metric's float32 weights set weights below float32's normal range to 0 (a product
    with a subnormal operand is slow) and equal the manifold's weights everywhere else.
    """
    from mitsuba_manifold._util.float32 import TINY

    narrow = Manifold(  # a narrow taper: far materials' weights fall below float32's range
        m.names,
        m.latent,
        m.database,
        m.hashes,
        m.length_scale,
        m.noise,
        m.features,
        m.albedos,
        gram=m.gram,
        record=m.record,
        interpolant={**m.interpolant.params(), "taper": 0.02, "spread": 0.0},
        table_gram=m.table_gram,
    )
    rng = np.random.default_rng(1)
    X = m.latent[rng.integers(m.n, size=400)] + 0.05 * rng.normal(size=(400, m.q))
    w = narrow.weights(X).w
    tiny = (w != 0) & (np.abs(w) < TINY)
    assert tiny.any()  # the case the test is about occurs
    W = paths.PathMetric(narrow, rows=paths.PathMetric.of(m).rows).weights(X)
    assert W.dtype == np.float32 and not np.any((W != 0) & (np.abs(W) < TINY))
    assert np.all(W[tiny] == 0)
    assert np.array_equal(W[~tiny], w[~tiny].astype(np.float32))

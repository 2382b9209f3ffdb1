"""Beyond the data: plausible combinations of measured tables, and the path-stray measure."""

import os

import numpy as np
import pytest
from measured_helpers import MERL, weights_path, write_set

from mitsuba_manifold.data.database import Database, albedo_weights
from mitsuba_manifold.manifold import appearance
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.manifold.plausibility import DirectionalAlbedo

pytestmark = pytest.mark.skipif(not os.path.exists(weights_path()), reason="no NBRDF weights")


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    root = tmp_path_factory.mktemp("measured")
    merl_db = write_set(str(root / "merl"), "merl", MERL)
    rgl = write_set(str(root / "rgl"), "rgl", ["paper_white", "spectralon", "satin_gold"])
    return Manifold.fit(merl_db), Database(rgl)


def test_directional_albedo_of_a_lambertian_table_is_its_albedo():
    da = DirectionalAlbedo((30, 30, 60))
    bins = 30 * 30 * 60
    table = np.concatenate([np.full(bins, rho / np.pi) for rho in (0.2, 0.5, 0.9)])
    a = da.of(table)[0]
    assert a.shape == (3, len(da.theta_i))
    assert np.allclose(a, np.array([0.2, 0.5, 0.9])[:, None], rtol=0.02)
    # the bihemispherical albedo of the same tables, by the package's quadrature, agrees
    q = albedo_weights((30, 30, 60)).reshape(-1)
    assert np.allclose(table.reshape(3, -1) @ q, [0.2, 0.5, 0.9], rtol=0.03)


def test_projection_beyond_the_data_is_plausible_and_closer_than_the_convex_one(measured):
    m, rgl = measured
    tables = m.tables()
    da = DirectionalAlbedo(m.dims)
    ratios = []
    for name in ("paper_white", "spectralon"):
        target = np.asarray(rgl.reflectance(name)).reshape(-1)
        p = m.project(target, beyond=True)
        b = p.beyond
        assert abs(b.weights).sum() > 0 and b.weights.shape == (m.n,)
        full = b.weights.astype(np.float32) @ tables
        assert full.min() >= -1e-6 * full.max()  # no negative lobe
        assert da.of(full).max() <= 1.0 + 1e-6  # albedo <= 1 at every incidence
        assert b.max_albedo <= 1.0 + 1e-6 and b.min_value == pytest.approx(
            full.min(), abs=1e-6 * full.max()
        )
        assert p.best_error <= p.error + 1e-9
        ratios.append(p.best_error / p.nearest_error)
    # paper_white and spectralon are brighter than any MERL material: the convex space cannot
    # reach them, the plausible combination gets closer than the nearest material
    assert np.median(ratios) < 0.9


def test_a_projection_without_beyond_has_none(measured):
    m, rgl = measured
    target = np.asarray(rgl.reflectance("satin_gold")).reshape(-1)
    plain = m.project(target)
    assert plain.beyond is None and plain.best_error == plain.error


def test_stray_flags_a_detour_and_not_a_straight_morph():
    # three materials: blue, white and a dark brown; albedos (N, incidences, RGB)
    blue, white, brown = [
        np.tile(np.array(c)[None], (3, 1))
        for c in ([0.05, 0.08, 0.4], [0.8, 0.8, 0.8], [0.08, 0.04, 0.02])
    ]
    A = np.stack([blue, white, brown])
    t = np.linspace(0, 1, 21)
    straight = np.stack([1 - t, t, 0 * t], 1)
    detour = straight.copy()
    bump = np.sin(np.pi * t) * 0.8
    detour[:, 2] = bump
    detour[:, :2] *= (1 - bump)[:, None]
    s, d = appearance.stray(straight, A), appearance.stray(detour, A)
    assert d["delta_e"] > 20 and d["share"] > 0.3 and 5 <= d["at"] <= 15
    assert s["delta_e"] < 0.5 * d["delta_e"]
    # Lab: a perfect white is L = 100, a = b = 0
    assert np.allclose(appearance.lab(np.ones(3)), [100, 0, 0], atol=1e-6)


def test_stray_on_the_measured_manifold_flags_blue_to_white_through_dark(measured):
    m, _ = measured
    A = appearance.material_albedos(m.tables(), m.dims)
    ia, ib, ibrown = m.index("blue-rubber"), m.index("white-paint"), m.index("black-phenolic")
    t = np.linspace(0, 1, 21)
    W = np.zeros((21, m.n))
    W[:, ia], W[:, ib] = 1 - t, t
    direct = appearance.stray(W, A)
    bump = np.sin(np.pi * t) * 0.7
    V = W * (1 - bump)[:, None]
    V[:, ibrown] += bump
    assert appearance.stray(V, A)["delta_e"] > direct["delta_e"] + 10


def _rays_out_of_the_hull(m):
    """Points from the latent centroid through each vertex of the hull and on out of the data."""
    from scipy.spatial import ConvexHull

    c = m.latent.mean(axis=0)
    ts = np.linspace(1.0, 3.0, 9)
    return [c[None] + ts[:, None] * (m.latent[v] - c)[None] for v in ConvexHull(m.latent).vertices]


def test_the_default_weights_go_on_beyond_the_data_and_stay_plausible(measured):
    m, _ = measured
    assert m.interpolant.params()["beyond"] == "continue"
    tables, da = m.tables(), DirectionalAlbedo(m.dims)
    beyond = []
    for X in _rays_out_of_the_hull(m):
        _, rho = m.interpolant.hull().project(X)
        assert rho[0] < 1e-9 and (rho[1:] > 0).all()  # each ray leaves the hull at a vertex
        w = m.weights(X).w
        assert np.allclose(w.sum(axis=1), 1.0)
        full = w.astype(np.float32) @ tables
        assert (full >= 0).all()  # no negative bin
        assert da.of(full).max() <= 1.0 + 1e-6  # albedo <= 1 at every incidence
        gap = np.abs(w - m.interpolant._convex(X)).sum(axis=1)
        beyond.append(w.min() < -1e-3 and gap[-1] > gap[2])
    # on many rays the material leaves the mixes of the data, the farther the more (on the
    # others a spiky or dark material meets the plausibility limit at once)
    assert np.mean(beyond) >= 1 / 5


def test_far_beyond_the_data_the_material_settles_and_stays_plausible(measured):
    """Far out along a ray the weights stop changing (they do not drift to the mean of all
    materials); the settled material is plausible and led by the materials furthest out in
    that direction."""
    m, _ = measured
    tables, da = m.tables(), DirectionalAlbedo(m.dims)
    c = m.latent.mean(axis=0)
    for v in _rays_out_of_the_hull(m):
        n = (v[-1] - c) / np.linalg.norm(v[-1] - c)
        X = c + np.array([1e3, 1e6, 1e12, 1e29])[:, None] * n
        w = m.weights(X).w
        assert np.allclose(w[1:], w[1], atol=1e-9) and np.allclose(w[0], w[1], atol=1e-4)
        assert np.isfinite(m.weights_jacobian(X)).all()
        full = w[:1].astype(np.float32) @ tables
        assert (full >= 0).all() and da.of(full).max() <= 1.0 + 1e-6
        convex = m.interpolant._convex(X[:1])[0]
        lead = np.flatnonzero(convex > 0.5)  # not the mean: one material holds most of it
        assert len(lead) == 1 and np.isclose(m.latent[lead[0]] @ n, (m.latent @ n).max())


def test_beyond_the_far_bound_a_point_gets_the_weights_of_the_point_at_it(measured):
    """``FAR``: a point farther than ``FAR l`` from the data's centre is continued as the point
    at ``FAR l`` in its direction: the same weights (to rounding of the pulled point), finite,
    on directions through no vertex of the hull, where the hull's closest point and the
    secant's direction still move with the distance.
    """
    m, _ = measured
    it = m.interpolant
    c, l = m.latent.mean(axis=0), m.length_scale
    rng = np.random.default_rng(1)
    for _ in range(3):
        u = rng.standard_normal(m.q)
        u /= np.linalg.norm(u)
        X = c + np.array([it.FAR, 3 * it.FAR, 1e8])[:, None] * l * u
        with np.errstate(over="raise", invalid="raise"):
            w = m.weights(X).w
            e = it.continuation(X, it._convex(X))
        assert np.isfinite(w).all() and np.abs(e[0]).max() > 1e-4  # continued, not convex
        np.testing.assert_allclose(w[1:], np.broadcast_to(w[0], w[1:].shape), rtol=0, atol=1e-12)
        np.testing.assert_allclose(e[1:], np.broadcast_to(e[0], e[1:].shape), rtol=0, atol=1e-12)


def test_the_plausible_step_of_a_point_does_not_depend_on_the_others_of_its_batch(measured):
    """``StepLimit.step`` bisects points in groups of like sizes: each point's step is the one it
    gets alone (to rounding), whatever tables the other points of the batch sum."""
    m, _ = measured
    it = m.interpolant
    rng = np.random.default_rng(5)
    c = m.latent.mean(axis=0)
    X = c + rng.standard_normal((80, m.q)) * 2.0 * np.ptp(m.latent, axis=0)
    p, rho = it.hull().project(X)
    n = (X - p) / rho[:, None]
    eps = it.secant * it.length_scale
    ends = it._thin(it._untapered(np.concatenate([p, p - eps * n])))
    w, e = it._convex(X), 3.0 * (ends[:80] - ends[80:])
    e[0] = rng.standard_normal(m.n) * 0.1  # one point that may push every table negative
    e[0] -= e[0].mean()
    together = it.limit.step(w, e)
    alone = np.array([it.limit.step(w[i : i + 1], e[i : i + 1])[0] for i in range(len(w))])
    np.testing.assert_allclose(together, alone, rtol=1e-9, atol=0)  # to the albedos' rounding
    assert (together < 1).sum() > 10 and (together > 0).sum() > 10  # the limit holds, not all 0


def test_the_continuation_leaves_the_weights_inside_the_hull_unchanged(measured):
    m, _ = measured
    rng = np.random.default_rng(3)
    lam = rng.dirichlet(np.full(m.n, 0.3), size=40)
    inside = np.concatenate(
        [lam @ m.latent, m.latent]
    )  # convex combinations, the points themselves
    w = m.weights(inside).w
    assert np.array_equal(w, m.interpolant._convex(inside))
    assert np.allclose(w[40:], np.eye(m.n))  # exact at every training point


def test_the_jacobian_beyond_the_data_is_that_of_the_continued_weights(measured):
    m, _ = measured
    X = _rays_out_of_the_hull(m)
    x = max((r[4] for r in X), key=lambda x: -m.weights(x).w.min())
    h = 1e-3 * m.length_scale
    fd = np.stack(
        [(m.weights(x + h * e).w - m.weights(x - h * e).w) / (2 * h) for e in np.eye(m.q)], axis=1
    )
    J = m.weights_jacobian(x)
    assert J.shape == (m.n, m.q)
    scale = np.abs(fd).max()
    assert np.abs(J - fd).max() <= 0.05 * scale
    # not the convex weights' Jacobian: beyond the data the continuation moves the material
    assert np.abs(m.interpolant._convex_jacobian(x[None])[0] - fd).max() > 0.2 * scale


def test_a_saved_default_manifold_continues_beyond_the_data_when_loaded(measured, tmp_path):
    m, _ = measured
    m.save(tmp_path / "m.npz")
    back = Manifold.load(tmp_path / "m.npz")
    assert back.interpolant.params() == m.interpolant.params()
    x = _rays_out_of_the_hull(m)[0][-1]
    assert np.allclose(back.weights(x).w, m.weights(x).w)


def test_the_plausibility_limit_is_kept_for_the_next_process(tmp_path):
    """A second :class:`StepLimit` on the same tables reads the ratios and albedos the first one
    computed from its store and reads no table for them; it gives the same steps.
    """
    from mitsuba_manifold.manifold.plausibility import StepLimit

    rng = np.random.default_rng(0)
    dims = (4, 4, 8)
    tables = rng.uniform(0.05, 1.0, (3, 3 * 4 * 4 * 8)).astype(np.float32)
    reads = []

    def rows(idx):
        reads.extend(idx)
        return [tables[i] for i in idx]

    w = np.array([[0.5, 0.5, 0.0], [0.2, 0.3, 0.5]])
    e = np.array([[0.6, 0.4, -1.0], [1.0, -0.5, -0.5]])
    store = tmp_path / "limit.npz"
    first = StepLimit(rows, 3, dims, store=store).step(w, e)
    assert reads and store.exists()
    reads.clear()
    second = StepLimit(rows, 3, dims, store=store).step(w, e)
    assert reads == []
    assert np.array_equal(first, second)
    # a store of another number of tables is not used
    reads.clear()
    StepLimit(rows, 2, dims, store=store).step(w[:1, :2], np.array([[1.0, -1.0]]))
    assert reads


def test_domination_ratios_read_each_table_once_per_block_of_columns():
    """``StepLimit.ratios`` of r rows against c <= TABLE_BLOCK columns reads r + c tables (not
    r per column), and its values are ``min_b table_i / table_j`` over the bins of ``table_j > 0``.
    """
    from mitsuba_manifold.manifold.plausibility import TABLE_BLOCK, StepLimit

    rng = np.random.default_rng(1)
    n = 10
    tables = rng.uniform(0.05, 1.0, (n, 3 * 4 * 4 * 8)).astype(np.float32)
    tables[3, :5] = 0.0  # bins a column skips
    reads = []

    def rows(idx):
        reads.extend(idx)
        return [tables[i] for i in idx]

    r, c = np.array([0, 1, 2, 5, 6, 7]), np.array([3, 4, 8])
    assert len(c) <= TABLE_BLOCK
    R, C = np.meshgrid(r, c, indexing="ij")
    got = StepLimit(rows, n, (4, 4, 8)).ratios(R, C)
    assert sorted(reads) == sorted(r.tolist() + c.tolist())
    on = tables > 0
    want = [[(tables[i][on[j]] / tables[j][on[j]]).min() for j in c] for i in r]
    np.testing.assert_allclose(got, want, rtol=1e-6)


def test_steps_of_one_limit_from_several_threads_take_turns(tmp_path):
    """The explorer's frames, maps and walks share one :class:`StepLimit`: their steps run one
    at a time (no two read tables at once, its store is written whole) and give the serial steps.
    """
    import threading
    import time

    from mitsuba_manifold.manifold.plausibility import StepLimit

    rng = np.random.default_rng(2)
    tables = rng.uniform(0.05, 1.0, (4, 3 * 4 * 4 * 8)).astype(np.float32)
    inside, most = [0], [0]
    guard = threading.Lock()

    def rows(idx):
        with guard:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        time.sleep(0.05)
        with guard:
            inside[0] -= 1
        return [tables[i] for i in idx]

    w = np.array([[0.5, 0.5, 0.0, 0.0], [0.2, 0.3, 0.5, 0.0], [0.0, 0.1, 0.4, 0.5]])
    e = np.array([[0.6, 0.4, -1.0, 0.0], [1.0, -0.5, 0.0, -0.5], [-0.3, 0.0, 0.8, -0.5]])
    serial = [
        StepLimit(lambda i: [tables[k] for k in i], 4, (4, 4, 8)).step(w[k], e[k]) for k in range(3)
    ]
    limit = StepLimit(rows, 4, (4, 4, 8), store=tmp_path / "limit.npz")
    got = [None] * 3

    def run(k):
        got[k] = limit.step(w[k], e[k])

    threads = [threading.Thread(target=run, args=(k,)) for k in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert most[0] == 1
    for k in range(3):
        np.testing.assert_array_equal(got[k], serial[k])
    with np.load(tmp_path / "limit.npz") as f:  # the store holds what all three computed
        assert np.isfinite(f["albedo"]).all()

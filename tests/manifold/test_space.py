"""The material space: presets, interpolants, Jacobians, projection, pruning, old files, space metrics."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from mitsuba_manifold.data.database import Database
from mitsuba_manifold.gp import gplvm
from mitsuba_manifold.manifold import interpolant, space
from mitsuba_manifold.manifold.model import InputError, Manifold
from mitsuba_manifold.manifold.presets import canonical_order

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="module")
def default(small_db):
    """The default preset as users get it: ``Manifold.fit(database)``."""
    return Manifold.fit(small_db)


@pytest.fixture(scope="module")
def paper(small_manifold_paper):
    return Manifold.load(small_manifold_paper)


def _box_points(m, n=64, seed=0):
    lo, hi = space.latent_box(m.latent, 0.5)
    return lo + np.random.default_rng(seed).random((n, m.q)) * (hi - lo)


def test_default_is_convex_inside_the_data_continuous_and_reproduces_training_materials(default):
    assert default.info["preset"] == "default" and default.interpolant.kind == "shepard"
    lam = np.random.default_rng(0).dirichlet(np.full(default.n, 0.5), size=64)
    X = lam @ default.latent  # inside the hull of the latent points
    _, W = default.weights(X)
    assert (W >= 0).all() and np.allclose(W.sum(axis=1), 1)
    A = default.albedo(X)
    assert (A >= default.albedos.min(0) - 1e-12).all() and (
        A <= default.albedos.max(0) + 1e-12
    ).all()
    # around the data (beyond the hull: affine weights) the albedo stays in [0, 1]
    _, W = default.weights(_box_points(default))
    assert np.allclose(W.sum(axis=1), 1)
    A = default.albedo(_box_points(default))
    assert (A >= 0).all() and (A <= 1).all()
    for i in range(default.n):
        assert np.array_equal(default.weights(default.latent[i]).w, np.eye(default.n)[i])
    assert default.discontinuity() < 1e-6
    b, w = default.weights(X[0])
    assert np.allclose(b, w - 1 / default.n)


def test_paper_preset_reproduces_the_previous_fit(paper, small_db):
    """preset="paper" is Hooke-Jeeves on raw features from their PCA, Eq. 4 weights: the materials
    in their canonical order (by content hash), the points in the canonical pose.
    """
    db = Database(small_db)
    _, S = db.gram(features="raw")
    order = canonical_order(db.hashes(), db.names)
    ref = gplvm.fit_latent(
        S[np.ix_(order, order)],
        3 * int(np.prod(db.dims)),
        q=2,
        method="hooke-jeeves",
        length_scale=1.0,
        noise=1e-4,
    )
    back = np.argsort(order)
    assert np.array_equal(paper.latent, ref.latent[back])
    assert paper.interpolant.kind == "gp" and paper.features == "raw"
    x = np.array([0.1, -0.3])
    k = np.exp(-0.5 * ((paper.latent - x) ** 2).sum(1))
    assert np.allclose(paper.weights(x).b, np.linalg.solve(paper.K, k))


@pytest.mark.parametrize("which", ["default", "paper"])
def test_weights_jacobian_and_variance_gradient_match_finite_differences(which, default, paper):
    """The one test of Manifold.weights_jacobian (Shepard and Eq. 4 weights) and variance_gradient."""
    m = default if which == "default" else paper
    X = _box_points(m, 8, seed=1)
    J = m.weights_jacobian(X)
    assert J.shape == (8, m.n, m.q) and np.allclose(J.sum(axis=1), 0, atol=1e-9)
    G = m.variance_gradient(X)
    h = 1e-6
    for k in range(m.q):
        e = np.zeros(m.q)
        e[k] = h
        fd = (m.weights(X + e).w - m.weights(X - e).w) / (2 * h)
        assert np.allclose(J[:, :, k], fd, rtol=1e-4, atol=1e-6)
        fdv = (m.variance(X + e) - m.variance(X - e)) / (2 * h)
        assert np.allclose(G[:, k], fdv, rtol=1e-5, atol=1e-8)
    for i in range(len(X)):  # one point: the batch's row
        assert np.array_equal(m.weights_jacobian(X[i]), J[i]) and np.array_equal(
            m.variance_gradient(X[i]), G[i]
        )


def test_far_points_get_far_field_weights_without_warnings_until_they_overflow(default, paper):
    import warnings

    steep = interpolant.ShepardWeights(default.latent, power=16.0, taper=0.2, spread=0.3)
    for m, weights, jacobian in [
        (default, default.weights, default.weights_jacobian),
        (paper, paper.weights, paper.weights_jacobian),
        (default, steep.weights, steep.jacobian),
    ]:
        far = np.full(m.q, -1e29)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            w = np.asarray(getattr(weights(far), "w", weights(far)))
            assert np.isfinite(jacobian(far)).all()
        if weights == default.weights:  # continued beyond the data: affine, plausible
            assert np.isclose(w.sum(), 1.0) and np.isfinite(w).all()
        if weights == paper.weights:  # Eq. 4: the mean material far from the data
            assert np.allclose(w, 1.0 / m.n)
        else:  # a tapered Shepard: the material furthest out in that direction, not the mean
            convex = np.asarray(default.interpolant._convex(far[None])[0])
            if weights == steep.weights:
                convex = w
            assert np.isclose(convex.max(), 1.0) and np.argmax(convex) == np.argmin(m.latent.sum(1))
        with pytest.raises(InputError, match="too far out"):
            weights(np.full(m.q, 1e308))


def test_projection_finds_a_training_material_and_a_noisy_copy(default):
    tables = default.tables()
    i = 3
    p = default.project(tables[i])
    assert p.error < 1e-6 and p.nearest == default.names[i]
    assert np.allclose(default.weights(p.x).w, np.eye(default.n)[i], atol=1e-6)
    rng = np.random.default_rng(0)
    noisy = tables[i] * np.exp(rng.normal(0, 0.05, tables.shape[1])).astype(np.float32)
    p = default.project(noisy)
    assert p.nearest == default.names[i] and p.error <= p.nearest_error
    assert p.weights[i] > 0.5 and p.negative_fraction == 0


def test_projection_beats_the_nearest_material_for_a_blend(default):
    """A table made as a blend of two neighbours lies on the manifold: projection finds it."""
    x = 0.5 * (default.latent[0] + default.latent[1])
    target = default.interpolate(x, prune=0.0).table
    p = default.project(target)
    assert p.error < 0.2 * p.nearest_error


def test_projection_rejects_bad_tables(default, tmp_path):
    with pytest.raises(InputError, match="values"):
        default.project(np.zeros(10))
    bad = tmp_path / "bad.binary"
    bad.write_bytes(b"nope")
    with pytest.raises(InputError, match="table to project"):
        default.project(str(bad))


def test_project_tool(default, small_db, tmp_path):
    path = str(tmp_path / "m.npz")
    default.save(path)
    out = tmp_path / "p.json"
    r = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "tools", "project.py"),
            os.path.join(small_db, "chrome.binary"),
            "--manifold",
            path,
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        cwd=str(tmp_path),
    )
    assert r.returncode == 0, r.stderr
    result = json.loads(out.read_text())
    assert result["nearest"] == "chrome" and result["error"] < 1e-6 and "x =" in r.stdout
    r = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "tools", "project.py"),
            str(tmp_path / "none.binary"),
            "--manifold",
            path,
        ],
        capture_output=True,
        text=True,
        cwd=str(tmp_path),
    )
    assert r.returncode != 0 and "none.binary" in r.stderr and "Traceback" not in r.stderr


def test_project_json_replaces_only_its_own_files(default, small_db, tmp_path):
    from guarantees_helpers import assert_one_error, run_tool, snapshot

    manifold, table = str(tmp_path / "m.npz"), str(tmp_path / "in.binary")
    default.save(manifold)
    shutil.copy(os.path.join(small_db, "chrome.binary"), table)
    (tmp_path / "mine.json").write_text("my notes")
    (tmp_path / "locked.json").write_text("locked")
    os.chmod(tmp_path / "locked.json", 0o444)
    before = snapshot(tmp_path)
    for out, extra, words in [
        (table, [], ["--json"]),
        (tmp_path / "notes.txt", ["--force"], [".json"]),
        (tmp_path / "mine.json", [], ["mine.json", "--force"]),
        (tmp_path / "locked.json", ["--force"], ["locked.json", "read-only"]),
    ]:
        rc, _, err = run_tool("project", table, "--manifold", manifold, "--json", out, *extra)
        assert_one_error(rc, err, *words)
    assert snapshot(tmp_path) == before
    for _ in range(2):  # its own output is replaced
        rc, _, err = run_tool(
            "project", table, "--manifold", manifold, "--json", tmp_path / "p.json"
        )
        assert rc == 0, err
    assert json.loads((tmp_path / "p.json").read_text())["nearest"] == "chrome"
    rc, _, err = run_tool(
        "project", table, "--manifold", manifold, "--json", tmp_path / "nodir" / "p.json"
    )
    assert_one_error(rc, err, str(tmp_path / "nodir" / "p.json"), "does not exist")
    assert ".tmp" not in err


def test_default_prune_keeps_the_table_within_its_bounds(default):
    """The "raw-l2" rule within 1% of the raw L2 norm; the default "image" rule within 1% of the
    cosine-weighted norm and 0.5% of each albedo channel (errors measured on the tables)."""
    from mitsuba_manifold.data.database import albedo_weights

    tables = default.tables()
    q = albedo_weights(default.dims).reshape(-1)
    qq = np.tile(q, 3)
    for x in _box_points(default, 12, seed=2):
        w = default.weights(x).w
        full = w @ tables.astype(np.float64)
        table, keep, _ = default.combine(w, rule="raw-l2")
        err = np.linalg.norm(table.reshape(-1) - full) / np.linalg.norm(full)
        assert err <= 0.01 + 1e-5
        assert err == pytest.approx(default.prune_error(w, keep, rule="raw-l2"), abs=1e-5)
        table, keep, _ = default.combine(w)
        d = table.reshape(-1) - full
        err = np.sqrt((qq * d * d).sum() / (qq * full * full).sum())
        assert err <= 0.01 + 1e-5 and err == pytest.approx(default.prune_error(w, keep), abs=1e-5)
        albedo = full.reshape(3, -1) @ q
        assert (np.abs(d.reshape(3, -1) @ q) <= 0.005 * albedo + 1e-6).all()


def test_prune_by_contribution_keeps_small_weights_on_spiky_tables(paper):
    """A small weight on a table 1000x brighter contributes more than a big one on a dull table."""
    G = np.diag(np.array([1.0, 1e6] + [1e-2] * (paper.n - 2)))
    from mitsuba_manifold.manifold import pruning

    w = np.r_[0.6, 0.01, np.full(paper.n - 2, 0.39 / (paper.n - 2))]
    keep, w_kept, _ = pruning.prune(w, G, 0.01)
    assert 1 in keep and w_kept.sum() == pytest.approx(1.0)
    assert pruning.error(w, keep, G) <= 0.01


def test_saved_manifold_of_the_previous_release_loads_as_paper(paper, tmp_path):
    """A version-1 file (no interpolant, no table Gram) loads with the paper's GP weights; bad versions fail clearly."""
    path = tmp_path / "v1.npz"
    meta = {
        "format": "mitsuba-manifold",
        "version": 1,
        "names": paper.names,
        "database": paper.database,
        "hashes": paper.hashes,
        "length_scale": 1.0,
        "noise": 1e-4,
        "features": "raw",
        "info": {k: v for k, v in paper.info.items() if k != "preset"},
    }
    np.savez(
        path,
        latent=paper.latent,
        history=paper.history,
        meta=np.array(json.dumps(meta)),
        albedos=paper.albedos,
        gram=paper.gram,
    )
    old = Manifold.load(path)
    assert old.interpolant.kind == "gp" and old.info["preset"] == "paper" and old.table_gram is None
    x = np.array([0.2, 0.1])
    assert np.array_equal(old.weights(x).w, paper.weights(x).w)
    keep, _, _ = old.prune(old.weights(x).w)  # table Gram computed from the database on demand
    assert old.table_gram is not None and len(keep) >= 1
    meta["version"] = 7
    np.savez(path, latent=paper.latent, meta=np.array(json.dumps(meta)))
    with pytest.raises(InputError, match="refit"):
        Manifold.load(path)


def test_saved_default_round_trips(default, tmp_path):
    path = tmp_path / "m.npz"
    default.save(path)
    m = Manifold.load(path)
    assert m.interpolant.params() == default.interpolant.params() and m.info["preset"] == "default"
    X = _box_points(m, 5)
    assert np.array_equal(m.weights(X).w, default.weights(X).w)
    assert np.array_equal(m.table_gram, default.table_gram)


def test_unknown_settings_fail_clearly(small_db):
    with pytest.raises(InputError, match="preset"):
        Manifold.fit(small_db, preset="best")
    with pytest.raises(InputError, match="interpolant"):
        Manifold.fit(small_db, interpolant={"kind": "spline"})


# ------------------------------------------------------------------- metrics


def test_baselines_from_the_gram_matrix_match_direct_computation():
    rng = np.random.default_rng(4)
    F = rng.normal(size=(12, 40)) @ rng.normal(size=(40, 40))
    G = F @ F.T
    train, test = np.arange(9), np.arange(9, 12)
    be = space.baseline_errors(G, train, test, F.shape[1], components=(2,))
    mean = F[train].mean(0)
    Z = F[train] - mean
    _, _, Vt = np.linalg.svd(Z, full_matrices=False)
    for k, t in enumerate(test):
        z = F[t] - mean
        r = z - Vt[:2].T @ (Vt[:2] @ z)
        assert be["pca2"][k] == pytest.approx(np.sqrt(r @ r / 40))
        assert be["mean"][k] == pytest.approx(np.sqrt(z @ z / 40))
        nn = np.sqrt(((F[train] - F[t]) ** 2).mean(1))
        assert be["nearest"][k] == pytest.approx(nn.min()) and be["nearest_index"][k] == nn.argmin()


def test_path_metrics_and_jump():
    latent = np.array([[0.0], [1.0]])
    # two points: Shepard weights w_0 = (1-t)^2 / (t^2 + (1-t)^2); largest step in the middle, share p/40
    ip = interpolant.ShepardWeights(latent, power=2.0)
    paths = space.path_smoothness(ip, [(0, 1)], steps=40)
    assert paths.weight_share[0] == pytest.approx(2 / 40, rel=0.02)
    assert space.step_share(np.ones((1, 40)))[0] == pytest.approx(1 / 40)
    assert space.training_jump(ip).max() < 1e-9
    gp = interpolant.GaussianProcessWeights(np.array([[0.0], [1e-3]]), noise=1e-4)
    assert space.training_jump(gp).max() > 0.5 and gp.jump() == pytest.approx(
        space.training_jump(gp).max(), rel=1e-3
    )


def test_plausibility_of_convex_and_affine_weights(default, paper):
    tables = default.tables()
    conv = space.plausibility(
        default.interpolant, default.albedos, tables, n_albedo=400, n_tables=8
    )
    assert conv.albedo_outside == 0 and conv.negative_fraction.max() == 0
    assert conv.negative_weights > 0  # beyond the data: affine weights, held plausible
    inside = interpolant.make(default.latent, {**default.interpolant.params(), "beyond": "nearest"})
    conv = space.plausibility(inside, default.albedos, tables, n_albedo=400, n_tables=8)
    assert conv.negative_weights == 0
    aff = space.plausibility(paper.interpolant, paper.albedos, tables, n_albedo=400, n_tables=8)
    assert aff.negative_weights > 0


def test_a_partial_interpolant_override_keeps_the_presets_other_parameters():
    from mitsuba_manifold.manifold.model import settings

    assert settings("default", interpolant={"taper": 0.3})["interpolant"] == {
        **settings("default")["interpolant"],
        "taper": 0.3,
    }
    assert settings("default", interpolant={"kind": "gp"})["interpolant"] == {
        "kind": "gp"
    }  # another kind: whole


def test_cross_validation_runs_and_reports(default, small_db):
    db = Database(small_db)
    tables = default.tables()
    G = space.feature_gram(tables, "log")
    from mitsuba_manifold.manifold.model import fit_layout, make_interpolant, settings
    from mitsuba_manifold.manifold.presets import stress_distances

    cfg = settings("default", q=2)
    D = stress_distances(tables, default.dims)  # the default's stress term's targets

    def fit(train):
        layout = fit_layout(
            space.centred(G, train), tables.shape[1], cfg, distances=D[np.ix_(train, train)]
        )
        return make_interpolant(layout.latent, cfg)

    held = space.cross_validate(
        tables, db.names, fit, G, 2, default.albedos, split=space.FoldSplit(k=4, only=(0,))
    )
    s = held.summary()
    assert (
        s["n"] == 2
        and (held.error <= held.nearest + 1e-6).all()
        and s["worst_negative_fraction"] == 0
    )
    assert json.dumps(held.as_dict())
    assert len(held.fold_ratios()) == 1 and s["worst_fold_median_ratio"] == pytest.approx(
        np.median(held.error / held.nearest)
    )


def test_all_neighbour_pairs_hold_every_materials_nearest_neighbour_once():
    latent = np.random.default_rng(2).normal(size=(30, 3))
    pairs = space.all_neighbour_pairs(latent)
    d = np.linalg.norm(latent[:, None] - latent[None], axis=-1) + np.diag(np.full(30, np.inf))
    assert len(pairs) == len(set(pairs)) and all(i < j for i, j in pairs)
    assert all(tuple(sorted((i, int(d[i].argmin())))) in pairs for i in range(30))
    assert all(d[i, j] == d[i].min() or d[i, j] == d[j].min() for i, j in pairs)


def test_convex_blend_recovers_a_blend_of_two_tables():
    rng = np.random.default_rng(3)
    A = rng.uniform(0.0, 5.0, (4, 500))
    y = np.log1p(0.3 * A[1] + 0.7 * A[2])
    w = space.convex_blend(A, y)
    assert w == pytest.approx([0.0, 0.3, 0.7, 0.0], abs=1e-3) and w.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("q", [4, 5])
def test_the_closest_point_of_the_hull_is_the_projection_whatever_face_was_found_before(q):
    """``LatentHull.project`` for ``q >= 4``: each point outside gets the point of the hull no
    vertex lies beyond (``(x - p) . (v - p) <= 0``: the projection onto a convex set), the same
    whether the face found for the point before it is right (steps of a descent), wrong (far
    apart points) or none (a fresh hull)."""
    rng = np.random.default_rng(q)
    latent = rng.standard_normal((40, q))
    hull = interpolant.LatentHull(latent)
    walk = latent[0] * 1.8 + np.cumsum(1e-3 * rng.standard_normal((60, q)), axis=0)
    scattered = 2.5 * rng.standard_normal((60, q))
    for X in (walk, scattered, np.concatenate([scattered, walk])[rng.permutation(120)]):
        one_by_one = np.array([hull.project(x)[0][0] for x in X])
        fresh = np.array([interpolant.LatentHull(latent).project(x)[0][0] for x in X])
        np.testing.assert_allclose(one_by_one, fresh, rtol=0, atol=1e-12)
        p, rho = hull.project(X)
        np.testing.assert_allclose(p, one_by_one, rtol=0, atol=1e-12)
        out = rho > 0
        assert out.sum() > 30
        d = X[out] - p[out]
        beyond = np.einsum("mvq,mq->mv", latent[None] - p[out][:, None], d)
        assert (beyond.max(axis=1) <= 1e-9 * rho[out] ** 2).all()
        assert (p @ hull.planes[:, :-1].T + hull.planes[:, -1] <= 1e-9).all()  # on the hull


def test_the_closest_point_of_a_hull_with_flat_facets_is_on_the_hull():
    """A hull whose faces hold many points in one plane (Qhull splits them into facets, some
    flat): the closest point of the unit 4-cube to points around it is ``clip(x, 0, 1)``, for
    many points at once (the facet shortcut) as for one at a time."""
    rng = np.random.default_rng(0)
    corners = np.array(np.meshgrid(*[[0.0, 1.0]] * 4)).reshape(4, -1).T
    on_faces = rng.uniform(0.0, 1.0, (100, 4))
    on_faces[np.arange(100), rng.integers(0, 4, 100)] = rng.integers(0, 2, 100)
    latent = np.concatenate([corners, on_faces, rng.uniform(0.2, 0.8, (10, 4))])
    X = rng.uniform(-1.5, 2.5, (200, 4))
    exact = np.clip(X, 0.0, 1.0)
    p, rho = interpolant.LatentHull(latent).project(X)
    np.testing.assert_allclose(p, exact, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rho, np.linalg.norm(X - exact, axis=1), rtol=0, atol=1e-9)

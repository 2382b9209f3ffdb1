"""The acquisition's convex programme: its constraints hold, it is optimal, a known combination
comes back from noise-free images, and its result file round-trips."""

import numpy as np
import pytest
import scipy.optimize

from mitsuba_manifold.basis.inverse import acquisition as aq
from mitsuba_manifold.errors import FormatError, InputError


def _problem(seed=0, n=6, rows=200):
    rng = np.random.default_rng(seed)
    A = rng.uniform(0.0, 1.0, (rows, n))
    albedo = rng.uniform(0.1, 0.6, (n, 4))
    check = rng.uniform(0.0, 1.0, (n, 50))
    check[:, :5] = np.where(rng.uniform(size=(n, 5)) < 0.5, 0.0, 2.0)  # bins only some tables have
    cons = aq.Constraints(albedo, check, rng.uniform(0.0, 1.0, (n, 3)))
    return A, cons


def test_constraints_hold_and_the_target_beyond_them_is_not_reached():
    """A target far outside every feasible set: each method's answer satisfies its constraints
    (no negative weight for nonneg/convex, the simplex for convex, no negative sampled bin for
    beyond) and the albedo bound, and beyond's feasible set contains nonneg's (its error is no
    larger)."""
    A, cons = _problem()
    w_true = np.array([3.0, -2.0, 1.0, 0.0, -1.0, 2.0])
    t = A @ w_true
    photos = aq.LinearPhotos(A, np.zeros(len(t)), t, np.arange(len(t)) // 10, np.zeros(len(t), int))
    H, g, _ = photos.normal_equations()
    got = {m: aq.solve(H, g, cons, m, 1e-6) for m in ("nonneg", "convex", "beyond")}
    for m, w in got.items():
        assert (w @ cons.albedo).max() <= 1 + 1e-8, m
    assert got["nonneg"].min() >= -1e-10 and got["convex"].min() >= -1e-10
    assert got["convex"].sum() == pytest.approx(1.0, abs=1e-8)
    assert (got["beyond"] @ cons.check).min() >= -1e-8
    assert got["beyond"].min() < 0  # it used weights of either sign
    err = {m: photos.relative_error(w) for m, w in got.items()}
    assert err["beyond"] <= err["nonneg"] + 1e-9 <= err["convex"] + 2e-9


def test_quadratic_programme_is_optimal():
    """The least-distance/NNLS solve matches SciPy's SLSQP on the same small programme."""
    rng = np.random.default_rng(3)
    M = rng.normal(size=(30, 5))
    H = M.T @ M + 0.1 * np.eye(5)
    g = rng.normal(size=5) * 5
    G = np.vstack([np.eye(5), -np.ones((1, 5))])
    h = np.concatenate([np.zeros(5), [-1.0]])
    w = aq.quadratic_programme(H, g, G, h)
    ref = scipy.optimize.minimize(
        lambda v: v @ H @ v - 2 * g @ v,
        np.full(5, 0.1),
        jac=lambda v: 2 * H @ v - 2 * g,
        method="SLSQP",
        constraints=[{"type": "ineq", "fun": lambda v: G @ v - h, "jac": lambda v: G}],
        options={"ftol": 1e-14, "maxiter": 500},
    ).x
    assert np.all(G @ w - h >= -1e-9)
    assert w @ H @ w - 2 * g @ w <= ref @ H @ ref - 2 * g @ ref + 1e-8


def test_infeasible_constraints_are_named():
    H, g = np.eye(2), np.ones(2)
    G, h = np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([1.0, 0.0])  # w0 >= 1 and w0 <= 0
    with pytest.raises(Exception, match="infeasible"):
        aq.quadratic_programme(H, g, G, h)


def test_a_known_combination_comes_back():
    """Noise-free images of a non-negative combination: the answer reproduces it."""
    A, cons = _problem(seed=1)
    cons = aq.Constraints(cons.albedo * 0.1, cons.check, cons.peak)
    w_true = np.array([0.5, 0.0, 0.3, 0.0, 0.2, 0.0])
    t = A @ w_true
    photos = aq.LinearPhotos(A, np.zeros(len(t)), t, np.arange(len(t)) // 10, np.zeros(len(t), int))
    H, g, _ = photos.normal_equations()
    for method in ("nonneg", "beyond"):
        w = aq.solve(H, g, cons, method, 1e-9)
        np.testing.assert_allclose(w, w_true, atol=1e-4)
    lam, scores = aq.cross_validate(photos, cons, "nonneg")
    assert lam == min(s[0] for s in scores)  # the least regularised fits noise-free data best
    feasible, _, found = aq.choose(photos, cons, "plausible")
    assert feasible == "nonneg" and set(found) == {"nonneg", "beyond"}  # beyond is not needed


def test_beyond_is_chosen_where_the_photo_needs_it():
    """Images of a combination with a negative weight (inside the plausible set): the choice
    between the feasible sets takes ``beyond``."""
    A, cons = _problem(seed=2)
    cons = aq.Constraints(cons.albedo * 0.1, np.abs(cons.check) + 1.0, cons.peak)
    w_true = np.array([1.0, -0.3, 0.5, 0.0, 0.0, 0.2])
    t = A @ w_true
    photos = aq.LinearPhotos(A, np.zeros(len(t)), t, np.arange(len(t)) // 10, np.zeros(len(t), int))
    feasible, lam, _ = aq.choose(photos, cons, "plausible")
    assert feasible == "beyond"
    H, g, _ = photos.normal_equations()
    np.testing.assert_allclose(aq.solve(H, g, cons, "beyond", 1e-9), w_true, atol=1e-3)


def test_guarantee_steps_back_to_a_non_negative_table():
    """Weights whose full table dips below 0 outside the sampled bins are moved toward the
    non-negative start until no value of the full table is negative."""
    tables = np.array([[1.0, 1.0, 1.0, 0.0], [0.5, 0.2, 0.9, 1.0]], dtype=np.float32)
    albedo = np.full((2, 1), 0.1)
    w = np.array([1.5, -0.5])  # value of the last bin: -0.5
    start = np.array([0.5, 0.5])
    got, s = aq.guarantee(w, start, lambda i: tables[i], 2, albedo)
    full = got @ tables.astype(np.float64)
    assert full.min() >= -1e-6 and 0 < s < 1


def test_result_round_trips_and_refuses_other_files(tmp_path):
    r = aq.Acquisition(
        names=["a", "b"],
        w=[0.7, -0.1],
        method="plausible",
        error=0.05,
        single={"name": "a", "error": 0.1},
        warnings=["w"],
    )
    path = r.write(tmp_path / "r.json")
    back = aq.Acquisition.read(path)
    assert back.weights == {"a": 0.7, "b": -0.1} and back.single["name"] == "a"
    assert back.warnings == ["w"] and back.method == "plausible"
    assert 'name="weights" value="a:0.7, b:-0.1"' in r.snippet("m.npz")
    bad = tmp_path / "bad.json"
    bad.write_text('{"weights": {}}')
    with pytest.raises(FormatError, match="not an acquisition file"):
        aq.Acquisition.read(bad)


@pytest.mark.parametrize(
    "change, says",
    [
        ({"method": "magic"}, "`method`"),
        ({"regularisation": -1.0}, "`regularisation`"),
        ({"spp": 0}, "`spp`"),
        ({"bootstrap": -1}, "`bootstrap`"),
    ],
)
def test_options_name_the_bad_field(change, says):
    with pytest.raises(InputError, match=says):
        aq.AcquireOptions(**change).check()

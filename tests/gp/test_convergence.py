"""The fit as a property of the data: a stated convergence test, exact Hessian products, the
canonical pose, and the same points whatever the last bits of the arithmetic or the order."""

import warnings

import numpy as np
import pytest
from gp_synthetic import gram, smooth_data

from mitsuba_manifold.errors import ConvergenceWarning
from mitsuba_manifold.gp import gplvm
from mitsuba_manifold.gp.optimisers import _KrylovModel, gradient_norm
from mitsuba_manifold.gp.stress import PenalisedLikelihood
from mitsuba_manifold.manifold.presets import canonical_order, fit_layout, settings

#: The noise levels of the continuation tests.
CONTINUATION = (1e-2, 1e-3)


def _problem(n=16, seed=3, d=2e4):
    Z = smooth_data(n, seed=seed)
    S = gram(Z, d)
    diff = Z[:, None, :] - Z[None, :, :]
    D = np.sqrt((diff**2).sum(-1))
    return S, d, D


def _random_motion(X, seed):
    rng = np.random.default_rng(seed)
    R, _ = np.linalg.qr(rng.standard_normal((X.shape[1], X.shape[1])))
    return X @ R + rng.standard_normal(X.shape[1])


def test_hessian_vector_products_match_finite_differences_of_the_gradient():
    S, d, D = _problem()
    lik = gplvm.Likelihood(S, d).in_units()
    target = PenalisedLikelihood(lik, gplvm.Stress(5.0).term(D, len(S), d))
    rng = np.random.default_rng(0)
    U = gplvm.pca_init(S, 3) + 0.1 * rng.standard_normal((len(S), 3))
    V = rng.standard_normal(U.shape)
    for f in (lik, target):
        h = 1e-5
        fd = (f._value_grad(U + h * V)[1] - f._value_grad(U - h * V)[1]) / (2 * h)
        exact = f._hessp(U, V)
        assert np.abs(exact - fd).max() < 1e-5 * np.abs(fd).max()


def test_canonical_pose_is_the_same_for_every_rigid_motion_and_keeps_distances():
    X = np.random.default_rng(1).standard_normal((30, 3)) * [3.0, 2.0, 1.0] + 0.3
    X[:, 0] += 0.5 * X[:, 0] ** 2  # skewed: every axis has a third moment
    posed = gplvm.canonical_pose(X)
    for seed in range(4):
        again = gplvm.canonical_pose(_random_motion(X, seed))
        assert np.abs(again - posed).max() < 1e-9
    assert np.abs(posed.mean(axis=0)).max() < 1e-12
    var = posed.var(axis=0)
    assert np.all(np.diff(var) <= 0)
    cov = posed.T @ posed
    assert np.abs(cov - np.diag(np.diag(cov))).max() < 1e-9 * cov.max()
    dist = lambda A: np.sqrt(((A[:, None] - A[None]) ** 2).sum(-1))  # noqa: E731
    assert np.abs(dist(posed) - dist(X)).max() < 1e-9


@pytest.mark.parametrize("method", ["newton", "lbfgs"])
def test_a_converged_fit_meets_its_stated_test_and_says_so(method):
    S, d, D = _problem()
    cfg = settings("default", q=2, method=method, stress=2.0)
    tol = 1e-7 if method == "newton" else 1e-5  # L-BFGS's line search stops sooner
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        res = fit_layout(S, d, cfg, distances=D, tol=tol)
    assert res.converged and "gradient norm" in res.message
    assert res.grad_norm <= tol or "Newton step" in res.message  # the two stated tests
    lik = gplvm.Likelihood(S, d).in_units()
    target = PenalisedLikelihood(lik, gplvm.Stress(2.0).term(D, len(S), d))
    assert gradient_norm(target, res.latent) == pytest.approx(res.grad_norm, rel=1e-3, abs=1e-12)


@pytest.mark.parametrize("method", ["newton", "lbfgs", "hooke-jeeves"])
def test_a_fit_stopped_by_its_cap_warns_and_is_recorded_unconverged(method):
    S, d, D = _problem()
    stress = 0.0 if method == "hooke-jeeves" else 2.0
    cfg = settings("default", q=2, method=method, stress=stress)
    with pytest.warns(ConvergenceWarning, match="did not converge"):
        res = fit_layout(S, d, cfg, distances=D, max_iter=2)
    assert not res.converged and res.n_iterations <= 2
    assert "max_iter" in res.message and res.grad_norm > 0


def test_newton_ends_at_the_same_points_when_the_data_differ_in_their_last_bits():
    S, d, D = _problem(n=24, seed=5)
    cfg = settings("default", q=3, stress=5.0)
    ref = fit_layout(S, d, cfg, distances=D)
    assert ref.converged
    rng = np.random.default_rng(0)
    for _ in range(2):  # what another BLAS, or another machine, does to S and D
        noise = rng.standard_normal(S.shape)
        S2 = S * (1 + 1e-14 * (noise + noise.T))
        D2 = D * (1 + 1e-14 * np.abs(noise + noise.T))
        res = fit_layout(S2, d, cfg, distances=D2)
        assert res.converged
        assert np.abs(res.latent - ref.latent).max() < 1e-4  # within the stopping step_tol


@pytest.mark.parametrize("method", ["newton", "hooke-jeeves"])
def test_the_layout_does_not_depend_on_the_order_the_materials_are_given_in(method):
    S, d, D = _problem(n=14, seed=2)
    cfg = settings("default", q=2, method=method, stress=0.0 if method == "hooke-jeeves" else 3.0)
    names = [f"m{i:02d}" for i in range(len(S))]
    hashes = [f"{(7 * i) % 14:064x}" for i in range(len(S))]  # an order unlike the names'
    ref = fit_layout(S, d, cfg, distances=D, order=canonical_order(hashes, names))
    perm = np.random.default_rng(4).permutation(len(S))
    res = fit_layout(
        S[np.ix_(perm, perm)],
        d,
        cfg,
        distances=D[np.ix_(perm, perm)],
        order=canonical_order([hashes[i] for i in perm], [names[i] for i in perm]),
    )
    assert np.abs(res.latent - ref.latent[perm]).max() < 1e-6


def test_canonical_order_sorts_by_content_then_name():
    order = canonical_order(["b" * 64, "a" * 64, "b" * 64], ["z", "y", "x"])
    assert order.tolist() == [1, 2, 0]
    with pytest.raises(ValueError, match="one per material"):
        canonical_order(["a" * 64], ["x", "y"])


def test_a_newton_fit_through_the_noise_continuation_records_its_stages():
    S, d, D = _problem(n=20, seed=1)
    cfg = settings("default", q=2, stress=3.0)
    res = fit_layout(S, d, cfg, distances=D, continuation=CONTINUATION)
    assert [mu for mu, _ in res.stages] == [1e-2, 1e-3, cfg["noise"]]
    assert sum(k for _, k in res.stages) == res.n_iterations
    assert res.converged and "noise continuation" in res.message
    # the last stage is the fit at the kernel's own mu: a stationary point of its objective
    lik = gplvm.Likelihood(S, d).in_units()
    target = PenalisedLikelihood(lik, gplvm.Stress(3.0).term(D, len(S), d))
    assert gradient_norm(target, res.latent) == pytest.approx(res.grad_norm, rel=1e-3)
    assert res.log_likelihood == pytest.approx(lik._value(res.latent), rel=1e-12)
    plain = fit_layout(S, d, cfg, distances=D)  # the default: no continuation
    assert plain.stages == [(cfg["noise"], plain.n_iterations)]
    assert "continuation" not in plain.message


def test_the_continuation_skips_levels_at_or_below_the_kernels_noise():
    S, d, D = _problem(n=12, seed=4)
    cfg = settings("default", q=2, stress=1.0, noise=1e-3)
    res = fit_layout(S, d, cfg, distances=D, continuation=CONTINUATION)
    assert [mu for mu, _ in res.stages] == [1e-2, 1e-3]


def test_max_iter_caps_every_stage_of_the_continuation_together():
    S, d, D = _problem(n=16, seed=3)
    with pytest.warns(ConvergenceWarning, match="every noise stage together"):
        cfg = settings("default", q=2, stress=2.0)
        res = fit_layout(S, d, cfg, distances=D, max_iter=3, continuation=CONTINUATION)
    assert res.n_iterations <= 3 and not res.converged


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"continuation": (1e-3, 1e-2)}, "must decrease"),
        ({"continuation": (1e-2, -1.0)}, "continuation"),
        ({"continuation": 5}, "sequence of noise levels"),
    ],
)
def test_bad_continuations_are_rejected_clearly(kwargs, match):
    with pytest.raises(ValueError, match=match):
        gplvm.optimiser_options("newton", **kwargs)
    with pytest.raises(ValueError, match="option of method 'newton'"):
        gplvm.optimiser_options("lbfgs", continuation=(1e-2,))


def test_the_continued_fit_ends_at_the_same_points_when_the_data_differ_in_their_last_bits():
    S, d, D = _problem(n=30, seed=7)
    cfg = settings("default", q=4)
    ref = fit_layout(S, d, cfg, distances=D, continuation=CONTINUATION)
    rng = np.random.default_rng(1)
    for _ in range(2):
        noise = rng.standard_normal(S.shape)
        res = fit_layout(
            S * (1 + 1e-14 * (noise + noise.T)),
            d,
            cfg,
            distances=D * (1 + 1e-14 * np.abs(noise + noise.T)),
            continuation=CONTINUATION,
        )
        assert res.converged
        assert np.abs(res.latent - ref.latent).max() < 1e-4
        assert res.history[-1] == pytest.approx(ref.history[-1], rel=1e-9)


def _symmetric(n, seed, lowest):
    """A symmetric n x n matrix with eigenvalues ``lowest`` and log-spaced from 1 to 10, and a
    gradient."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    e = np.concatenate([[lowest], np.geomspace(1.0, 10.0, n - 1)])
    return (Q * e) @ Q.T, rng.standard_normal(n)


@pytest.mark.parametrize("lowest, size", [(0.5, 2.0), (0.5, 0.1), (-2.0, 0.5)])
def test_each_newton_step_minimises_its_model_within_the_trust_region(lowest, size):
    """With the whole space as its Krylov subspace the step is the trust-region problem's
    solution: the Newton step when H is positive definite and that step fits (``size``: the
    radius over its length), else ``(H + lam I) p = -g`` with ``lam >= max(0, -lowest
    eigenvalue)`` and ``|p| = radius``; and the model's decrease as predicted."""
    H, g = _symmetric(12, seed=2, lowest=lowest)
    newton = -np.linalg.solve(H, g)
    radius = size * np.linalg.norm(newton)
    p, boundary, predicted = _KrylovModel(lambda v: H @ v, g, 12).step(radius)
    if lowest > 0 and size > 1:
        assert not boundary and np.allclose(p, newton, rtol=1e-9, atol=1e-12)
    else:
        assert boundary and np.linalg.norm(p) == pytest.approx(radius, rel=1e-9)
        lam = -(p @ (H @ p + g)) / (p @ p)
        assert lam >= max(0.0, -lowest) - 1e-9
        assert np.abs(H @ p + lam * p + g).max() < 1e-8 * np.abs(g).max()
    assert predicted == pytest.approx(-(g @ p + 0.5 * p @ H @ p), rel=1e-9)
    assert predicted > 0


@pytest.mark.parametrize("along_lowest", [0.0, 1e-20])
def test_a_step_at_a_saddle_approached_along_its_stable_directions_follows_the_negative_curvature(
    along_lowest,
):
    """The hard case: in the model's eigenbasis the gradient has (almost) nothing along the
    direction of negative curvature; the step still goes to the boundary, mostly along it, and
    lowers the model."""
    H = np.diag([-1.0, 2.0, 3.0])
    g = np.array([along_lowest, 0.01, 0.01])
    model = object.__new__(_KrylovModel)  # the model in its eigenbasis, as Lanczos leaves it
    model.e, model.c, model.basis = np.diag(H).copy(), g, np.eye(3)
    for radius in (1.0, 10.0):
        p, boundary, predicted = model.step(radius)
        assert boundary and np.linalg.norm(p) == pytest.approx(radius, rel=1e-6)
        assert abs(p[0]) > 0.9 * radius
        assert predicted == pytest.approx(-(g @ p + 0.5 * p @ H @ p), rel=1e-9) and predicted > 0


def test_the_newton_step_changes_by_the_last_bits_when_the_data_do():
    """The step on a subspace smaller than the space (ill-conditioned, indefinite H), on the
    region's boundary and inside it, moves by about as much as the gradient's last bits."""
    H, g = _symmetric(200, seed=4, lowest=-1e-2)
    H = H + np.diag(np.geomspace(1e-3, 1.0, 200))  # stiff as well
    rng = np.random.default_rng(5)
    model = _KrylovModel(lambda v: H @ v, g, 24)
    inside = 2.0 * np.linalg.norm(-model.basis.T @ (model.c / model.e))
    kinds = set()
    for radius in (0.05, 1.0, inside):
        p, boundary, _ = model.step(radius)
        kinds.add(boundary)
        for _ in range(5):
            g2 = g * (1 + 1e-14 * rng.standard_normal(g.size))
            p2 = _KrylovModel(lambda v: H @ v, g2, 24).step(radius)[0]
            assert np.abs(p2 - p).max() < 1e-9 * max(radius, 1.0)
    assert kinds == {True, False}  # both kinds of step were checked


@pytest.mark.parametrize("krylov", [0, -3, 2.5, True, "64"])
def test_a_bad_krylov_size_is_rejected_clearly(krylov):
    with pytest.raises(ValueError, match="krylov"):
        gplvm.optimiser_options("newton", krylov=krylov)
    with pytest.raises(ValueError, match="option of method 'newton'"):
        gplvm.optimiser_options("lbfgs", krylov=8)

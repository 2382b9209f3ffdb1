"""Tests of the GPLVM fit (mitsuba_manifold.gp.gplvm): PCA start, rank-one updates, the
optimisers, on synthetic Gram matrices."""

import warnings

import numpy as np
import pytest
from gp_synthetic import dense_log_likelihood, gram, smooth_data

from mitsuba_manifold.errors import ConvergenceWarning
from mitsuba_manifold.gp import gplvm


@pytest.fixture(scope="module")
def problem():
    d = 1e6
    S = gram(smooth_data(24, seed=1), d)
    return S, d


# ------------------------------------------------------------------ PCA start


def test_pca_init_recovers_linear_layout_and_scales_with_l():
    rng = np.random.default_rng(4)
    coords = rng.standard_normal((15, 2)) * [3.0, 1.0]
    Z = coords @ rng.standard_normal((2, 50))  # rank 2: PCA is exact
    S = gram(Z)
    X = gplvm.pca_init(S, 2)
    assert X[:, 0].std() == pytest.approx(1.0, rel=1e-12)

    def distances(Y):
        return np.sqrt(((Y[:, None] - Y[None]) ** 2).sum(-1))

    Zc = Z - Z.mean(0)
    ratio = distances(X)[np.triu_indices(15, 1)] / distances(Zc)[np.triu_indices(15, 1)]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)  # an isometry up to one scale
    for l in (1e-3, 1e3):
        np.testing.assert_allclose(gplvm.pca_init(S, 2, length_scale=l), l * X, rtol=1e-12)
    # deterministic signs: the largest entry of each axis is positive
    big = np.abs(X).argmax(axis=0)
    assert np.all(X[big, [0, 1]] > 0)
    np.testing.assert_array_equal(gplvm.pca_init(S.copy(), 2), X)
    # axes beyond the rank of S are zero
    assert np.all(gplvm.pca_init(S, 4)[:, 2:] == 0)


# -------------------------------------------------------------- rank-updated inverse


def fresh(X, S, d, mu):
    K = gplvm.kernel_matrix(X, noise=mu)
    C = np.linalg.cholesky(K)
    Ci = np.linalg.inv(C)
    K_inv = Ci.T @ Ci
    return K, K_inv, 2 * np.log(np.diag(C)).sum(), np.sum(K_inv * S)


@pytest.mark.parametrize("mu,spread", [(1e-4, 1.0), (1e-4, 0.1), (1e-6, 0.1)])
def test_rank_updates_match_fresh_factorisation_after_many_moves(problem, mu, spread):
    S, d = problem
    n = len(S)
    rng = np.random.default_rng(5)
    X = rng.standard_normal((n, 3)) * spread
    state = gplvm.RankUpdatedInverse(X, S, d, noise=mu, refactor_every=10**6)
    for _ in range(400):
        i = rng.integers(n)
        state.move(i, 0.9 * state.latent[i] + 0.5 * spread * rng.standard_normal(3))
    # the updates did the work: no refactorisation beyond the initial one
    assert state.n_updates == 400
    assert state.n_refactorisations == 1
    K, K_inv, logdet, trace = fresh(state.latent, S, d, mu)
    assert np.linalg.cond(K) < 1e8
    np.testing.assert_array_equal(state.K, K)
    assert np.abs(state.K_inv - K_inv).max() <= 1e-8 * np.abs(K_inv).max()
    assert state.log_det == pytest.approx(logdet, rel=1e-8, abs=1e-8)
    assert state.trace == pytest.approx(trace, rel=1e-8)
    L = gplvm.log_likelihood(state.latent, S, d, noise=mu)
    assert state.log_likelihood == pytest.approx(L, rel=1e-8)


def test_trials_leave_state_unchanged_and_match_fresh_values(problem):
    S, d = problem
    X = gplvm.pca_init(S, 2)
    state = gplvm.RankUpdatedInverse(X, S, d)
    L0, K_inv0 = state.log_likelihood, state.K_inv
    cands = X[4] + np.array([[0.1, 0.0], [0.0, -0.3], [2.0, 2.0], [50.0, 0.0]])
    trial = state.try_moves(4, cands)
    for j, c in enumerate(cands):
        Y = X.copy()
        Y[4] = c
        assert trial.log_likelihood[j] == pytest.approx(gplvm.log_likelihood(Y, S, d), rel=1e-10)
    assert state.log_likelihood == L0
    np.testing.assert_array_equal(state.K_inv, K_inv0)
    assert state.accept(trial, 2) == pytest.approx(trial.log_likelihood[2], rel=1e-12)
    np.testing.assert_array_equal(state.latent[4], cands[2])
    with pytest.raises(ValueError, match="evaluated before the last change"):
        state.accept(trial, 1)


def test_ill_conditioned_move_is_evaluated_from_scratch(problem):
    S, d = problem
    X = gplvm.pca_init(S, 2)
    mu = 1e-10
    state = gplvm.RankUpdatedInverse(X, S, d, noise=mu)
    # put point 3 exactly onto point 8: the Schur complement drops to mu
    trial = state.try_moves(3, X[8][None, :])
    assert state.n_fresh_trials >= 1
    Y = X.copy()
    Y[3] = X[8]
    ref = gplvm.log_likelihood(Y, S, d, noise=mu)
    assert np.isfinite(trial.log_likelihood[0])
    assert trial.log_likelihood[0] == pytest.approx(ref, rel=1e-8)
    state.accept(trial, 0)
    assert state.log_likelihood == pytest.approx(ref, rel=1e-8)
    # and moving it away again is accurate too
    state.move(3, X[3])
    assert state.log_likelihood == pytest.approx(gplvm.log_likelihood(X, S, d, noise=mu), rel=1e-8)


# ----------------------------------------------------------------------- the fits


def test_hooke_jeeves_never_decreases_L(problem, monkeypatch):
    S, d = problem
    X0 = gplvm.pca_init(S, 2)
    seen, moves = [], []
    accept = gplvm.RankUpdatedInverse.accept

    def recording_accept(self, trial, j=0):
        before = self.log_likelihood
        after = accept(self, trial, j)
        moves.append((before, after))
        return after

    monkeypatch.setattr(gplvm.RankUpdatedInverse, "accept", recording_accept)
    res = gplvm.fit_latent(
        S, d, q=2, init=X0, callback=lambda it, X, L: seen.append((it, L)) and False
    )
    h = res.history
    assert res.method == "hooke-jeeves"
    assert h[0] == pytest.approx(gplvm.log_likelihood(X0, S, d), rel=1e-12)
    assert np.all(np.diff(h) >= 0)
    assert h[-1] > h[0]
    assert res.log_likelihood == pytest.approx(h[-1], rel=1e-12)
    assert res.log_likelihood == pytest.approx(gplvm.log_likelihood(res.latent, S, d), rel=1e-12)
    assert [it for it, _ in seen] == list(range(1, len(h)))
    assert res.converged and res.n_iterations == len(h) - 1
    assert res.max_drift < 1e-9
    assert res.n_evaluations > len(S) * res.n_iterations
    # every accepted single-point move was an improvement
    assert len(moves) > len(S)
    assert all(after > before for before, after in moves)


def test_both_optimisers_improve_from_the_same_start_and_agree():
    d = 1e6
    S = gram(smooth_data(10, hidden=2, seed=0), d)
    X0 = gplvm.pca_init(S, 2)
    L0 = gplvm.log_likelihood(X0, S, d)
    hj = gplvm.fit_latent(S, d, q=2, method="hooke-jeeves", init=X0)
    lb = gplvm.fit_latent(S, d, q=2, method="lbfgs", init=X0)
    for res in (hj, lb):
        assert res.history[0] == pytest.approx(L0, rel=1e-12)
        assert np.all(np.diff(res.history) >= 0)
        assert res.log_likelihood > L0
        assert np.isfinite(res.latent).all()
    gain = max(hj.log_likelihood, lb.log_likelihood) - L0
    assert abs(hj.log_likelihood - lb.log_likelihood) < 1e-3 * gain
    assert lb.converged
    # both end near a stationary point
    _, grad0 = gplvm.log_likelihood_grad(X0, S, d)
    for res in (hj, lb):
        _, grad = gplvm.log_likelihood_grad(res.latent, S, d)
        assert np.abs(grad).max() < 1e-2 * np.abs(grad0).max()


@pytest.mark.parametrize("method", ["hooke-jeeves", "lbfgs"])
def test_fit_scales_with_length_scale(problem, method):
    """Scaling l and the latent points together changes nothing (paper Sec. 3)."""
    S, d = problem
    base = gplvm.fit_latent(S, d, q=2, method=method, options=_options(method, 40))
    for l in (1e-3, 1e3):
        res = gplvm.fit_latent(
            S, d, q=2, method=method, length_scale=l, options=_options(method, 40)
        )
        assert res.log_likelihood == pytest.approx(base.log_likelihood, rel=1e-7)
        np.testing.assert_allclose(res.history[0], base.history[0], rtol=1e-10)
        if method == "hooke-jeeves":
            np.testing.assert_allclose(res.latent / l, base.latent, rtol=1e-8, atol=1e-8)


# ------------------------------------------------------------------- stiff, extreme


@pytest.mark.parametrize("method", ["hooke-jeeves", "lbfgs", "newton"])
@pytest.mark.parametrize("mu", [1e-4, 1e-10])
def test_duplicate_materials(method, mu):
    d = 1e5
    Z = smooth_data(14, seed=7)
    Z[5] = Z[2]
    Z[9] = Z[2]  # S singular beyond the mean
    S = gram(Z, d)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # no silent overflow/invalid value
        warnings.simplefilter("ignore", ConvergenceWarning)  # coincident points: stiff
        res = gplvm.fit_latent(S, d, q=2, method=method, noise=mu)
    assert np.isfinite(res.latent).all() and np.isfinite(res.history).all()
    assert np.all(np.diff(res.history) >= 0)
    assert res.log_likelihood > res.history[0]
    assert res.log_likelihood == pytest.approx(
        gplvm.log_likelihood(res.latent, S, d, noise=mu), rel=1e-9
    )


def test_duplicates_coincide_under_hooke_jeeves():
    d = 1e5
    Z = smooth_data(14, seed=7)
    Z[5] = Z[2]
    S = gram(Z, d)
    X = gplvm.fit_latent(S, d, q=2).latent
    dist = np.sqrt(((X[:, None] - X[None]) ** 2).sum(-1))
    others = dist[np.triu_indices(14, 1)]
    assert dist[2, 5] < 1e-3 * np.sort(others)[1]


def test_coincident_points_without_noise_fail_clearly(problem):
    S, d = problem
    X = gplvm.pca_init(S, 2)
    X[1] = X[0]
    with pytest.raises(gplvm.NotPositiveDefiniteError, match="not positive definite"):
        gplvm.log_likelihood(X, S, d, noise=1e-300)
    with pytest.raises(np.linalg.LinAlgError, match="noise"):
        gplvm.fit_latent(S, d, q=2, init=X, noise=1e-300)


@pytest.mark.parametrize("method", ["hooke-jeeves", "lbfgs", "newton"])
def test_far_away_point_decouples(problem, method):
    S, d = problem
    mu = 1e-4
    X = gplvm.pca_init(S, 2)
    X[6] = [1e6, -1e6]
    # K is block diagonal: L splits into the other points' L and point 6's own term
    rest = np.delete(np.arange(len(S)), 6)
    expected = (
        dense_log_likelihood(X[rest], S[np.ix_(rest, rest)], d, 1.0, mu)
        - 0.5 * d * np.log(1 + mu)
        - 0.5 * S[6, 6] / (1 + mu)
    )
    L, grad = gplvm.log_likelihood_grad(X, S, d, noise=mu)
    assert L == pytest.approx(expected, rel=1e-10)
    assert np.all(grad[6] == 0) and np.isfinite(grad).all()
    seen = []
    res = gplvm.fit_latent(
        S,
        d,
        q=2,
        method=method,
        init=X,
        noise=mu,
        options=_options(method, 200),
        callback=lambda it, latent, L: seen.append(latent.copy()),
    )
    assert np.isfinite(res.latent).all()
    # no force reaches it (before the pose); Newton's steps are kept off the rigid motions
    # (rotations about the mean, which a point at 1e6 dominates), which moves it by 1e-7 of a step
    moved = np.abs(seen[-1][6] - X[6]).max()
    assert moved <= (1e-12 * np.abs(X[6]).max() if method == "newton" else 0.0)
    assert res.log_likelihood > L
    assert np.all(np.diff(res.history) >= 0)


@pytest.mark.parametrize("method", ["hooke-jeeves", "lbfgs"])
def test_gram_spanning_many_orders_of_magnitude(method):
    """Like a chrome table beside diffuse ones: materials' energies differ by 1e12."""
    d = 4.4e6
    scales = 10.0 ** np.linspace(-3, 3, 16)[np.random.default_rng(8).permutation(16)]
    S = scales[:, None] * gram(smooth_data(16, seed=8), d) * scales[None, :]
    assert np.diag(S).max() / np.diag(S).min() > 1e11
    res = gplvm.fit_latent(S, d, q=2, method=method, options=_options(method, 300))
    assert np.isfinite(res.latent).all()
    assert np.all(np.diff(res.history) >= 0)
    assert res.log_likelihood > res.history[0]
    assert res.log_likelihood == pytest.approx(gplvm.log_likelihood(res.latent, S, d), rel=1e-10)
    if method == "hooke-jeeves":
        assert res.max_drift < 1e-9


def test_callback_can_stop_the_fit(problem):
    S, d = problem
    for method in ("hooke-jeeves", "lbfgs"):
        res = gplvm.fit_latent(S, d, method=method, callback=lambda it, X, L: it >= 2)
        assert res.n_iterations == 2
        assert not res.converged and "callback" in res.message
        assert res.log_likelihood == pytest.approx(res.history[-1], rel=1e-12)


# --------------------------------------------------------------------- validation


def _S():
    return gram(smooth_data(6, dd=20, seed=9))


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(S=np.ones((3, 4))), "square"),
        (dict(S=np.ones((1, 1))), "at least 2"),
        (dict(S=np.where(np.eye(6, dtype=bool), np.nan, _S())), "non-finite"),
        (dict(S=_S() + np.triu(np.ones((6, 6)), 1)), "not symmetric"),
        (dict(S=-_S()), "positive semi-definite"),
        (dict(S=[["a"] * 6] * 6), "real numeric"),
        (dict(d=0), "`d` "),
        (dict(d=2.5), "`d` "),
        (dict(d=True), "`d` "),
        (dict(q=0), "`q` must"),
        (dict(q=9), "`q` must"),
        (dict(q=2.0), "`q` must"),
        (dict(init=np.zeros((5, 2))), "5 points"),
        (dict(init=np.zeros((6, 3))), "expected q = 2"),
        (dict(init=np.full((6, 2), np.inf)), "non-finite"),
        (dict(length_scale=0.0), "length_scale"),
        (dict(length_scale=-1.0), "length_scale"),
        (dict(noise=0.0), "noise"),
        (dict(noise=np.nan), "noise"),
        (dict(method="newtons"), "unknown `method`"),
        (dict(options=gplvm.LBFGSOptions()), "must be a HookeJeevesOptions"),
    ],
)
def test_bad_input_is_rejected_clearly(kwargs, match):
    args = dict(S=_S(), d=100, q=2)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        gplvm.fit_latent(args.pop("S"), args.pop("d"), **args)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(max_iter=-1), "max_iter"),
        (dict(tol=-1e-3), "tol"),
        (dict(initial_step=0.0), "initial_step"),
    ],
)
def test_bad_optimiser_options_are_rejected_clearly(kwargs, match):
    for method in gplvm.METHODS:
        with pytest.raises(ValueError, match=match):
            gplvm.optimiser_options(method, **kwargs)


def _options(method, max_iter):
    return gplvm.optimiser_options(method, max_iter=max_iter)


def test_bad_latent_is_rejected_by_the_objective():
    S = _S()
    with pytest.raises(ValueError, match="shape"):
        gplvm.log_likelihood(np.zeros(6), S, 10)
    with pytest.raises(ValueError, match="latent dimension 9"):
        gplvm.log_likelihood(np.zeros((6, 9)), S, 10)
    with pytest.raises(ValueError, match="non-finite"):
        gplvm.log_likelihood_grad(np.full((6, 2), np.nan), S, 10)
    with pytest.raises(ValueError, match="Gram matrix `S` is zero"):
        gplvm.pca_init(np.zeros((4, 4)), 2)

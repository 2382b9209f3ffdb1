"""The latent search shared by the basis match and the render match (basis/inverse/search.py)."""

import numpy as np
import pytest

from mitsuba_manifold.basis.inverse import search
from mitsuba_manifold.manifold.model import Manifold


class WeightsTarget:
    """``E(w) = |w - target|^2``: an objective of the weights, with its gradient and a batch form."""

    def __init__(self, target):
        self.target = np.asarray(target, float)

    def __call__(self, w):
        d = w - self.target
        return float(d @ d), 2.0 * d

    def batch(self, W):
        d = W - self.target
        return np.einsum("mn,mn->m", d, d), None


@pytest.fixture(scope="module")
def manifold(small_manifold):
    return Manifold.load(small_manifold)


def _between(m, i, j, t=0.4):
    return (1 - t) * m.latent[i] + t * m.latent[j]


def test_descent_recovers_the_point_whose_weights_it_matches(manifold):
    m = manifold
    x_true = _between(m, 0, 2)
    obj = WeightsTarget(m.weights(x_true)[1])
    bounds = search.box(m)
    X, err = search.scan(m, obj, 0.0, bounds, 512, seed=3)
    best = int(np.argmin(obj.batch(np.eye(m.n))[0]))
    runs = [
        search.descend(m, obj, 0.0, x0, bounds, 200)
        for x0 in search.start_points(m, best, X, err, 3)
    ]
    top = min(runs, key=lambda r: r["objective"])
    assert top["objective"] < 1e-8 * max(1.0, obj(m.weights(m.latent[best])[1])[0])
    np.testing.assert_allclose(m.weights(top["x"])[1], obj.target, atol=1e-4)
    assert all(r["n_evaluations"] > 0 for r in runs)


def test_scan_stays_in_the_box_and_scores_every_point(manifold):
    m = manifold
    bounds = search.box(m, margin=0.1)
    X, err = search.scan(m, WeightsTarget(np.full(m.n, 1.0 / m.n)), 0.0, bounds, 300, seed=1)
    lo, hi = np.array(bounds).T
    assert X.shape == (300, m.q) and err.shape == (300,) and np.isfinite(err).all()
    assert (X >= lo).all() and (X <= hi).all()
    assert search.scan(m, WeightsTarget(np.zeros(m.n)), 0.0, bounds, 0)[0].shape == (0, m.q)


def test_starts_begin_at_the_best_material_and_keep_apart(manifold):
    m = manifold
    rng = np.random.default_rng(0)
    X = m.latent[rng.integers(m.n, size=200)] + 0.3 * rng.standard_normal((200, m.q))
    err = rng.random(200)
    starts = search.start_points(m, 2, X, err, 4, spread=0.25)
    assert len(starts) <= 4 and np.linalg.norm(starts[0] - m.latent[2]) < 1e-5 * m.length_scale
    assert not np.array_equal(starts[0], m.latent[2])  # nudged off the training point
    for a in range(len(starts)):
        for b in range(a + 1, len(starts)):
            assert np.linalg.norm(starts[a] - starts[b]) >= 0.25 * m.length_scale - 1e-9
    nearest = search.start_points(m, 2, np.zeros((0, m.q)), np.zeros(0), 3)
    d = np.linalg.norm(m.latent - m.latent[2], axis=1)
    np.testing.assert_allclose(
        [np.linalg.norm(s - m.latent[2]) for s in nearest], np.sort(d)[:3], atol=1e-5
    )

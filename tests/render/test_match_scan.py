"""The scan that chooses match_render's starts: the noise-free error estimate from two renders, and
the scan on a rendered target."""

import numpy as np
import pytest

from mitsuba_manifold.render.inverse import scan as ms


def _synthetic(rng, n=6, p=400, noisy=0, sigma=0.6):
    """Noise-free images T (n, p) of n materials, a target equal to material 0 (the glossy one,
    whose renders are noisy: sigma on ``noisy`` of them), two independent noisy render sets."""
    T = rng.uniform(0.2, 1.0, size=(n, p))
    T[1] = T[0] + 0.08  # a matte near-miss
    scale = np.full(n, 0.02)
    scale[noisy] = sigma
    A = T + scale[:, None] * rng.standard_normal((n, p))
    B = T + scale[:, None] * rng.standard_normal((n, p))
    return T, A, B, T[0].copy(), np.full(p, 1.0 / p)


def test_cross_error_is_free_of_the_render_noise_and_ranks_the_noisy_true_material_first():
    rng = np.random.default_rng(1)
    T, A, B, t, c = _synthetic(rng)
    obj = ms.CrossMSE(A, B, t, c)
    cross = obj.batch(np.eye(len(T)))[0]
    plain = ((A - t) ** 2 * c).sum(axis=1)  # the error of one render adds its variance
    truth = ((T - t) ** 2 * c).sum(axis=1)
    assert np.argmin(cross) == 0 and np.argmin(plain) != 0
    assert np.allclose(cross[1:], truth[1:], atol=2e-3)
    assert abs(cross[0]) < 0.05 and plain[0] > 0.3
    # the mean over many noise draws is the noise-free error (unbiased), for a blend too
    w = np.array([0.5, 0.3, 0.2, 0.0, 0.0, 0.0])
    draws = [ms.CrossMSE(*_synthetic(np.random.default_rng(s))[1:])(w)[0] for s in range(200)]
    T0, _, _, t0, c0 = _synthetic(np.random.default_rng(0))
    assert np.mean(draws) == pytest.approx(float(((w @ T0 - t0) ** 2 * c0).sum()), abs=3e-3)


@pytest.mark.parametrize("exposure_free", [False, True])
def test_cross_error_gradient_batch_and_exposure(exposure_free):
    rng = np.random.default_rng(2)
    _, A, B, t, c = _synthetic(rng, sigma=0.05)
    obj = ms.CrossMSE(A, B, 1.7 * t if exposure_free else t, c, exposure_free)
    w = rng.dirichlet(np.ones(6))
    e, g, s = obj(w)
    eb, sb = obj.batch(w[None])
    assert e == pytest.approx(float(eb[0])) and s == pytest.approx(float(sb[0]))
    if exposure_free:
        assert obj(np.eye(6)[0])[2] == pytest.approx(1.7, rel=0.05)
    else:
        assert s == 1.0
    h = 1e-6
    fd = [(obj(w + h * d)[0] - obj(w - h * d)[0]) / (2 * h) for d in np.eye(6)]
    assert np.allclose(g, fd, rtol=1e-5, atol=1e-8)


@pytest.mark.render
@pytest.mark.usefixtures("variant")
def test_scan_finds_a_glossy_target_and_checks_its_candidates(small_manifold):
    """A target at a point between chrome and steel (mirror-like: at a few spp their renders are the
    noisiest): the scan ranks one of them first, its starts are checked candidates, apart, off the
    training points."""
    from mitsuba_manifold.manifold.model import Manifold
    from mitsuba_manifold.render.inverse import match_render as mr
    from mitsuba_manifold.render.scene import scenes

    sphere = scenes.scene_path("sphere")
    m = Manifold.load(small_manifold)
    x_true = 0.7 * m.latent[m.index("chrome")] + 0.3 * m.latent[m.index("steel")]
    target = scenes.render_reference(
        sphere, small_manifold, x_true, 256, seed=3, resolution=16, max_depth=2
    )
    opts = mr.MatchRenderOptions(scan_spp=8, starts=2, max_depth=2, progress=False)
    problem = mr._Problem([mr.View(sphere, target)], small_manifold, opts)
    found = ms.scan(problem, opts, 16)
    assert m.names[found["ranked"][0][1]] in ("chrome", "steel")
    assert 1 <= len(found["starts"]) <= 2 and found["candidates"]
    checked = [c["checked_error"] for c in found["candidates"]]
    assert checked == sorted(checked)
    xs = [x for _, _, x in found["starts"]]
    assert all(
        np.linalg.norm(a - b) >= 0.25 * m.length_scale for i, a in enumerate(xs) for b in xs[:i]
    )
    for _, x0, _ in found["starts"]:
        assert np.max(m.weights(x0)[1]) < ms.AT_TRAINING_POINT
    best = found["starts"][0][2]
    near_truth = problem.evaluate(x_true, 1.0, 64, 5)[0]
    assert problem.evaluate(best, 1.0, 64, 5)[0] <= 1.5 * near_truth

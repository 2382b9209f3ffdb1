"""The differentiable latent point of ``manifold_brdf`` (:mod:`mitsuba_manifold.render.plugin.ad`): the custom
operation's Jacobian, the gradient of a full-GI ``prb`` render against central finite differences
(fixed sampling proxy, no Russian roulette), training-point starts, and the primal image of AD mode
against the combined table."""

import gc

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np
import pytest

import mitsuba_manifold.render  # noqa: F401  (selects a working libLLVM before drjit loads; the plugins)
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.render.plugin import ad  # noqa: E402

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]

RES, SPP, DEPTH = 12, 8, 3


@pytest.fixture(scope="module")
def manifold(small_manifold):
    return Manifold.load(small_manifold)


def _scene(manifold_path, x, terms=4, prune=0.01, defaults=False):
    """A sphere on a floor sharing the manifold material, under a constant sky (inter-reflections);
    ``defaults``: the plugin's own ``ad_terms`` and ``prune``."""
    mat = {
        "type": "manifold_brdf",
        "id": "mat",
        "manifold": manifold_path,
        "x": ", ".join(map(str, x)),
    }
    if not defaults:
        mat.update(ad_terms=terms, prune=prune)
    return mi.load_dict(
        {
            "type": "scene",
            "mat": mat,
            "sensor": {
                "type": "perspective",
                "fov": 40,
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=[0, 1.2, 3.5], target=[0, 0, 0], up=[0, 1, 0]
                ),
                "film": {
                    "type": "hdrfilm",
                    "width": RES,
                    "height": RES,
                    "rfilter": {"type": "box"},
                },
            },
            "sphere": {"type": "sphere", "bsdf": {"type": "ref", "id": "mat"}},
            "floor": {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f()
                .translate([0, -1, 0])
                .rotate([1, 0, 0], -90)
                .scale(4),
                "bsdf": {"type": "ref", "id": "mat"},
            },
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "lamp": {
                "type": "point",
                "position": [1.5, 2.5, 1.5],
                "intensity": {"type": "rgb", "value": 8.0},
            },
        },
        optimize=False,
    )


def _x0(manifold):
    """A point between two materials (no training point: nonzero Jacobian)."""
    return 0.55 * manifold.latent[1] + 0.45 * manifold.latent[2]


def _grad_enabled(scene, x):
    params = mi.traverse(scene)
    params["mat.x"] = mi.Float(np.asarray(x, dtype=np.float32))
    dr.enable_grad(params["mat.x"])
    params.update()
    return params


PRB = {"type": "prb", "max_depth": DEPTH, "rr_depth": 1000}


def _mean_image(scene, params, x, seed):
    params["mat.x"] = mi.Float(np.asarray(x, dtype=np.float32))
    dr.enable_grad(params["mat.x"])
    params.update()
    with dr.suspend_grad():
        img = mi.render(scene, params, integrator=mi.load_dict(PRB), spp=SPP, seed=seed)
    return float(np.array(img, dtype=np.float64).mean())


def _central_differences(scene, params, x0, h=2e-3, seed=1):
    fd = []
    for j in range(x0.size):
        e = np.eye(x0.size)[j] * h
        fd.append(
            (_mean_image(scene, params, x0 + e, seed) - _mean_image(scene, params, x0 - e, seed))
            / (2 * h)
        )
    return np.array(fd)


def test_custom_op_jacobian_with_rescaled_active_set(manifold):
    x0 = _x0(manifold)
    _, w = manifold.weights(x0)
    J = manifold.weights_jacobian(x0)
    idx = ad.choose_active(w, J, 3, ad.typical_step(manifold.latent))

    def fn(x):
        _, w = manifold.weights(x)
        return ad.rescaled(w, manifold.weights_jacobian(x), idx)

    v, Jv = fn(x0)
    assert v.sum() == pytest.approx(1.0) and np.allclose(Jv.sum(axis=0), 0.0, atol=1e-9)
    h = 1e-6
    fd = np.stack(
        [(fn(x0 + h * e)[0] - fn(x0 - h * e)[0]) / (2 * h) for e in np.eye(manifold.q)], axis=1
    )
    np.testing.assert_allclose(Jv, fd, rtol=1e-4, atol=1e-6)
    full = ad.rescaled(w, J, np.arange(manifold.n))[1]
    np.testing.assert_allclose(
        full, J, atol=1e-12
    )  # nothing dropped: exactly Manifold.weights_jacobian

    x = mi.Float(x0.astype(np.float32))
    dr.enable_grad(x)
    out = ad.latent_weights(x, fn)
    c = np.arange(1.0, len(idx) + 1)
    dr.backward(dr.sum(out * mi.Float(c)))
    np.testing.assert_allclose(np.array(dr.grad(x)), c @ Jv, rtol=1e-5)
    x = mi.Float(x0.astype(np.float32))
    dr.enable_grad(x)
    out = ad.latent_weights(x, fn)
    dr.set_grad(x, mi.Float([1.0, -2.0]))
    dr.forward_to(out)
    np.testing.assert_allclose(np.array(dr.grad(out)), Jv @ [1.0, -2.0], rtol=1e-5, atol=1e-7)


def test_active_set_by_weight_and_jacobian_with_hysteresis():
    w = np.array([0.5, 0.3, 0.15, 0.05])
    J = np.array([[0.0], [0.0], [0.0], [10.0]])
    assert ad.choose_active(w, J, 2, step=0.0).tolist() == [0, 1]
    assert ad.choose_active(w, J, 2, step=0.1).tolist() == [0, 3]  # the weight that moves fast
    assert ad.choose_active(w, J * 0, 2, step=0.0, previous=[0, 2]).tolist() == [0, 1]
    w2 = np.array([0.5, 0.27, 0.3, 0.0])  # 2 slightly ahead of the member 1: kept (hysteresis)
    assert ad.choose_active(w2, J * 0, 2, step=0.0, previous=[0, 1]).tolist() == [0, 1]


@pytest.mark.parametrize(
    "mode", ["backward", "render_forward", "forward_to", "forward", "forward_weights"]
)
def test_render_gradient_matches_central_differences(small_manifold, manifold, mode):
    """Backward and forward mode the way a Mitsuba user writes them: ``dr.backward`` of ``mi.render``;
    ``dr.set_grad(x, dx)`` then ``integrator.render_forward`` or ``mi.render`` and ``dr.forward_to``;
    ``dr.forward(x)``; and the older ``bsdf.forward_weights(dx)`` leaf."""
    gc.collect()  # no AD graph of an earlier test's scene left (prb's forward mode traverses from the enqueued)
    x0 = _x0(manifold)
    scene = _scene(small_manifold, x0)
    params = _grad_enabled(scene, x0)
    bsdf = [b for b in scene.shapes()][0].bsdf()
    assert bsdf.differentiable and len(bsdf.active_set.idx) == 4
    bsdf.hold_proxy = True  # one sampling proxy for every render below
    integ = mi.load_dict(PRB)
    # the gradient pass uses seed_grad: the finite differences render with that seed
    if mode == "backward":
        img = mi.render(scene, params, integrator=integ, spp=SPP, seed=7, seed_grad=1)
        dr.backward(dr.mean(img, axis=None))
        grad = np.array(dr.grad(params["mat.x"]))
    elif mode == "forward":  # dr.forward(x): the derivative along dx = (1, ..., 1)
        img = mi.render(scene, params, integrator=integ, spp=SPP, seed=7, seed_grad=1)
        dr.forward(params["mat.x"])
        grad = np.array([float(np.array(dr.grad(img), dtype=np.float64).mean())])
    else:
        grad = []
        for j in range(manifold.q):
            params = _grad_enabled(scene, x0)
            dx = np.eye(manifold.q)[j]
            if mode == "forward_weights":
                leaf = bsdf.forward_weights(dx)
                d_img = mi.load_dict(PRB).render_forward(scene, {"w": leaf}, seed=1, spp=SPP)
            else:
                dr.set_grad(params["mat.x"], mi.Float(dx.astype(np.float32)))
                if mode == "render_forward":
                    d_img = integ.render_forward(scene, params, seed=1, spp=SPP)
                else:
                    img = mi.render(scene, params, integrator=integ, spp=SPP, seed=7, seed_grad=1)
                    dr.forward_to(img)
                    d_img = dr.grad(img)
            grad.append(float(np.array(d_img, dtype=np.float64).mean()))
        grad = np.array(grad)
    fd = _central_differences(scene, params, x0)
    fd = np.array([fd.sum()]) if mode == "forward" else fd
    assert np.abs(grad).max() > 0
    np.testing.assert_allclose(grad, fd, rtol=2e-2, atol=2e-3 * np.abs(fd).max())


def test_traced_weights_value_and_derivatives():
    """:func:`ad.traced_weights`: value ``v`` exactly, forward ``J dx``, backward ``J^T dw``."""
    v = np.array([0.6, 0.3, 0.1])
    J = np.array([[1.0, -2.0], [0.5, 0.25], [-1.5, 1.75]])
    x = mi.Float([0.2, -0.4])
    dr.enable_grad(x)
    w = ad.traced_weights(x, mi.Float(v), mi.Float(J.ravel()))
    np.testing.assert_array_equal([float(np.array(wi)[0]) for wi in w], v.astype(np.float32))
    dr.backward(sum(c * wi for c, wi in zip((1.0, 2.0, 3.0), w)))
    np.testing.assert_allclose(np.array(dr.grad(x)), np.array([1.0, 2.0, 3.0]) @ J, rtol=1e-6)
    x = mi.Float([0.2, -0.4])
    dr.enable_grad(x)
    w = ad.traced_weights(x, mi.Float(v), mi.Float(J.ravel()))
    dr.set_grad(x, mi.Float([1.0, -2.0]))
    dr.forward_to(*w)
    np.testing.assert_allclose(
        [float(np.array(dr.grad(wi))[0]) for wi in w], J @ [1.0, -2.0], rtol=1e-6
    )


def _adam_moves(scene, x0, steps=2):
    """How far ``steps`` Adam iterations on the mean image take ``x`` from ``x0``."""
    params = _grad_enabled(scene, x0)
    opt = mi.ad.Adam(lr=0.05)
    opt["mat.x"] = params["mat.x"]
    params.update(opt)
    for it in range(steps):
        img = mi.render(
            scene, params, integrator=mi.load_dict(PRB), spp=4, seed=2 * it, seed_grad=2 * it + 1
        )
        dr.backward(dr.mean(img, axis=None))
        opt.step()
        params.update(opt)
    return float(np.linalg.norm(np.array(opt["mat.x"], dtype=np.float64) - x0))


def test_training_point_has_zero_gradient_and_jitter_moves(small_manifold, manifold):
    xi = manifold.latent[3]
    assert np.abs(manifold.weights_jacobian(xi)).max() < 1e-8  # Shepard: flat at a training point
    moved = ad.jitter(xi, manifold)
    others = np.linalg.norm(manifold.latent - xi, axis=1)[np.arange(manifold.n) != 3]
    assert 0 < np.linalg.norm(moved - xi) < others.min()
    assert np.abs(manifold.weights_jacobian(moved)).max() > 1e-6
    assert np.array_equal(
        ad.jitter(_x0(manifold), manifold), _x0(manifold)
    )  # off the data: unchanged
    scene = _scene(
        small_manifold, xi, prune=0.0
    )  # pruning would keep one material so near a training point
    assert (
        _adam_moves(scene, xi) < 1e-4
    )  # started on the training point: stuck (float32 rounding aside)
    assert _adam_moves(scene, moved) > 1e-2  # jittered: moves (Adam steps of ~lr = 0.05)


def test_ad_mode_primal_equals_combined_table(small_manifold, manifold):
    """K = N and no pruning: the AD mode renders the same material as today's combined table;
    without gradients the plugin stays on the combined table."""
    x0 = _x0(manifold)
    scene = _scene(small_manifold, x0, terms=manifold.n, prune=0.0)
    bsdf = [b for b in scene.shapes()][0].bsdf()
    integ = mi.load_dict({"type": "path", "max_depth": DEPTH})
    params = mi.traverse(scene)
    assert (
        params.flags("mat.x") & mi.ParamFlags.NonDifferentiable == 0
    )  # differentiable in AD variants
    params["mat.x"] = mi.Float(x0.astype(np.float32))
    params.update()
    assert not bsdf.differentiable and bsdf.active_set is None
    plain = np.array(mi.render(scene, integrator=integ, spp=16, seed=3))
    params = _grad_enabled(scene, x0)
    bsdf.hold_proxy = False
    assert bsdf.differentiable
    with dr.suspend_grad():
        in_ad = np.array(mi.render(scene, integrator=integ, spp=16, seed=3))
    np.testing.assert_allclose(in_ad, plain, rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(bsdf.weights.sum(), 1.0)


@pytest.mark.parametrize("kind", ["prbvolpath", "direct_projective"])
def test_other_differentiable_integrators(small_manifold, manifold, kind):
    """prbvolpath (as prb) and direct_projective (direct light only) differentiate x too: their
    gradients agree in sign with prb's, limited to the same depth."""
    x0 = _x0(manifold)
    scene = _scene(small_manifold, x0)
    grads = []
    for d in (
        dict(PRB, max_depth=2),
        {"type": kind} if kind == "direct_projective" else dict(PRB, type=kind),
    ):
        params = _grad_enabled(scene, x0)
        img = mi.render(scene, params, integrator=mi.load_dict(d), spp=16, seed=2, seed_grad=3)
        dr.backward(dr.mean(img, axis=None))
        grads.append(np.array(dr.grad(params["mat.x"])))
    assert np.abs(grads[1]).max() > 0
    assert np.all(np.sign(grads[0]) == np.sign(grads[1]))


def test_active_set_switch_recompiles_nothing(small_manifold, manifold):
    """K is fixed: moving x across the data replaces slots and weights, never the kernels."""
    x0 = _x0(manifold)
    scene = _scene(small_manifold, x0, terms=2)
    bsdf = scene.shapes()[0].bsdf()
    integ = mi.load_dict(PRB)

    def step(x, seed):
        params = _grad_enabled(scene, x)
        img = mi.render(scene, params, integrator=integ, spp=2, seed=seed, seed_grad=seed + 1)
        dr.backward(dr.mean(img, axis=None))
        return [k for k in dr.kernel_history() if k.get("cache_hit") is False]

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        step(x0, 0)
        first = bsdf.active_set.idx.copy()
        far = 0.5 * (manifold.latent[5] + manifold.latent[6])
        compiled = step(far, 2)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert set(bsdf.active_set.idx.tolist()) != set(first.tolist()) and bsdf.active_set.switches > 0
    assert compiled == []


def _eval_at(bsdf, directions):
    ctx, out = mi.BSDFContext(), []
    for wi, wo in directions:
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = mi.Vector3f(*map(float, wi))
        f, p = bsdf.eval_pdf(ctx, si, mi.Vector3f(*map(float, wo)))
        out.append(np.concatenate([np.ravel(f), np.ravel(p)]).astype(np.float64))
    return np.array(out)


@pytest.mark.parametrize("interpolation", ["nearest", "linear"])
def test_scalar_variant_keeps_the_combined_table_and_ad_mode_agrees(
    small_manifold, manifold, interpolation
):
    """scalar_rgb: x is NonDifferentiable and the plugin evaluates today's combined table; the AD
    mode of llvm_ad_rgb (K = N, no pruning) evaluates the same values (and a pdf from the same proxy)."""
    rng = np.random.default_rng(4)
    v = rng.normal(size=(12, 2, 3))
    v[..., 2] = np.abs(v[..., 2])  # upper hemisphere
    dirs = list(v / np.linalg.norm(v, axis=-1, keepdims=True))
    x = ", ".join(map(str, _x0(manifold)))
    spec = {
        "type": "manifold_brdf",
        "manifold": small_manifold,
        "x": x,
        "prune": 0.0,
        "ad_terms": manifold.n,
        "interpolation": interpolation,
    }
    results = {}
    for variant in ("scalar_rgb", "llvm_ad_rgb"):
        mi.set_variant(variant)
        bsdf = mi.load_dict(spec)
        params = mi.traverse(bsdf)
        non_diff = bool(params.flags("x") & mi.ParamFlags.NonDifferentiable)
        assert non_diff == (variant == "scalar_rgb")
        if variant == "llvm_ad_rgb":
            dr.enable_grad(params["x"])
            params.update()
            assert bsdf.differentiable
        results[variant] = _eval_at(bsdf, dirs)
    assert (results["scalar_rgb"][:, 0] > 0).any()
    np.testing.assert_allclose(results["llvm_ad_rgb"], results["scalar_rgb"], rtol=1e-4, atol=1e-6)


def test_gradient_at_defaults_is_that_of_the_plain_render(small_manifold, manifold):
    """Default ``prune`` and ``ad_terms``: the AD mode renders the material the plain render does
    (the pruned, rescaled combination), and ``dr.grad`` of a rendered loss agrees with central
    differences of plain renders within 2% (common random numbers: one seed and, through
    ``hold_proxy``, one sampling density, so that the same random numbers draw the same paths)."""
    gc.collect()
    x0 = _x0(manifold)
    scene = _scene(small_manifold, x0, defaults=True)
    bsdf = scene.shapes()[0].bsdf()
    _, w = manifold.weights(x0)
    pruned = manifold.prune(w).keep
    assert 1 < len(pruned) < manifold.n  # pruning drops materials at this point
    integ = mi.load_dict(PRB)

    def plain(x, seed):
        params = mi.traverse(scene)
        params["mat.x"] = mi.Float(np.asarray(x, dtype=np.float32))
        params.update()
        assert not bsdf.differentiable
        return np.array(mi.render(scene, integrator=integ, spp=SPP, seed=seed), dtype=np.float64)

    base = plain(x0, 1)
    bsdf.hold_proxy = True
    params = _grad_enabled(scene, x0)
    assert bsdf.differentiable and sorted(bsdf.used_names) == sorted(
        manifold.names[i] for i in pruned
    )
    with dr.suspend_grad():
        in_ad = np.array(mi.render(scene, integrator=integ, spp=SPP, seed=1), dtype=np.float64)
    np.testing.assert_allclose(in_ad, base, rtol=1e-3, atol=1e-5)  # the same material
    img = mi.render(scene, params, integrator=integ, spp=SPP, seed=7, seed_grad=1)
    dr.backward(dr.mean(img, axis=None))
    grad = np.array(dr.grad(params["mat.x"]), dtype=np.float64)
    h = 2e-3
    fd = np.array(
        [
            (plain(x0 + h * e, 1).mean() - plain(x0 - h * e, 1).mean()) / (2 * h)
            for e in np.eye(manifold.q)
        ]
    )
    assert np.abs(fd).max() > 0
    np.testing.assert_allclose(grad, fd, rtol=2e-2, atol=2e-3 * np.abs(fd).max())

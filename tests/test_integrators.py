"""Tests of the ``manifold_path`` integrator (L1- split), the example scenes and their assets.

Statistical comparisons render K independent images per integrator (different seeds),
estimate each pixel's Monte Carlo variance from them, and compare means over 8x8 pixel
blocks and over the whole image with a z-score whose variance pools all pixels of the
block (hundreds of degrees of freedom, so the z-scores are close to standard normal).
Seeds are fixed: the outcome is deterministic.

Materials are ``manifold_brdf`` instances on the small surrogate manifold of conftest.py,
loaded from the project's scenes (``scenes/*.xml``) or from dictionaries.
"""

import os
import shutil
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import mitsuba_manifold  # (selects a working libLLVM before drjit loads)
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from mitsuba_manifold import geometry, integrators  # noqa: E402
from mitsuba_manifold.manifold import Manifold  # noqa: E402
from helpers import chain  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = os.path.join(ROOT, "scenes")
VARIANT = "llvm_ad_rgb"
Z_MAX = 4.5  # |z| above this fails; P(|N(0,1)| > 4.5) ~ 7e-6 per statistic


@pytest.fixture(autouse=True)
def variant():
    mi.set_variant(VARIANT)
    mitsuba_manifold.register()
    yield VARIANT


def load(name, manifold, material=None, **params):
    """A scene of scenes/, its manifold material set to a training ``material``."""
    scene = mi.load_file(os.path.join(SCENES, f"{name}.xml"), manifold=manifold,
                         **{k: str(v) for k, v in params.items()})
    if material is not None:
        for bsdf in integrators.manifold_bsdfs(scene):
            bsdf.set_material(material)
    return scene


def integrator(**props):
    return mi.load_dict({"type": "manifold_path", **props})


def renders(scene, integ, spp, seeds):
    """Images (K, H, W, C) rendered with the given seeds."""
    return np.stack([np.array(mi.render(scene, integrator=integ, spp=spp, seed=s)) for s in seeds])


def mean_var(imgs, block=8):
    """Per-block means and the variance of those means, from K independent images.

    Returns arrays (blocks_y, blocks_x, C) and the whole-image mean/variance (C,).
    """
    k, h, w, c = imgs.shape
    m = imgs.mean(0)
    v = imgs.var(0, ddof=1) / k  # variance of each pixel's mean over the K images
    by, bx = h // block, w // block
    bm = m[:by * block, :bx * block].reshape(by, block, bx, block, c).mean((1, 3))
    bv = v[:by * block, :bx * block].reshape(by, block, bx, block, c).sum((1, 3)) / block ** 4
    return bm, bv, m.mean((0, 1)), v.sum((0, 1)) / (h * w) ** 2


def z_scores(a, b):
    """z-scores of (a - b) for (mean, var) pairs; 0 where both means are exactly equal."""
    (ma, va), (mb, vb) = a, b
    d = ma - mb
    s = np.sqrt(va + vb)
    return np.where(d == 0, 0.0, d / np.where(s > 0, s, 1e-30))


def assert_same_mean(imgs_a, imgs_b, what):
    ba, bva, ga, gva = mean_var(imgs_a)
    bb, bvb, gb, gvb = mean_var(imgs_b)
    zb = z_scores((ba, bva), (bb, bvb))
    zg = z_scores((ga, gva), (gb, gvb))
    assert np.max(np.abs(zb)) < Z_MAX, f"{what}: block z-scores up to {np.max(np.abs(zb)):.2f}"
    assert np.max(np.abs(zg)) < Z_MAX, f"{what}: image means {ga} vs {gb}, z = {zg}"
    return zb, zg


def midpoint(manifold_path, a, b):
    """Latent point halfway between training materials a and b, as the scenes' x string."""
    m = Manifold.load(manifold_path)
    x = 0.5 * (m.latent[m.names.index(a)] + m.latent[m.names.index(b)])
    return ", ".join(repr(float(v)) for v in x)


# ------------------------------------------------------------------ agreement with `path`

@pytest.mark.parametrize("material", ["gold-paint", "midpoint"])
def test_l1_equals_path_on_convex_scene(small_manifold, material):
    """A convex object alone never scatters light onto itself: L1- is the whole image."""
    if material == "midpoint":
        scene = load("sphere", small_manifold, res=32,
                     x=midpoint(small_manifold, "gold-paint", "blue-acrylic"))
    else:
        scene = load("sphere", small_manifold, material, res=32)
    seeds = range(16)
    ref = renders(scene, mi.load_dict({"type": "path", "max_depth": 8}), 16, seeds)
    l1 = renders(scene, integrator(max_depth=8, component="l1"), 16, [100 + s for s in seeds])
    assert l1.shape == ref.shape == (16, 32, 32, 3)
    assert l1.mean() > 0.05  # the comparison is not between two black images
    assert_same_mean(l1, ref, "L1- vs path on sphere.xml")


@pytest.mark.parametrize("max_depth,rr_depth,hide", [(2, 5, False), (3, 5, True), (-1, 2, False)])
def test_full_equals_path(small_manifold, max_depth, rr_depth, hide):
    """component=full is Mitsuba's path tracer: same max_depth, rr_depth (Russian roulette)
    and hide_emitters meaning."""
    scene = load("cbox", small_manifold, "steel", res=32)
    seeds = range(12)
    props = dict(max_depth=max_depth, rr_depth=rr_depth, hide_emitters=hide)
    ref = renders(scene, mi.load_dict({"type": "path", **props}), 16, seeds)
    full = renders(scene, integrator(component="full", **props), 16, [50 + s for s in seeds])
    assert_same_mean(full, ref, f"full vs path, {props}")


def test_hidden_emitters_are_seen_through_as_path_does():
    """hide_emitters: the camera sees what lies behind an area light (a red wall), not the
    light's own (green) surface, as with Mitsuba's path."""
    t = mi.ScalarTransform4f()
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": t.look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [1, 1, 1]}},
        "light": {"type": "rectangle", "to_world": t.scale(3),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5, 5, 5]}},
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0.9, 0]}}},
        "wall": {"type": "rectangle", "to_world": t.translate([0, 0, -1]).scale(3),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.9, 0, 0]}}}})
    seeds = range(8)
    ref = renders(scene, mi.load_dict({"type": "path", "hide_emitters": True, "max_depth": 4}), 16, seeds)
    full = renders(scene, integrator(component="full", hide_emitters=True, max_depth=4), 16,
                   [20 + s for s in seeds])
    assert full[..., 0].mean() > 0.05 and full[..., 1].max() == 0
    assert_same_mean(full, ref, "hide_emitters: full vs path")


# ------------------------------------------------------------------ the split

def test_base_plus_touch_equals_l1(small_manifold):
    scene = load("table", small_manifold, "gold-paint", res=32)
    seeds = range(12)
    base = renders(scene, integrator(component="base", max_depth=8), 16, seeds)
    touch = renders(scene, integrator(component="touch", max_depth=8), 16, [20 + s for s in seeds])
    l1 = renders(scene, integrator(component="l1", max_depth=8), 16, [40 + s for s in seeds])
    assert base.mean() > 0.02 and touch.mean() > 0.01
    # (base + touch) from independent renders: pixel variances add.
    bm, bv, gm, gv = mean_var(base)
    tm, tv, hm, hv = mean_var(touch)
    lm, lv, km, kv = mean_var(l1)
    zb = z_scores((bm + tm, bv + tv), (lm, lv))
    zg = z_scores((gm + hm, gv + hv), (km, kv))
    assert np.max(np.abs(zb)) < Z_MAX and np.max(np.abs(zg)) < Z_MAX, (zb, zg)


def test_split_aovs_partition_the_image(small_manifold):
    """split=true returns base/touch(/rest) from the same paths; they add up to the image."""
    scene = load("table", small_manifold, "white-diffuse-bball", res=24)
    integ = integrator(component="full", split=True, max_depth=8)
    img = np.array(mi.render(scene, integrator=integ, spp=8, seed=3))
    assert integ.aov_names() == [f"{c}.{ch}" for c in ("base", "touch", "rest") for ch in "RGB"]
    assert img.shape == (24, 24, 12)
    main, base, touch, rest = (img[..., 3 * k:3 * k + 3] for k in range(4))
    np.testing.assert_allclose(base + touch + rest, main, rtol=1e-5, atol=1e-6)
    assert np.all(base >= 0) and np.all(touch >= 0) and np.all(rest >= 0)
    assert touch.mean() > 0.01 and rest.max() > 0
    # The same seed with component=l1 gives exactly the base and touch parts of these paths.
    integ = integrator(component="l1", split=True, max_depth=8)
    l1 = np.array(mi.render(scene, integrator=integ, spp=8, seed=3))
    assert integ.aov_names() == [f"{c}.{ch}" for c in ("base", "touch") for ch in "RGB"]
    np.testing.assert_allclose(l1[..., :3], base + touch, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(l1[..., 3:6], base, rtol=1e-5, atol=1e-6)


def test_l1_misses_measurable_l2_plus_on_concave_scene(small_manifold):
    """In the bowl, light scatters off the material more than once: path > L1- clearly."""
    scene = load("table", small_manifold, "white-diffuse-bball", res=32)
    seeds = range(12)
    ref = renders(scene, mi.load_dict({"type": "path", "max_depth": 8}), 16, seeds)
    full = renders(scene, integrator(component="full", split=True, max_depth=8), 16,
                   [30 + s for s in seeds])
    l1 = renders(scene, integrator(component="l1", max_depth=8), 16, [60 + s for s in seeds])
    assert_same_mean(full[..., :3], ref, "full vs path on table.xml")
    # The paths left out of L1- (rest = L2+, from the same paths as the full image) carry a
    # clearly measurable share of the light ...
    rest = full[..., 9:12]
    _, _, g, gv = mean_var(rest)
    _, _, gf, _ = mean_var(full[..., :3])
    assert np.all(g / np.sqrt(gv) > 10) and np.all(g / gf > 0.005), (g, gv, gf)
    # ... and are exactly what L1- lacks: L1- + L2+ (independent renders) matches path.
    assert_same_mean(l1 + rest, ref, "L1- + L2+ vs path on table.xml")


def test_touch_is_linear_in_the_material(small_manifold):
    """Paper Eq. 13: the touch image of the material w1*rho1 + w2*rho2 is the same blend of
    the touch images of rho1 and rho2; the base image does not depend on the material;
    the L2+ image is not affine (it is quadratic and more in the material)."""
    a, b, wa = "white-diffuse-bball", "black-obsidian", 0.5
    scene = load("table", small_manifold, res=24)
    (bsdf,) = integrators.manifold_bsdfs(scene)
    seeds = range(16)
    split = integrator(component="full", split=True, max_depth=8)
    base = integrator(component="base", max_depth=8)
    out = {}
    for offset, weights in enumerate(({a: 1.0}, {b: 1.0}, {a: wa, b: 1 - wa})):
        bsdf.set_weights(weights)
        imgs = renders(scene, split, 32, [1000 * offset + s for s in seeds])
        out[len(out)] = (imgs[..., 6:9], imgs[..., 9:12],
                         np.array(mi.render(scene, integrator=base, spp=8, seed=7)))
    (t1, r1, b1), (t2, r2, b2), (t, r, b_) = out[0], out[1], out[2]
    # Base: the paths that never scatter off the material are the same for every material.
    assert b1.mean() > 0.05
    np.testing.assert_array_equal(b1, b2)
    np.testing.assert_array_equal(b1, b_)
    for direct, im1, im2, what in ((t, t1, t2, "touch"), (r, r1, r2, "rest")):
        m, v, g, gv = mean_var(direct)
        m1, v1, g1, gv1 = mean_var(im1)
        m2, v2, g2, gv2 = mean_var(im2)
        w1, w2 = wa, 1 - wa
        zb = z_scores((m, v), (w1 * m1 + w2 * m2, w1 ** 2 * v1 + w2 ** 2 * v2))
        zg = z_scores((g, gv), (w1 * g1 + w2 * g2, w1 ** 2 * gv1 + w2 ** 2 * gv2))
        if what == "touch":
            assert np.max(np.abs(zb)) < Z_MAX and np.max(np.abs(zg)) < Z_MAX, (what, zb, zg)
        else:  # about (w1 rho1)^2 < w1 rho1^2: the direct L2+ image is the darker one
            assert np.all(zg < -6), (what, zg)


# ------------------------------------------------------------------ several manifold materials

def two_spheres(manifold, a="white-diffuse-bball", b="gold-paint", interpolation="nearest", rfilter="box"):
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                             up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": rfilter}},
                   "sampler": {"type": "independent", "sample_count": 16}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
        "a": {"type": "manifold_brdf", "manifold": manifold, "material": a,
              "interpolation": interpolation},
        "b": {"type": "manifold_brdf", "manifold": manifold, "material": b,
              "interpolation": interpolation},
        "grey": {"type": "diffuse"},
        "sa": {"type": "sphere", "center": [-0.55, 0, 0], "radius": 0.5, "bsdf": {"type": "ref", "id": "a"}},
        "sb": {"type": "sphere", "center": [0.55, 0, 0], "radius": 0.5, "bsdf": {"type": "ref", "id": "b"}},
        "floor": {"type": "rectangle", "bsdf": {"type": "ref", "id": "grey"},
                  "to_world": mi.ScalarTransform4f().translate([0, -0.5, 0]).rotate([1, 0, 0], -90).scale(3)},
    })


def test_each_target_gets_its_own_class(small_manifold):
    scene = two_spheres(small_manifold)
    assert [b.id() for b in integrators.manifold_bsdfs(scene)] == ["a", "b"]
    seeds = range(12)
    each = integrator(target="each", component="l1", split=True, max_depth=6)
    every = integrator(target="all", component="l1", split=True, max_depth=6)
    e = renders(scene, each, 16, seeds)
    a = renders(scene, every, 16, [40 + s for s in seeds])
    assert each.aov_names() == [f"{c}.{ch}" for c in ("base", "touch_a", "touch_b", "touch_a+b")
                                for ch in "RGB"]
    assert every.aov_names() == [f"{c}.{ch}" for c in ("base", "touch") for ch in "RGB"]
    base_e, ta, tb, tab = (e[..., 3 + 3 * k:6 + 3 * k] for k in range(4))
    base_a, touch_a = a[..., 3:6], a[..., 6:9]
    # With both materials as one group, touching a then b is a second touch: the group's
    # single-touch image is the sum of the two single-material classes.
    assert_same_mean(touch_a, ta + tb, "touch(all) vs touch:a + touch:b")
    assert_same_mean(base_a, base_e, "base(all) vs base(each)")
    _, _, g, gv = mean_var(tab)
    assert np.all(g / np.sqrt(gv) > 8), "the spheres see each other: touch:a+b must be visible"
    # A named class as the component is that AOV.
    integ = integrator(target="a, b", component="touch:b+a", split=True, max_depth=6)
    img = np.array(mi.render(scene, integrator=integ, spp=8, seed=1))
    np.testing.assert_allclose(img[..., :3], img[..., 12:15], rtol=1e-5, atol=1e-7)


# ------------------------------------------------------------------ one-pass basis

@pytest.mark.parametrize("name", ["sphere", "table"])
def test_onepass_matches_per_material(small_manifold, name):
    """Issue 5: every material's image from the shared paths equals, within Monte Carlo
    noise, the touch image rendered with that material alone; base too."""
    scene = load(name, small_manifold, "gold-paint", res=24)
    (bsdf,) = integrators.manifold_bsdfs(scene)
    before = bsdf.weights
    seeds = range(10)
    integ = integrator(max_depth=8)
    # Several passes (4 spp each) and uneven material chunks (3, 3, 2).
    calls = []
    one = [integ.render_onepass(scene, spp=16, seed=s, chunk=3, spp_per_pass=4,
                                progress=lambda d, t: calls.append((d, t))) for s in seeds]
    assert calls[-1] == (12, 12)
    np.testing.assert_array_equal(bsdf.weights, before)  # the scene's material is untouched
    assert list(one[0][1]) == bsdf.names
    assert one[0][0].shape == (24, 24, 3)
    base = renders(scene, integrator(component="base", max_depth=8), 16, [100 + s for s in seeds])
    assert_same_mean(np.stack([o[0] for o in one]), base, "one-pass vs per-material base")
    touch = integrator(component="touch", max_depth=8)
    for k, material in enumerate(bsdf.names):
        bsdf.set_material(material)
        ref = renders(scene, touch, 16, [200 + 20 * k + s for s in seeds])
        img = np.stack([o[1][material] for o in one])
        assert img.mean() > 0
        assert_same_mean(img, ref, f"one-pass vs per-material {material} on {name}.xml")


@pytest.mark.parametrize("interpolation", ["nearest", "linear"])
def test_onepass_replays_the_per_material_render_exactly(small_manifold, interpolation):
    """With one material, the one-pass sampling density is that material's own: the same
    seed traces the same paths, and the replayed touch image equals the direct render."""
    scene = two_spheres(small_manifold, interpolation=interpolation)
    integ = integrator(target="a", max_depth=6)
    base, images = integ.render_onepass(scene, materials=["gold-paint"], spp=4, seed=5)
    (a,) = [b for b in integrators.manifold_bsdfs(scene) if b.id() == "a"]
    a.set_material("gold-paint")
    touch = np.array(mi.render(scene, integrator=integrator(target="a", component="touch",
                                                              max_depth=6), spp=4, seed=5))
    ref_base = np.array(mi.render(scene, integrator=integrator(target="a", component="base",
                                                                 max_depth=6), spp=4, seed=5))
    assert images["gold-paint"].mean() > 0.01
    np.testing.assert_allclose(images["gold-paint"], touch, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(base, ref_base, rtol=1e-5, atol=1e-7)


def test_onepass_with_a_wide_filter_replays_the_per_material_render(small_manifold):
    """Films whose filter spreads a sample over several pixels take the general path (each
    material's table looked up and splatted with the filter): still the direct render."""
    scene = two_spheres(small_manifold, rfilter="gaussian")
    integ = integrator(target="a", max_depth=6)
    base, _ = integ.render_onepass(scene, materials=["gold-paint", "chrome"], spp=4, seed=5)
    (a,) = [b for b in integrators.manifold_bsdfs(scene) if b.id() == "a"]
    ref_base = np.array(mi.render(scene, integrator=integrator(target="a", component="base",
                                                                 max_depth=6), spp=4, seed=5))
    np.testing.assert_allclose(base, ref_base, rtol=1e-5, atol=1e-7)
    # With two materials the paths differ from a direct render: compare one material alone.
    base, images = integ.render_onepass(scene, materials=["gold-paint"], spp=4, seed=5)
    a.set_material("gold-paint")
    touch = np.array(mi.render(scene, integrator=integrator(target="a", component="touch",
                                                              max_depth=6), spp=4, seed=5))
    assert images["gold-paint"].mean() > 0.01
    np.testing.assert_allclose(images["gold-paint"], touch, rtol=1e-4, atol=1e-6)


def test_onepass_table_product_is_the_same_in_tiles_and_chunks(small_manifold, monkeypatch):
    """The per-pixel sums of the table product do not depend on how they are split: the
    whole image at once, or tiles of 100 pixels (the memory bound) with materials in
    chunks of 3 that straddle the 16-material packets of the interleaved tables."""
    scene = load("table", small_manifold, res=24)
    integ = integrator(max_depth=8)
    base, whole = integ.render_onepass(scene, spp=8, seed=2)
    monkeypatch.setattr(integrators, "_SUM_BYTES", 100 * 12 * 16 * max(1, dr.thread_count()))
    calls = []
    base2, tiled = integ.render_onepass(scene, spp=8, seed=2, chunk=3,
                                        progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 3), (2, 3), (3, 3)]
    np.testing.assert_array_equal(base, base2)
    assert list(tiled) == list(whole)
    for name in whole:
        assert whole[name].shape == (24, 24, 3)
        np.testing.assert_allclose(tiled[name], whole[name], rtol=1e-5, atol=1e-7)
    assert max(img.mean() for img in whole.values()) > 0.01


def test_material_rows_interleave_the_tables_and_are_cached(small_db, tmp_path):
    """Database.material_rows (read by the table product): rows[bin, channel, material],
    zero padding to 16 materials, one cache file per material list, the newest kept."""
    from mitsuba_manifold.database import Database
    folder = tmp_path / "db"
    shutil.copytree(small_db, folder, ignore=shutil.ignore_patterns(".manifold-cache"))
    db = Database(folder)
    names = ["chrome", "gold-paint", "white-diffuse-bball"]
    rows = db.material_rows(names)
    bins = int(np.prod(db.dims))
    assert rows.shape == (bins, 3, 16) and rows.dtype == np.float32
    for k, name in enumerate(names):
        np.testing.assert_array_equal(rows[:, :, k], np.asarray(db.reflectance(name)).reshape(3, bins).T)
    assert not np.any(rows[:, :, len(names):])
    assert os.path.samefile(db.material_rows(names).filename, rows.filename)
    cached = lambda: sorted(f for f in os.listdir(db.cache_dir) if ".rows-" in f)  # noqa: E731
    assert len(cached()) == 1
    db.material_rows(names[::-1])
    db.material_rows(names[:2])
    assert len(cached()) == 2  # the two most recent
    assert os.path.basename(rows.filename) not in cached()


def test_mixture_from_given_table_is_the_combined_material(small_manifold, small_db):
    """set_weights(w, table=...) (how one-pass rendering builds its sampling mixture from the
    interleaved tables) gives the material that combining the tables gives."""
    from mitsuba_manifold.database import Database
    names = ["chrome", "gold-paint", "blue-acrylic"]
    w = [0.2, 0.5, 0.3]
    spec = {"type": "manifold_brdf", "manifold": small_manifold, "prune": 0.0}
    combined = mi.load_dict({**spec, "weights": ", ".join(f"{n}:{v}" for n, v in zip(names, w))})
    rows = Database(small_db).material_rows(names)
    pad = np.zeros(rows.shape[2], dtype=np.float32)
    pad[:3] = w
    dims = Database(small_db).dims
    table = (np.asarray(rows).reshape(-1, rows.shape[2]) @ pad).reshape(-1, 3).T.reshape((3,) + tuple(dims))
    given = mi.load_dict({**spec, "material": names[0]})
    given.set_weights(dict(zip(names, w)), table=table)
    assert given.used_names == combined.used_names
    rng = np.random.default_rng(3)
    si = dr.zeros(mi.SurfaceInteraction3f, 4096)
    si.wi = mi.warp.square_to_cosine_hemisphere(mi.Point2f(*rng.random((2, 4096))))
    s1, s2 = mi.Float(rng.random(4096)), mi.Point2f(*rng.random((2, 4096)))
    ctx = mi.BSDFContext()
    for bsdf in (combined, given):
        bs, value = bsdf.sample(ctx, si, s1, s2)
        wo = mi.warp.square_to_uniform_hemisphere(mi.Point2f(*rng.random((2, 4096))))
        bsdf.result = [np.array(v) for v in (bs.wo, bs.pdf, value, bsdf.eval(ctx, si, bs.wo),
                                              bsdf.pdf(ctx, si, bs.wo))]
    assert np.array(combined.result[1]).max() > 0
    for a, b in zip(combined.result, given.result):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_onepass_refuses_what_it_cannot_do(small_manifold):
    scene = two_spheres(small_manifold)
    with pytest.raises(ValueError, match="one-pass rendering handles one target group"):
        integrator(target="each").render_onepass(scene, spp=1)
    with pytest.raises(ValueError, match="unknown: \\['nope'\\]"):
        integrator(target="a").render_onepass(scene, materials=["chrome", "nope"], spp=1)
    with pytest.raises(ValueError, match="no manifold material"):
        integrator().render_onepass(mi.load_dict(mi.cornell_box()), spp=1)
    with pytest.raises(ValueError, match="spp_per_pass must be >= 1"):
        integrator(target="a").render_onepass(scene, spp=4, spp_per_pass=0)
    with pytest.raises(ValueError, match="chunk must be >= 1"):
        integrator(target="a").render_onepass(scene, spp=4, chunk=0)


# ------------------------------------------------------------------ errors

def test_scene_without_manifold_material_is_refused():
    scene = mi.load_dict(mi.cornell_box())
    integ = integrator(component="touch")
    with pytest.raises(ValueError, match="no manifold material"):
        integ.render(scene, spp=1)
    with pytest.raises(Exception) as info:
        mi.render(scene, integrator=integ, spp=1)
    assert "the scene has no manifold material" in chain(info.value)
    with pytest.raises(ValueError, match="no manifold material"):
        integrators.target_groups(scene)
    # A plain full render needs no target.
    img = mi.render(scene, integrator=integrator(component="full", max_depth=2), spp=1)
    assert np.array(img).shape[2] == 3


@pytest.mark.parametrize("props,message", [
    ({"component": "l2"}, "unknown component 'l2'"),
    ({"max_depth": -2}, "max_depth must be -1"),
    ({"rr_depth": 0}, "rr_depth must be > 0"),
])
def test_bad_parameters(props, message):
    with pytest.raises(Exception) as info:
        integrator(**props)
    assert message in chain(info.value)


@pytest.mark.parametrize("props,message", [
    ({"target": "grey"}, "'grey' is not a manifold_brdf"),
    ({"target": "nope"}, "'nope' is not in the scene"),
    ({"target": "a, a"}, "names a BSDF twice"),
    ({"target": "a", "component": "touch:a"}, "makes one group"),
    ({"target": "each", "component": "touch:a+c"}, "must name distinct target groups"),
])
def test_bad_targets(small_manifold, props, message):
    scene = two_spheres(small_manifold)
    with pytest.raises(ValueError, match=message):
        integrator(**props).render(scene, spp=1)


def test_scalar_variant_is_refused_clearly():
    mi.set_variant("scalar_rgb")
    integrators.register()
    with pytest.raises(Exception) as info:
        mi.load_dict({"type": "manifold_path"})
    assert "needs an RGB JIT variant" in chain(info.value)


# ------------------------------------------------------------------ scenes and assets

@pytest.mark.parametrize("name", ["sphere", "table", "cbox"])
def test_scene_parameters(small_manifold, tmp_path, name):
    root = ET.parse(os.path.join(SCENES, f"{name}.xml")).getroot()
    defaults = {el.get("name"): el.get("value") for el in root.iter("default")}
    assert defaults == {"manifold": "../out/manifold.npz", "x": "0, 0", "spp": "64", "res": "256",
                        "integrator": "path", "max_depth": "8"}
    # The default manifold is found relative to the scene's folder (../out/manifold.npz).
    shutil.copytree(SCENES, tmp_path / "scenes")
    (tmp_path / "out").mkdir()
    shutil.copy(small_manifold, tmp_path / "out" / "manifold.npz")
    scene = mi.load_file(str(tmp_path / "scenes" / f"{name}.xml"))
    (bsdf,) = integrators.manifold_bsdfs(scene)
    assert bsdf.id() == "material"
    assert os.path.samefile(bsdf.manifold_path, tmp_path / "out" / "manifold.npz")
    np.testing.assert_array_equal(bsdf.latent, [0.0, 0.0])
    sensor = scene.sensors()[0]
    assert list(sensor.film().size()) == [256, 256] and sensor.sampler().sample_count() == 64
    assert "PathIntegrator" in str(scene.integrator()) and "max_depth = 8" in str(scene.integrator())
    # Every parameter can be overridden.
    scene = load(name, small_manifold, x="0.3, -1.2", res=16, spp=4, integrator="manifold_path",
                 max_depth=5)
    (bsdf,) = integrators.manifold_bsdfs(scene)
    assert os.path.samefile(bsdf.manifold_path, small_manifold)
    np.testing.assert_allclose(bsdf.latent, [0.3, -1.2])
    sensor = scene.sensors()[0]
    assert list(sensor.film().size()) == [16, 16] and sensor.sampler().sample_count() == 4
    assert scene.integrator().max_depth == 5 and scene.integrator().component == "l1"
    # A latent point of the wrong dimension is refused by the material, naming x.
    with pytest.raises(Exception) as info:
        load(name, small_manifold, x="0.3, -1.2, 4")
    assert "x must be 2 finite numbers" in chain(info.value)


def test_bowl_mesh_is_closed_and_outward():
    v, f = geometry.bowl()
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    directed = set(map(tuple, edges))
    assert len(directed) == len(edges)  # no edge used twice in one direction
    assert all((b, a) in directed for a, b in directed)  # every edge has its twin: closed
    assert geometry.signed_volume(v, f) > 0.1  # normals point out of the solid
    assert v[:, 1].min() == pytest.approx(0.0, abs=1e-6)  # stands on y = 0
    r, y = geometry.bowl_profile()
    assert r[0] == 0 and r[-1] == 0 and y[-1] == pytest.approx(0.06)
    with pytest.raises(ValueError, match="thickness"):
        geometry.bowl_profile(thickness=2.0)


def test_committed_assets_match_the_generator(tmp_path):
    mesh = mi.load_dict({"type": "ply", "filename": os.path.join(SCENES, "bowl.ply")})
    v, f = geometry.bowl()
    params = mi.traverse(mesh)
    np.testing.assert_allclose(np.array(params["vertex_positions"]).reshape(-1, 3), v, atol=1e-6)
    np.testing.assert_array_equal(np.array(params["faces"]).reshape(-1, 3), f)
    sky = np.array(mi.Bitmap(os.path.join(SCENES, "sky.exr")))
    np.testing.assert_allclose(sky, geometry.sky_envmap(), rtol=1e-6)
    # Atomic writer: a rewrite leaves a complete file and no temporary beside it.
    out = tmp_path / "bowl.ply"
    geometry.write_ply(out, v, f)
    geometry.write_ply(out, v, f)
    assert os.listdir(tmp_path) == ["bowl.ply"]
    with pytest.raises(ValueError, match="out of range"):
        geometry.write_ply(tmp_path / "bad.ply", v, f + len(v))
    assert sorted(os.listdir(tmp_path)) == ["bowl.ply"]


def test_sky_map_convention_puts_the_sun_where_asked():
    sun = np.array([0.45, 0.62, 0.64])
    sun /= np.linalg.norm(sun)
    env = mi.load_dict({"type": "envmap", "filename": os.path.join(SCENES, "sky.exr")})
    si = dr.zeros(mi.SurfaceInteraction3f, 4)
    dirs = np.array([sun, [0, 1, 0], [0, -1, 0], -sun])
    si.wi = -mi.Vector3f(dirs.T)  # eval looks along -wi
    value = np.array(env.eval(si)).T  # (lanes, RGB)
    assert value[0, 0] > 100  # the sun
    assert value[1, 2] > value[1, 0]  # blue zenith
    np.testing.assert_allclose(value[2], [0.25, 0.2, 0.15], rtol=0.05)  # ground
    assert value[3].max() < 2

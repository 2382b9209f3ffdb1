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

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np
import pytest
from helpers import chain  # noqa: E402

import mitsuba_manifold.render  # noqa: F401  (selects a working libLLVM before drjit loads; the plugins)
from mitsuba_manifold.manifold.file.shipped import shipped_path  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.render import integrators  # noqa: E402
from mitsuba_manifold.render.scene import geometry
from mitsuba_manifold.render.scene.scenes import SCENES_DIR  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENES = SCENES_DIR

from helpers import (
    Z_MAX,
    assert_same_mean,
    integrator,
    load,
    mean_var,
    midpoint,
    renders,  # noqa: E402,F401
    two_spheres,
    z_scores,
)

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]

# ------------------------------------------------------------------ agreement with `path`


@pytest.mark.parametrize("material", ["gold-paint", "midpoint"])
def test_l1_equals_path_on_convex_scene(small_manifold, material):
    """A convex object alone never scatters light onto itself: L1- is the whole image."""
    if material == "midpoint":
        scene = load(
            "sphere",
            small_manifold,
            res=32,
            x=midpoint(small_manifold, "gold-paint", "blue-acrylic"),
        )
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
    scene = mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "perspective",
                "fov": 30,
                "to_world": t.look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}},
            },
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": [1, 1, 1]}},
            "light": {
                "type": "rectangle",
                "to_world": t.scale(3),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5, 5, 5]}},
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0.9, 0]}},
            },
            "wall": {
                "type": "rectangle",
                "to_world": t.translate([0, 0, -1]).scale(3),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.9, 0, 0]}},
            },
        }
    )
    seeds = range(8)
    ref = renders(
        scene, mi.load_dict({"type": "path", "hide_emitters": True, "max_depth": 4}), 16, seeds
    )
    full = renders(
        scene,
        integrator(component="full", hide_emitters=True, max_depth=4),
        16,
        [20 + s for s in seeds],
    )
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
    main, base, touch, rest = (img[..., 3 * k : 3 * k + 3] for k in range(4))
    np.testing.assert_allclose(base + touch + rest, main, rtol=1e-5, atol=1e-6)
    assert np.all(base >= 0) and np.all(touch >= 0) and np.all(rest >= 0)
    assert touch.mean() > 0.01 and rest.max() > 0
    # The same seed with component=l1 gives exactly the base and touch parts of these paths.
    integ = integrator(component="l1", split=True, max_depth=8)
    l1 = np.array(mi.render(scene, integrator=integ, spp=8, seed=3))
    assert integ.aov_names() == [f"{c}.{ch}" for c in ("base", "touch") for ch in "RGB"]
    np.testing.assert_allclose(l1[..., :3], base + touch, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(l1[..., 3:6], base, rtol=1e-5, atol=1e-6)


def test_component_l2_plus_is_the_rest_aov_and_rest_its_former_spelling(small_manifold):
    """component="l2+" renders what split=true's ``rest`` AOV holds (same paths, same seed);
    "rest", its former spelling, is the same image with a DeprecationWarning."""
    scene = load("table", small_manifold, "white-diffuse-bball", res=16)
    split = np.array(
        mi.render(
            scene, integrator=integrator(component="full", split=True, max_depth=6), spp=4, seed=5
        )
    )
    l2 = np.array(
        mi.render(scene, integrator=integrator(component="l2+", max_depth=6), spp=4, seed=5)
    )
    assert l2.max() > 0
    np.testing.assert_allclose(l2, split[..., 9:12], rtol=1e-5, atol=1e-6)
    with pytest.warns(DeprecationWarning, match="now spelled 'l2\\+'"):
        old = integrator(component="rest", max_depth=6)
    assert old.component == "l2+"
    np.testing.assert_array_equal(np.array(mi.render(scene, integrator=old, spp=4, seed=5)), l2)


def test_l1_misses_measurable_l2_plus_on_concave_scene(small_manifold):
    """In the bowl, light scatters off the material more than once: path > L1- clearly."""
    scene = load("table", small_manifold, "white-diffuse-bball", res=32)
    seeds = range(12)
    ref = renders(scene, mi.load_dict({"type": "path", "max_depth": 8}), 16, seeds)
    full = renders(
        scene, integrator(component="full", split=True, max_depth=8), 16, [30 + s for s in seeds]
    )
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
        out[len(out)] = (
            imgs[..., 6:9],
            imgs[..., 9:12],
            np.array(mi.render(scene, integrator=base, spp=8, seed=7)),
        )
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
        zb = z_scores((m, v), (w1 * m1 + w2 * m2, w1**2 * v1 + w2**2 * v2))
        zg = z_scores((g, gv), (w1 * g1 + w2 * g2, w1**2 * gv1 + w2**2 * gv2))
        if what == "touch":
            assert np.max(np.abs(zb)) < Z_MAX and np.max(np.abs(zg)) < Z_MAX, (what, zb, zg)
        else:  # about (w1 rho1)^2 < w1 rho1^2: the direct L2+ image is the darker one
            assert np.all(zg < -6), (what, zg)


# ------------------------------------------------------------------ several manifold materials


def test_each_target_gets_its_own_class(small_manifold):
    scene = two_spheres(small_manifold)
    assert [b.id() for b in integrators.manifold_bsdfs(scene)] == ["a", "b"]
    seeds = range(12)
    each = integrator(target="each", component="l1", split=True, max_depth=6)
    every = integrator(target="all", component="l1", split=True, max_depth=6)
    e = renders(scene, each, 16, seeds)
    a = renders(scene, every, 16, [40 + s for s in seeds])
    assert each.aov_names() == [
        f"{c}.{ch}" for c in ("base", "touch_a", "touch_b", "touch_a+b") for ch in "RGB"
    ]
    assert every.aov_names() == [f"{c}.{ch}" for c in ("base", "touch") for ch in "RGB"]
    base_e, ta, tb, tab = (e[..., 3 + 3 * k : 6 + 3 * k] for k in range(4))
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


def test_a_manifold_material_inside_twosided_is_the_target(small_manifold):
    """manifold_brdf inside twosided: found, and a
    hit on the wrapper is a vertex on the material."""
    scene = mi.load_dict(
        {
            "type": "scene",
            "s": {
                "type": "sphere",
                "bsdf": {
                    "type": "twosided",
                    "id": "ts",
                    "b": {"type": "manifold_brdf", "manifold": small_manifold, "material": "steel"},
                },
            },
            "e": {"type": "constant"},
            "c": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4}},
        }
    )
    ((name, (bsdf,)),) = integrators.target_groups(scene, "each")
    assert name == "b" and integrators.is_manifold_bsdf(bsdf)
    plan = integrator(component="touch").plan(scene)
    assert [type(c).__name__ for c in plan.hits[0]] == ["BSDF"] and len(plan.mirror) == 1


@pytest.mark.parametrize(
    "props,message",
    [
        ({"component": "l2"}, "unknown component 'l2'"),
        ({"max_depth": -2}, "max_depth must be -1"),
        ({"rr_depth": 0}, "rr_depth must be > 0"),
    ],
)
def test_bad_parameters(props, message):
    with pytest.raises(Exception) as info:
        integrator(**props)
    assert message in chain(info.value)


@pytest.mark.parametrize(
    "props,message",
    [
        ({"target": "grey"}, "'grey' is not a manifold_brdf"),
        ({"target": "nope"}, "'nope' is not in the scene"),
        ({"target": "a, a"}, "names a BSDF twice"),
        ({"target": "a", "component": "touch:a"}, "makes one group"),
        ({"target": "each", "component": "touch:a+c"}, "must name distinct target groups"),
    ],
)
def test_bad_targets(small_manifold, props, message):
    scene = two_spheres(small_manifold)
    with pytest.raises(ValueError, match=message):
        integrator(**props).render(scene, spp=1)


def test_scalar_variant_is_refused_clearly():
    mi.set_variant("scalar_rgb")
    with pytest.raises(Exception) as info:
        mi.load_dict({"type": "manifold_path"})
    assert "needs an RGB JIT variant" in chain(info.value)


# ------------------------------------------------------------------ scenes and assets


@pytest.mark.parametrize("name", ["sphere", "table", "cbox"])
def test_scene_parameters(small_manifold, tmp_path, name):
    root = ET.parse(os.path.join(SCENES, f"{name}.xml")).getroot()
    defaults = {el.get("name"): el.get("value") for el in root.iter("default")}
    assert defaults == {
        "manifold": "merl",
        "x": "",
        "spp": "64",
        "res": "256",
        "integrator": "path",
        "max_depth": "8",
    }
    # The default is the shipped manifold "merl"; a file of that name beside the scene makes
    # the name ambiguous (refused naming both); "./merl" is the file.
    scene = mi.load_file(os.path.join(SCENES, f"{name}.xml"), res="8", spp="1")
    (bsdf,) = integrators.manifold_bsdfs(scene)
    assert os.path.samefile(bsdf.manifold_path, shipped_path("merl"))
    shutil.copytree(SCENES, tmp_path / "scenes")
    shutil.copy(small_manifold, tmp_path / "scenes" / "merl")
    with pytest.raises(Exception, match=r"'merl' is ambiguous.*builtin:merl"):
        mi.load_file(str(tmp_path / "scenes" / f"{name}.xml"))
    scene = mi.load_file(str(tmp_path / "scenes" / f"{name}.xml"), manifold="./merl")
    (bsdf,) = integrators.manifold_bsdfs(scene)
    assert bsdf.id() == "material"
    assert os.path.samefile(bsdf.manifold_path, tmp_path / "scenes" / "merl")
    np.testing.assert_array_equal(
        bsdf.latent, Manifold.load(small_manifold).latent[0]
    )  # fits any q
    sensor = scene.sensors()[0]
    assert list(sensor.film().size()) == [256, 256] and sensor.sampler().sample_count() == 64
    assert "PathIntegrator" in str(scene.integrator()) and "max_depth = 8" in str(
        scene.integrator()
    )
    # Every parameter can be overridden.
    scene = load(
        name, small_manifold, x="0.3, -1.2", res=16, spp=4, integrator="manifold_path", max_depth=5
    )
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

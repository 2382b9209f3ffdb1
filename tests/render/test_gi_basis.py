"""Full-GI bases (issue 21): the L2+ images and cross terms of the one pass, what a basis
leaves out, and the blends that use them."""

import json
import os

import mitsuba as mi  # noqa: E402
import numpy as np
import pytest
from helpers import assert_same_mean, integrator, load, renders  # noqa: E402

import mitsuba_manifold.render  # noqa: F401  (selects a working libLLVM before drjit loads; the plugins)
from mitsuba_manifold.basis import folder as bf  # noqa: E402
from mitsuba_manifold.basis.blend import BlendSettings, blend, blend_path  # noqa: E402
from mitsuba_manifold.errors import InputError, MismatchError  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.render import integrators
from mitsuba_manifold.render.jobs import render_basis  # noqa: E402

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]

SEEDS = range(8)


def _gi(scene, **kw):
    integ = integrator(max_depth=8)
    return [integ.render_onepass_gi(scene, spp=16, seed=s, **kw) for s in SEEDS]


def test_full_gi_image_of_a_training_material_equals_mitsubas_path(small_manifold):
    """base + touch + L2+ of a material, from the shared paths (every vertex on the material
    recorded: ``levels`` = ``max_depth``, nothing cut), equals Mitsuba's ``path`` rendering
    the scene with that material, within Monte Carlo noise (block and image z-tests); the
    touch images are those of render_onepass, exactly."""
    scene = load("table", small_manifold, "gold-paint", res=24)
    (bsdf,) = integrators.manifold_bsdfs(scene)
    out = _gi(scene, levels=8)
    assert out[0].paths[2:].sum() > 0  # the bowl sees itself
    base, touch = integrator(max_depth=8).render_onepass(scene, spp=16, seed=0)
    np.testing.assert_array_equal(out[0].base, base)
    for name in ("gold-paint", "white-diffuse-bball"):
        np.testing.assert_allclose(out[0].touch[name], touch[name], rtol=1e-5, atol=1e-7)
        bsdf.set_material(name)
        ref = renders(
            scene, mi.load_dict({"type": "path", "max_depth": 8}), 16, [300 + s for s in SEEDS]
        )
        img = np.stack([o.base + o.touch[name] + o.rest[name] for o in out])
        assert np.stack([o.rest[name] for o in out]).mean() > 1e-3 * img.mean()
        assert_same_mean(img, ref, f"full-GI one pass vs path, {name}")
        l1 = np.stack([o.base + o.touch[name] for o in out])
        assert (ref.mean() - l1.mean()) > 0  # what the L1- image left out


def test_cross_terms_make_a_pairs_midpoint_exact_for_every_number_of_touches(small_manifold):
    """``base + (F_a + F_b) / 2 + C_ab / 4`` from the shared paths (the blend at the pair's
    midpoint) equals Mitsuba's ``path`` rendering the midpoint material ``(f_a + f_b) / 2``
    within noise, with paths touching the bowl three and more times; the cross term is
    significantly negative (the midpoint's interreflection is below the mean of its ends')."""
    scene = load("table", small_manifold, "gold-paint", res=24)
    (bsdf,) = integrators.manifold_bsdfs(scene)
    a, b = "gold-paint", "white-diffuse-bball"
    out = _gi(scene, levels=8, pairs=[(a, b)])
    assert out[0].paths[3:].sum() > 0
    img = np.stack(
        [
            o.base
            + 0.5 * (o.touch[a] + o.rest[a] + o.touch[b] + o.rest[b])
            + 0.25 * o.cross[(a, b)]
            for o in out
        ]
    )
    bsdf.set_weights({a: 0.5, b: 0.5})
    ref = renders(
        scene, mi.load_dict({"type": "path", "max_depth": 8}), 16, [500 + s for s in SEEDS]
    )
    assert_same_mean(img, ref, "midpoint blend with cross terms vs path")
    cross = np.stack([o.cross[(a, b)] for o in out]).sum(axis=(1, 2, 3))  # per seed
    assert cross.mean() < -3 * cross.std(ddof=1) / np.sqrt(len(cross))  # f_a, f_b differ: C_ab < 0


def test_cross_term_of_two_identical_materials_vanishes(small_manifold):
    """C_aa = 2 L2_aa - L2_aa - L2_aa = 0 exactly (the kernel sums -a d(b1) d(b2) with
    d = f_a - f_a = 0); C_ab of two different materials is not 0 where the bowl sees itself."""
    scene = load("table", small_manifold, "gold-paint", res=16)
    (r,) = _gi(
        scene, levels=2, pairs=[("gold-paint", "gold-paint"), ("gold-paint", "pink-fabric")]
    )[:1]
    assert not np.any(r.cross[("gold-paint", "gold-paint")])
    c = r.cross[("gold-paint", "pink-fabric")]
    assert np.abs(c).max() > 0
    assert np.isfinite(c).all() and np.all(r.rest["gold-paint"] >= 0)


def test_pair_selection_keeps_cross_terms_that_matter_and_drops_null_ones(small_manifold):
    """Measured on the first pass: a pair of two identical materials (cross term exactly 0) is
    dropped, a pair of different ones kept; the kept pair's term is the one computed without
    selection on the same paths; the selection says what it measured."""
    from mitsuba_manifold.render.integrators.multisplats import PairSelection

    scene = load("table", small_manifold, "gold-paint", res=16)
    pairs = [("gold-paint", "gold-paint"), ("gold-paint", "pink-fabric")]
    sel = PairSelection(products=(0.25, 0.25), tol=1e-4, pilot=0.5)
    integ = integrator(max_depth=8)
    r = integ.render_onepass_gi(scene, spp=16, seed=3, levels=5, pairs=pairs, pair_selection=sel)
    assert list(r.cross) == [("gold-paint", "pink-fabric")]
    assert (
        r.selection["candidates"] == 2
        and r.selection["kept"] == 1
        and r.selection["largest_left_out"] == 0
    )
    full = integ.render_onepass_gi(scene, spp=16, seed=3, levels=5, pairs=pairs)
    np.testing.assert_allclose(r.cross[pairs[1]], full.cross[pairs[1]], rtol=1e-5, atol=1e-7)
    none = integ.render_onepass_gi(
        scene,
        spp=16,
        seed=3,
        levels=5,
        pairs=pairs,
        pair_selection=PairSelection(products=(0.25, 0.25), tol=1e9),
    )
    assert none.cross == {} and none.selection["kept"] == 0


def test_pairs_of_small_weight_use_a_share_of_the_splats_unbiased(small_manifold):
    """A pair whose weight product is at most p uses the power of two >= 4p of the splats (1 at
    the midpoint's 1/4); its cross term, over independent seeds, has the mean of the one from
    every splat (z-tests)."""
    from mitsuba_manifold.render.integrators.multisplats import PairSelection

    sel = PairSelection(products=(0.05,), tol=0.0)
    assert [sel.share(p) for p in (0.25, 0.2, 0.05, 0.01, 1e-4)] == [1.0, 1.0, 0.25, 0.0625, 0.0625]
    scene = load("table", small_manifold, "gold-paint", res=16)
    pair = ("gold-paint", "pink-fabric")
    integ = integrator(max_depth=8)
    part = [
        integ.render_onepass_gi(scene, spp=16, seed=s, levels=5, pairs=[pair], pair_selection=sel)
        for s in SEEDS
    ]
    assert part[0].selection["splat_share"] == 0.25
    whole = [
        integ.render_onepass_gi(scene, spp=16, seed=100 + s, levels=5, pairs=[pair]) for s in SEEDS
    ]
    assert_same_mean(
        np.stack([r.cross[pair] for r in part]),
        np.stack([r.cross[pair] for r in whole]),
        "cross term from a quarter of the splats vs all",
    )


def test_blend_at_a_training_material_is_its_full_gi_image(tmp_path, small_manifold):
    """A full-GI basis of the table: the manifest says what it holds; the default blend at a
    training point is ``base + F_i`` exactly, ``component="l1"`` is Eq. 13's ``base + I_i``;
    the blend along a path uses the cross terms as the point blend does."""
    pytest.importorskip("pyoidn")  # the default blend denoises (a GPU machine may lack OIDN)
    out = tmp_path / "basis"
    manifest = render_basis.render_basis(
        "table",
        small_manifold,
        out,
        spp=8,
        mode="onepass",
        components="full",
        resolution=16,
        max_depth=8,
    )
    # by default every vertex the path depth allows is recorded: no path is cut
    assert manifest.components[:2] == ["l1", "l2+"] and manifest.levels == 8
    assert manifest.gi_stats["paths_by_touches"][-1] == 0
    assert manifest.gi_stats["rest_fraction"] > 0 and not (manifest.left_out or {}).get("l2+")
    m = Manifold.load(small_manifold)
    b = bf.Basis.load(out, manifold=m)
    k = m.names.index("gold-paint")
    img, info = blend(b, m, x=m.latent[k], component="full", l2="raw")
    assert info.component == "full" and info.component_note == ""
    np.testing.assert_allclose(
        img, b.image("base") + b.image("gi:gold-paint"), rtol=1e-6, atol=1e-7
    )
    den, dinfo = blend(b, m, x=m.latent[k])  # the default: its part beyond L1- denoised
    l1_img = b.image("base") + b.image("gold-paint")
    assert dinfo.l2 == "denoised" and np.isfinite(den).all()
    # the denoiser's smoothing keeps each channel's light beyond L1- (what it took is put back)
    np.testing.assert_allclose(
        (den - l1_img).sum(axis=(0, 1)),
        (img - l1_img).sum(axis=(0, 1)),
        rtol=1e-3,
        atol=1e-4 * float(np.abs(img - l1_img).sum()),
    )
    img1, info1 = blend(b, m, x=m.latent[k], component="l1")
    np.testing.assert_allclose(img1, b.image("base") + b.image("gold-paint"), rtol=1e-6, atol=1e-7)
    assert img.mean() > img1.mean()
    pairs = b.cross_terms()[0]
    if pairs:
        a, c = next(iter(pairs))
        images, _, pinfo = blend_path(
            b, m, a, c, steps=3, kind="straight", settings=BlendSettings(component="full", l2="raw")
        )
        mid, minfo = blend(
            b,
            m,
            x=0.5 * (m.latent[m.names.index(a)] + m.latent[m.names.index(c)]),
            component="full",
            l2="raw",
        )
        np.testing.assert_allclose(images[1], mid, rtol=1e-4, atol=1e-6)
        assert pinfo.component == "full"


@pytest.mark.parametrize("levels", [1, 2.5, "5"])
def test_bad_levels_are_refused_before_anything_is_made(tmp_path, small_manifold, levels):
    out = tmp_path / "basis"
    with pytest.raises(InputError, match="`levels` must be an integer >= 2"):
        render_basis.render_basis(
            "table",
            small_manifold,
            out,
            spp=2,
            mode="onepass",
            components="full",
            resolution=8,
            levels=levels,
        )
    assert not out.exists()


def test_an_old_l1_basis_still_blends_and_says_so(tmp_path, small_manifold):
    """A basis whose manifest predates full GI (no ``components``) blends L1- and warns once."""
    out = tmp_path / "old"
    render_basis.render_basis(
        "sphere", small_manifold, out, spp=2, mode="onepass", resolution=8, components="l1"
    )
    path = os.path.join(out, bf.MANIFEST)
    with open(path) as f:
        manifest = json.load(f)
    for key in ("components", "left_out", "levels", "gi_stats"):
        manifest.pop(key, None)
    with open(path, "w") as f:
        json.dump(manifest, f)
    m = Manifold.load(small_manifold)
    b = bf.Basis.load(out, manifold=m)
    with pytest.warns(UserWarning, match="L1- only") as caught:
        img, info = blend(b, m, x=m.latent[0], component="full")
    assert len(caught) == 1 and "\n" not in str(caught[0].message)
    assert info.component == "l1"
    np.testing.assert_allclose(img, blend(b, m, x=m.latent[0], component="l1")[0])


def test_a_convex_object_alone_holds_no_l2(tmp_path, small_manifold):
    """The sphere cannot see itself: no path touches it twice, so the basis holds no L2+ or
    cross-term images, and the manifest (and the blend's note) say why."""
    out = tmp_path / "sphere"
    manifest = render_basis.render_basis(
        "sphere", small_manifold, out, spp=4, mode="onepass", components="full", resolution=12
    )
    assert manifest.components == ["l1"]
    assert "cannot see itself" in manifest.left_out["l2+"]
    assert manifest.gi_stats["paths_by_touches"][2:] == [0] * (
        len(manifest.gi_stats["paths_by_touches"]) - 2
    )
    assert not any(f.endswith(".gi.exr") or f == "cross.npz" for f in os.listdir(out))
    assert "cannot see itself" in render_basis.describe_components(manifest)
    m = Manifold.load(small_manifold)
    img, info = blend(out, m, x=m.latent[0], component="full")
    assert info.component == "l1" and "cannot see itself" in info.component_note


def test_changed_or_truncated_cross_terms_and_aovs_are_refused_naming_the_file(
    tmp_path, small_manifold
):
    """A ``cross.npz`` edited after render_basis wrote it (same shapes, other values) would blend
    silently wrong: its SHA-256 is in the manifest and a changed file is refused; a truncated
    one (or a truncated ``aovs.npz``) is a one-line error, not a zipfile traceback."""
    import shutil

    out = tmp_path / "basis"
    manifest = render_basis.render_basis(
        "table",
        small_manifold,
        out,
        spp=4,
        mode="onepass",
        components="full",
        resolution=8,
        max_depth=8,
        aovs=True,
    )
    assert "cross" in manifest.components and len(manifest.cross.sha256) == 64
    m = Manifold.load(small_manifold)
    x = m.latent[0]
    good, _ = blend(bf.Basis.load(out, manifold=m), m, x=x, l2="raw")
    cross = os.path.join(out, manifest.cross.file)
    edited = tmp_path / "edited"
    shutil.copytree(out, edited)
    with np.load(cross) as z:
        pairs, images = z["pairs"], z["images"]
    np.savez(os.path.join(edited, "cross.npz"), pairs=pairs, images=np.full_like(images, 1000))
    with pytest.raises(
        MismatchError, match="cross terms .* were changed after render_basis wrote them"
    ):
        blend(bf.Basis.load(edited, manifold=m), m, x=x, l2="raw")
    truncated = tmp_path / "truncated"
    shutil.copytree(out, truncated)
    with open(cross, "rb") as f:
        head = f.read(3000)
    with open(os.path.join(truncated, "cross.npz"), "wb") as f:
        f.write(head)
    manifest_path = os.path.join(truncated, bf.MANIFEST)
    with open(manifest_path) as f:
        data = json.load(f)
    data["cross"].pop("sha256")  # as a basis written before the hash was recorded
    with open(manifest_path, "w") as f:
        json.dump(data, f)
    with pytest.raises(MismatchError, match="unreadable") as err:
        blend(bf.Basis.load(truncated, manifold=m), m, x=x, l2="raw")
    assert "\n" not in str(err.value)
    bad_aovs = tmp_path / "bad_aovs"
    shutil.copytree(out, bad_aovs)
    with open(os.path.join(out, "aovs.npz"), "rb") as f:
        head = f.read(2000)
    with open(os.path.join(bad_aovs, "aovs.npz"), "wb") as f:
        f.write(head)
    with pytest.raises(MismatchError, match="aovs.npz is not an AOV file"):
        blend(bf.Basis.load(bad_aovs, manifold=m), m, x=x)
    np.testing.assert_array_equal(blend(bf.Basis.load(out, manifold=m), m, x=x, l2="raw")[0], good)


def test_point_render_gives_the_blended_material_and_its_exact_quadratic_model(small_manifold):
    """``point`` weights (the control variate of ``blend.py --refine``): the paths sample the
    blend, the blended material's own full-GI image equals Mitsuba's ``path`` rendering it
    (z-tests), and on paths with two vertices on the material (``levels`` 2) its L2+ equals, path
    by path, ``sum_i w_i R_i + sum_{i<j} w_i w_j C_ij`` from the same paths: the refinement's
    correction is exactly what the quadratic model misses."""
    from itertools import combinations

    from mitsuba_manifold.render.integrators.onepass import POINT

    scene = load("table", small_manifold, "gold-paint", res=16)
    (bsdf,) = integrators.manifold_bsdfs(scene)
    names, w = ["gold-paint", "white-diffuse-bball", "pink-fabric"], np.array([0.5, 0.3, 0.2])
    pairs = list(combinations(names, 2))
    (two,) = _gi(scene, levels=2, pairs=pairs, materials=names, point=w)[:1]
    model = sum(wi * two.rest[n] for wi, n in zip(w, names))
    model = model + sum(w[names.index(a)] * w[names.index(b)] * two.cross[(a, b)] for a, b in pairs)
    assert two.rest[POINT].mean() > 1e-3 * (two.base + two.touch[POINT]).mean()
    np.testing.assert_allclose(two.rest[POINT], model, rtol=1e-4, atol=1e-6 * two.rest[POINT].max())
    out = _gi(scene, levels=8, materials=names, point=w)
    bsdf.set_weights(dict(zip(names, w)))
    ref = renders(
        scene, mi.load_dict({"type": "path", "max_depth": 8}), 16, [700 + s for s in SEEDS]
    )
    assert_same_mean(
        np.stack([o.base + o.touch[POINT] + o.rest[POINT] for o in out]), ref, "point vs path"
    )


def test_point_weights_are_checked(small_manifold):
    from mitsuba_manifold.errors import InputError

    scene = load("table", small_manifold, "gold-paint", res=8)
    with pytest.raises(InputError, match="`point` must be finite weights, one per material"):
        integrator(max_depth=4).render_onepass_gi(
            scene, spp=1, materials=["gold-paint"], point=[0.5, 0.5]
        )

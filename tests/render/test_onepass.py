"""Tests of one-pass basis rendering (``render_onepass``): every material's touch image from
one set of paths agrees with rendering the material alone (statistically, or exactly when
the same paths are replayed), whatever the tiling and chunking of the table product."""

import os
import shutil

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np
import pytest
from helpers import assert_same_mean, chain, integrator, load, midpoint, renders, two_spheres  # noqa: E402,F401

import mitsuba_manifold.render  # noqa: F401  (selects a working libLLVM before drjit loads; the plugins)
from mitsuba_manifold.render import integrators  # noqa: E402
from mitsuba_manifold.render.integrators import splats  # noqa: E402

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]


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
    one = [
        integ.render_onepass(
            scene,
            spp=16,
            seed=s,
            chunk=3,
            spp_per_pass=4,
            progress=lambda d, t: calls.append((d, t)),
        )
        for s in seeds
    ]
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
    touch = np.array(
        mi.render(
            scene, integrator=integrator(target="a", component="touch", max_depth=6), spp=4, seed=5
        )
    )
    ref_base = np.array(
        mi.render(
            scene, integrator=integrator(target="a", component="base", max_depth=6), spp=4, seed=5
        )
    )
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
    ref_base = np.array(
        mi.render(
            scene, integrator=integrator(target="a", component="base", max_depth=6), spp=4, seed=5
        )
    )
    np.testing.assert_allclose(base, ref_base, rtol=1e-5, atol=1e-7)
    # With two materials the paths differ from a direct render: compare one material alone.
    base, images = integ.render_onepass(scene, materials=["gold-paint"], spp=4, seed=5)
    a.set_material("gold-paint")
    touch = np.array(
        mi.render(
            scene, integrator=integrator(target="a", component="touch", max_depth=6), spp=4, seed=5
        )
    )
    assert images["gold-paint"].mean() > 0.01
    np.testing.assert_allclose(images["gold-paint"], touch, rtol=1e-4, atol=1e-6)


def test_onepass_table_product_is_the_same_in_tiles_and_chunks(small_manifold, monkeypatch):
    """The per-pixel sums of the table product do not depend on how they are split: the
    whole image at once, or tiles of 100 pixels (the memory bound) with materials in
    chunks of 3 that straddle the 16-material packets of the interleaved tables."""
    scene = load("table", small_manifold, res=24)
    integ = integrator(max_depth=8)
    base, whole = integ.render_onepass(scene, spp=8, seed=2)
    monkeypatch.setattr(splats, "_SUM_BYTES", 100 * 12 * 16 * max(1, dr.thread_count()))
    calls = []
    base2, tiled = integ.render_onepass(
        scene, spp=8, seed=2, chunk=3, progress=lambda d, t: calls.append((d, t))
    )
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
    from mitsuba_manifold.data.database import Database

    folder = tmp_path / "db"
    shutil.copytree(small_db, folder, ignore=shutil.ignore_patterns(".manifold-cache"))
    db = Database(folder)
    names = ["chrome", "gold-paint", "white-diffuse-bball"]
    rows = db.material_rows(names)
    bins = int(np.prod(db.dims))
    assert rows.shape == (bins, 3, 16) and rows.dtype == np.float32
    for k, name in enumerate(names):
        np.testing.assert_array_equal(
            rows[:, :, k], np.asarray(db.reflectance(name)).reshape(3, bins).T
        )
    assert not np.any(rows[:, :, len(names) :])
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
    from mitsuba_manifold.data.database import Database

    names = ["chrome", "gold-paint", "blue-acrylic"]
    w = [0.2, 0.5, 0.3]
    spec = {"type": "manifold_brdf", "manifold": small_manifold, "prune": 0.0}
    combined = mi.load_dict({**spec, "weights": ", ".join(f"{n}:{v}" for n, v in zip(names, w))})
    rows = Database(small_db).material_rows(names)
    pad = np.zeros(rows.shape[2], dtype=np.float32)
    pad[:3] = w
    dims = Database(small_db).dims
    table = (
        (np.asarray(rows).reshape(-1, rows.shape[2]) @ pad)
        .reshape(-1, 3)
        .T.reshape((3,) + tuple(dims))
    )
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
        rng.random((2, 4096))  # the draw the test has always made: the generator stays where it was
        bsdf.result = [
            np.array(v)
            for v in (bs.wo, bs.pdf, value, bsdf.eval(ctx, si, bs.wo), bsdf.pdf(ctx, si, bs.wo))
        ]
    assert np.array(combined.result[1]).max() > 0
    for a, b in zip(combined.result, given.result):
        np.testing.assert_allclose(
            a, b, rtol=2e-4, atol=1e-6
        )  # float32: CUDA contracts FMAs its own way


def test_onepass_refuses_what_it_cannot_do(small_manifold):
    scene = two_spheres(small_manifold)
    with pytest.raises(ValueError, match="one-pass rendering handles one target group"):
        integrator(target="each").render_onepass(scene, spp=1)
    with pytest.raises(ValueError, match="unknown: \\['nope'\\]"):
        integrator(target="a").render_onepass(scene, materials=["chrome", "nope"], spp=1)
    with pytest.raises(ValueError, match="no manifold material"):
        integrator().render_onepass(mi.load_dict(mi.cornell_box()), spp=1)
    with pytest.raises(ValueError, match="`spp_per_pass` must be >= 1"):
        integrator(target="a").render_onepass(scene, spp=4, spp_per_pass=0)
    with pytest.raises(ValueError, match="`chunk` must be >= 1"):
        integrator(target="a").render_onepass(scene, spp=4, chunk=0)


# ------------------------------------------------------------------ errors


def test_onepass_takes_any_32_bit_seed_over_several_passes(small_manifold):
    """The largest seed a refinement pass can give, over several sub-passes: each sub-pass's seed
    stays a 32-bit number (no TypeError from Mitsuba's seed())."""
    scene = load("sphere", small_manifold, "gold-paint", res=8)
    base, images = integrator(max_depth=3).render_onepass(
        scene, spp=4, seed=0xFFFFFFFF, spp_per_pass=1
    )
    assert base.shape == (8, 8, 3) and np.isfinite(base).all() and base.max() > 0

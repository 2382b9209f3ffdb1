"""tools/explore.py for artists: paths that follow Manifold.path, the distance to the closest
measured material, thumbnails, the shipped HDRI, and in headless Chromium undo/redo,
favourites, compare, the slice at phi_d, the lobe plot and the layout at 1280x800."""

import json
import os

import numpy as np
import pytest

pytest.importorskip("starlette")
import test_explore  # noqa: E402  (mitsuba, the render marker, the module fixtures)
import test_explore_browser  # noqa: E402

from mitsuba_manifold.apps.explore import hdri  # noqa: E402
from mitsuba_manifold.data.distance import brdf_distance  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.manifold.paths import SEARCH_STRIDE  # noqa: E402

pytestmark = test_explore.pytestmark
small_basis, explorer, server, browser = (
    test_explore.small_basis,
    test_explore.explorer,
    test_explore.server,
    test_explore_browser.browser,
)
browser_only, _wait_displayed, _map_position = (
    test_explore.browser_only,
    test_explore._wait_displayed,
    test_explore._map_position,
)
READY = test_explore_browser.READY + " && window.explore.state.previewX"


# ---------------------------------------------------------------- service


def test_routes_are_manifold_paths(explorer, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    a, b = m.latent[m.index("chrome")], m.latent[m.index("pink-fabric")]
    for kind in ("straight", "uniform"):
        got = explorer.route("chrome", "pink-fabric", 21, kind).result(120)
        np.testing.assert_allclose(
            got["points"], m.path("chrome", "pink-fabric", 21, kind), rtol=0, atol=1e-9
        )
        assert got["kind"] == kind and got["a"] == a.tolist() and got["b"] == b.tolist()
    assert explorer.route("chrome", "pink-fabric", 21, "uniform").done()  # cached per pair
    geo = explorer.route("chrome", "pink-fabric", 21, "geodesic").result(300)
    straight = explorer.route("chrome", "pink-fabric", 21, "straight").result()
    np.testing.assert_array_equal(geo["points"][0], a)
    np.testing.assert_array_equal(geo["points"][-1], b)
    from mitsuba_manifold.manifold.paths import densify

    metric = explorer.walks.metric
    length = [metric.steps(densify(np.array(p["points"]), 129)).sum() for p in (geo, straight)]
    assert length[0] <= length[1] * (
        1 + 1e-3
    )  # never longer than the segment (both densely measured)
    with pytest.raises(test_explore.InputError, match="kind"):
        explorer.route("chrome", "steel", 21, "curly")
    with pytest.raises(test_explore.InputError, match="same point"):
        explorer.route("chrome", "chrome", 21, "uniform")


def test_closest_measured_material_under_the_perceptual_metric(explorer, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    tables = m.tables()
    _ = explorer.walks  # prepared in the background once the tables are in; waits for it
    for x in (
        0.5 * (m.latent[0] + m.latent[3]),
        0.3 * m.latent[1] + 0.7 * m.latent[5],
        m.latent[2],
    ):
        got = explorer.material(x, with_slice=False)["measured"]
        interpolated = np.maximum(m.weights(x)[1].astype(np.float32) @ tables, 0)
        d = brdf_distance(interpolated[None], tables, dims=m.info["dims"], stride=SEARCH_STRIDE)
        assert got["name"] == m.names[int(np.argmin(d))]
        assert got["distance"] == pytest.approx(d.min(), rel=1e-3, abs=1e-6)
        assert got["spacing"] > 0
    assert "slice" not in explorer.material(m.latent[0], with_slice=False)


def test_refinement_replaces_the_blend_only_where_it_is_off_by_more_than_its_noise():
    """The explorer's decision on release (reference.agreement): a blend equal to the refined image
    agrees; one 10% too dark does not, although its difference is small beside the pixels; after one
    pass (no noise estimate) there is no decision."""
    from mitsuba_manifold.apps.explore.reference import agreement
    from mitsuba_manifold.render.jobs.refine import _estimate

    rng = np.random.default_rng(3)
    truth = rng.uniform(0.2, 0.8, (16, 16, 3))
    passes = [truth + rng.normal(0, 0.01, truth.shape) for _ in range(4)]
    total, total2 = sum(4 * p for p in passes), sum(4 * p * p for p in passes)
    zero = np.zeros_like(truth)
    refined = _estimate(zero, total, total2, 16, 4, 1.0)
    assert agreement(truth.astype(np.float32), refined)["agrees"] is True
    off = agreement((0.9 * truth).astype(np.float32), refined)
    assert off["agrees"] is False and off["blend_rel_mse"] > 2 * off["noise_rel_mse"]
    one = _estimate(zero, 4 * passes[0], 4 * passes[0] ** 2, 4, 1, 1.0)
    assert agreement(truth.astype(np.float32), one)["agrees"] is None


def test_a_refinement_queued_behind_a_newer_one_never_renders():
    """Quick releases queue refinements behind one worker: only the newest one renders."""
    from mitsuba_manifold.apps.explore.reference import Job, References

    refs = References()
    try:
        stale, refs._latest_refine = Job(id="r1", basis="b", x=[0.0], spp=8, kind="refine"), "r2"
        refs._run_refine(stale, None, None, None, {})  # no basis needed: it stops before any work
        assert stale.state == "cancelled" and "superseded" in stale.message and not stale.images
        latest = Job(id="r2", basis="b", x=[0.0], spp=8, kind="refine")
        refs.supersede_refine()  # a drag began: the newest one stops too
        refs._run_refine(latest, None, None, None, {})
        assert latest.state == "cancelled" and "superseded" in latest.message
    finally:
        refs.shutdown()


@pytest.mark.render
def test_thumbnails_are_the_materials_alone_denoised_and_cached(small_manifold_paper, tmp_path):
    """Each tile is its material alone (weight 1), rendered at twice the size with its guides,
    denoised and averaged down: closer to a 16x-spp render of that material than the raw
    few-spp render averaged down is. A second start reads the cache (nothing rendered)."""
    import mitsuba as mi

    import mitsuba_manifold
    from mitsuba_manifold.apps.explore import encode, thumbs
    from mitsuba_manifold.basis.blend import blend
    from mitsuba_manifold.render.jobs.render_basis import render_basis

    m = Manifold.load(small_manifold_paper)
    t = thumbs.Thumbnails(small_manifold_paper, m, str(tmp_path), size=16, spp=4)
    assert t.wait(300) == "ready", t.message
    assert os.path.isfile(os.path.join(t.folder, "aovs.npz"))
    sheet, cols = _png(t.sheet()), t.columns
    assert sheet.shape[:2] == (16 * -(-m.n // cols), 16 * cols)
    mi.set_variant("llvm_ad_rgb")
    mitsuba_manifold.register()
    names = [m.names[0], m.names[-1]]
    clean = str(tmp_path / "clean")
    render_basis(
        t.scene,
        small_manifold_paper,
        clean,
        spp=64,
        resolution=(32, 32),
        mode="onepass",
        materials=names,
    )
    for i in (0, m.n - 1):
        r, c = divmod(i, cols)
        tile = sheet[16 * r : 16 * r + 16, 16 * c : 16 * c + 16, :3].astype(float)
        w = np.eye(m.n)[i]
        raw = encode.tonemap(thumbs.shrink(blend(t.folder, m, w=w, prune=0.0)[0], 16), 0.0).astype(
            float
        )
        truth = encode.tonemap(thumbs.shrink(blend(clean, m, w=w, prune=0.0)[0], 16), 0.0).astype(
            float
        )
        assert np.mean((tile - truth) ** 2) < 0.7 * np.mean((raw - truth) ** 2), m.names[i]
    again = thumbs.Thumbnails(small_manifold_paper, m, str(tmp_path), size=16, spp=4)
    assert (
        again.wait(60) == "ready" and again._proc is None and again.sheet() == t.sheet()
    )  # from the cache


def _png(data):
    import io

    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)))


def test_shipped_environment_is_the_generators_output():
    env = hdri.studio()
    with open(os.path.join(hdri.FOLDER, "studio.f16"), "rb") as f:
        shipped = np.frombuffer(f.read(), dtype="<f2").reshape(env.shape)
    np.testing.assert_array_equal(shipped, env.astype("<f2"))
    with open(os.path.join(hdri.FOLDER, "studio.json")) as f:
        assert json.load(f) == json.loads(json.dumps(hdri.describe(env)))
    _, omega = hdri.directions()
    total = (env * omega[..., None]).sum(axis=(0, 1))
    for n in hdri.LIGHTS:
        dirs, power = hdri.median_cut(env, n)
        assert dirs.shape == (n, 3) and np.allclose(np.linalg.norm(dirs, axis=1), 1)
        np.testing.assert_allclose(
            power.sum(axis=0), total, rtol=1e-6
        )  # every region's energy, once


# ---------------------------------------------------------------- browser


def _page(browser, url, width=1500, height=1000, context=None):
    return test_explore_browser._page(browser, url, width, height, context, READY)


def _go(pg, m, name):
    return test_explore._click_material(pg, m.file, name)


@browser_only
def test_scrubber_follows_the_uniform_path_and_the_map_draws_it(
    browser, server, small_manifold_paper
):
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server) as pg:
        pg.select_option("#path-kind", "uniform")
        for name, button in (("chrome", "#set-a"), ("pink-fabric", "#set-b")):
            _go(pg, m, name)
            pg.click(button)
        # straight at once, until the path arrives (a uniform path may come back within the same frame)
        assert pg.evaluate("window.explore.state.route.kind") in ("straight", "uniform")
        pg.wait_for_function("window.explore.state.route.kind === 'uniform'", timeout=120000)
        expected = m.path("chrome", "pink-fabric", 21, "uniform")
        np.testing.assert_allclose(
            pg.evaluate("window.explore.state.route.points"), expected, atol=1e-9
        )
        pg.fill("#scrub", "500")
        pg.dispatch_event("#scrub", "input")
        np.testing.assert_allclose(pg.evaluate("window.explore.state.x"), expected[10], atol=1e-12)
        assert "uniform" in pg.inner_text("#route-state") and "perceptual length" in pg.inner_text(
            "#route-state"
        )
        pg.click("#export-path")
        pg.wait_for_selector("#path-cmd:not([hidden])")
        assert "--path-kind uniform" in pg.inner_text("#path-cmd")
        assert not pg.errors


@browser_only
def test_undo_redo_favourites_compare(browser, server, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    ctx = browser.new_context(viewport={"width": 1500, "height": 1000})
    try:
        with _page(browser, server, context=ctx) as pg:
            a = _go(pg, m, "steel")
            b = _go(pg, m, "gold-paint")
            pg.keyboard.press("Control+z")
            _wait_displayed(pg, a)
            pg.keyboard.press("Control+Shift+z")
            _wait_displayed(pg, b)
            pg.click("#fav")
            assert pg.inner_text("#fav").startswith("★")
            pg.click("#compare-add")
            _go(pg, m, "chrome")
            pg.click("#compare-add")
            pg.wait_for_function(
                """() => { const imgs = document.querySelectorAll('#compare img.frame');
                return imgs.length === 2 && [...imgs].every((i) => i.complete && i.naturalWidth > 0); }""",
                timeout=30000,
            )
            assert "gold-paint" in pg.inner_text("#compare") and "chrome" in pg.inner_text(
                "#compare"
            )
        with _page(browser, server, context=ctx) as pg:  # favourites stay in this browser
            pg.wait_for_selector("#favs .fav")
            assert "gold-paint" in pg.inner_text("#favs")
            pg.click("#favs .fav span")
            _wait_displayed(pg, b)
            assert not pg.errors
    finally:
        ctx.close()


@browser_only
def test_slice_at_phi_d_and_lobe_from_the_table(browser, server, explorer, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server) as pg:
        x = _go(pg, m, "chrome")
        pg.wait_for_function(
            "(x) => window.explore.state.previewX.every((v, k) => v === x[k])", arg=x.tolist()
        )
        pg.click(".tabs button[data-tab=slice]")
        pg.fill("#phi-d", "30")
        pg.dispatch_event("#phi-d", "input")
        w, h, shown = pg.evaluate("""() => { const c = document.getElementById('slice');
            return [c.width, c.height, Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data)]; }""")
        data, meta = explorer.preview_table(x)
        table = np.frombuffer(data, dtype=np.float16).astype(np.float64).reshape([3] + meta["dims"])
        n_p = meta["dims"][2]
        ip = min(n_p - 1, round(30 / 180 * n_p - 0.5))
        v = np.log10(
            np.maximum(table[:, :, :, ip].mean(axis=0), 1e-3)
        )  # (n_h, n_d), theta_h up in the image
        brightness = np.array(shown, dtype=float).reshape(h, w, 4)[::-1, :, :3].sum(-1)
        assert (w, h) == (meta["dims"][1], meta["dims"][0])
        # one colour map, monotone in the value: the pixels rank as the log values do
        assert np.corrcoef(brightness.ravel(), v.ravel())[0, 1] > 0.95
        pg.click(".tabs button[data-tab=lobe]")
        pg.fill("#theta-i", "40")
        pg.dispatch_event("#theta-i", "input")
        assert (
            abs(pg.evaluate("window.explore.state.lobePeak") - 40) <= 3
        )  # chrome: the mirror direction
        assert not pg.errors


@browser_only
def test_closest_measured_thumbnails_environment_and_layout_at_1280(
    browser, server, small_manifold_paper
):
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server, 1280, 800) as pg:
        _go(pg, m, "blue-acrylic")
        pg.wait_for_function(
            "document.getElementById('measured').textContent.includes('blue-acrylic')"
        )
        assert (
            pg.evaluate("window.explore.state.material.measured.distance") < 1e-3
        )  # at its own point
        for sel in ("#map", "#scene", "#sphere"):  # map, scene and sphere above the fold
            box = pg.locator(sel).bounding_box()
            assert box["y"] + box["height"] <= 800 and box["x"] + box["width"] <= 1280, (sel, box)
        pg.wait_for_function(
            f"document.querySelectorAll('#gallery .tile .thumb').length === {m.n}", timeout=240000
        )
        pg.click("#gallery .tile[data-name=steel]")
        _wait_displayed(pg, m.latent[m.index("steel")])
        pg.wait_for_function("window.explore.preview.envReady")
        pg.wait_for_timeout(300)
        grab = """() => { const s = document.getElementById('sphere'), c = document.createElement('canvas');
            c.width = s.width; c.height = s.height; const g = c.getContext('2d'); g.drawImage(s, 0, 0);
            return Array.from(g.getImageData(0, 0, s.width, s.height).data); }"""
        before = np.array(pg.evaluate(grab), dtype=float)
        pg.fill("#env-rot", "120")
        pg.dispatch_event("#env-rot", "input")
        pg.wait_for_timeout(300)
        assert (
            np.abs(np.array(pg.evaluate(grab), dtype=float) - before).mean() > 1.0
        )  # the HDRI rotates
        assert not pg.errors

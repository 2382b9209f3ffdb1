"""tools/explore.py in headless Chromium: never the wrong point (drag, stop, copy), late answers
dropped, q > 2 slices, shared links out of range, zoom reset, the panel at wide layouts."""

import contextlib
import json
import os
import re
import struct

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("starlette")
pytestmark = pytest.mark.render

import test_explore  # noqa: E402

from mitsuba_manifold.apps.explore.web import launch  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402

small_basis, q3_basis, server = test_explore.small_basis, test_explore.q3_basis, test_explore.server
browser_only, CHROMIUM = test_explore.browser_only, test_explore.CHROMIUM
_wait_displayed, _map_position = test_explore._wait_displayed, test_explore._map_position
READY = "window.explore && window.explore.state.displayed && window.explore.state.material && window.explore.state.map"


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(
            executable_path=CHROMIUM,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        yield b
        b.close()


@contextlib.contextmanager
def _page(browser, url, width=1500, height=1000, context=None, ready=READY):
    """A new tab on ``url``, ready; in ``context`` (default: its own, clipboard allowed, closed afterwards)."""
    ctx = context or browser.new_context(
        viewport={"width": width, "height": height},
        permissions=["clipboard-read", "clipboard-write"],
    )
    try:
        pg = ctx.new_page()
        pg.errors = []
        pg.on("pageerror", lambda e: pg.errors.append(str(e)))
        pg.goto(url)
        pg.wait_for_function(ready, timeout=60000)
        yield pg
    finally:
        if context is None:
            ctx.close()


def _set(pg, x):
    pg.evaluate("(x) => window.explore.setX(x)", [float(v) for v in x])
    _wait_displayed(pg, x)


def _x_of_xml(xml):
    return np.array(
        [float(v) for v in re.search(r'name="x" value="([^"]+)"', xml).group(1).split(",")]
    )


@browser_only
def test_drag_the_path_slider_stop_and_copy_gives_the_point_shown(
    browser, server, small_manifold_paper
):
    """The issue's case: A and B set, the t slider dragged over 20 steps with the mouse, stop,
    Copy XML at once: the clipboard holds the point the panel shows, and the scene shows it."""
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server) as pg:
        pg.select_option(
            "#path-kind", "straight"
        )  # the latent segment (test_explore_artist: the other kinds)
        for name, button in (("gold-paint", "#set-a"), ("blue-acrylic", "#set-b")):
            _set(pg, m.latent[m.index(name)])
            pg.click(button)
        box = pg.locator("#scrub").bounding_box()
        y = box["y"] + box["height"] / 2
        pg.mouse.move(
            box["x"] + box["width"] - 8, y
        )  # B end: the slider is at t = 1 after "B <- here"
        pg.mouse.down()
        for k in range(1, 21):
            pg.mouse.move(box["x"] + box["width"] - 8 - k * (box["width"] / 2 - 8) / 20, y)
        pg.mouse.up()
        pg.click("#copy-xml")
        pg.wait_for_function("window.explore.state.copied !== undefined", timeout=10000)
        shown = np.array(pg.evaluate("window.explore.state.x"))
        t = pg.evaluate("+document.getElementById('scrub').value / 1000")
        assert 0.35 < t < 0.65, t
        np.testing.assert_allclose(
            shown,
            (1 - t) * m.latent[m.index("gold-paint")] + t * m.latent[m.index("blue-acrylic")],
            rtol=1e-12,
            atol=1e-12,
        )
        clip = pg.evaluate("navigator.clipboard.readText()")
        assert clip == pg.evaluate("window.explore.state.copied")
        np.testing.assert_allclose(_x_of_xml(clip), shown, rtol=1e-5, atol=1e-6)
        label = pg.inner_text("#material-name")
        assert label == "x = (" + ", ".join(f"{v:.3f}" for v in shown) + ")", label
        _wait_displayed(pg, shown)
        np.testing.assert_allclose(
            _x_of_xml(pg.inner_text("#snippet")), shown, rtol=1e-5, atol=1e-6
        )
        np.testing.assert_array_equal(pg.evaluate("window.explore.state.material.x"), shown)
        pg.click("#export-path")
        pg.wait_for_selector("#path-cmd:not([hidden])")
        cmd = pg.inner_text("#path-cmd")
        tool = os.path.join(
            os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
            "tools",
            "blend.py",
        )
        assert (
            cmd.startswith(f"python3 {tool} --basis /")
            and "--path gold-paint blue-acrylic --steps 20" in cmd
        )
        assert not pg.errors


@browser_only
def test_late_answers_are_dropped(browser, server, small_manifold_paper):
    """An answer older than the one shown (another kind's order, a slow worker) is not applied."""
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server) as pg:
        x = m.latent[m.index("chrome")]
        _set(pg, x)
        seq = pg.evaluate("window.explore.channel.answered.material")
        old = {"type": "material", "seq": seq - 1, "x": [9.0, 9.0], "weights": [], "nearest": []}
        head = json.dumps(old).encode()
        msg = list(struct.pack("<I", len(head)) + head)
        pg.evaluate("(b) => window.explore.channel.receive(new Uint8Array(b).buffer)", msg)
        assert pg.evaluate("window.explore.channel.dropped") >= 1
        np.testing.assert_array_equal(pg.evaluate("window.explore.state.material.x"), x)
        # a burst of points: what is shown at the end is the last one, frame, material and snippet
        pts = [0.5 * (m.latent[i % m.n] + m.latent[(i + 3) % m.n]) for i in range(40)]
        pg.evaluate(
            "(ps) => { for (const p of ps) window.explore.setX(p); }",
            [[float(v) for v in p] for p in pts],
        )
        _wait_displayed(pg, pts[-1])
        pg.wait_for_function(
            "(x) => { const s = window.explore.state; return s.material.x.every((v, k) => v === x[k]) "
            "&& s.snippet.x.every((v, k) => v === x[k]); }",
            arg=[float(v) for v in pts[-1]],
        )
        assert (
            pg.evaluate("window.explore.state.moves") < 40
        )  # one message per browser frame, not per call


@browser_only
def test_one_image_is_singular_and_weights_mark_the_kept(browser, server, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server) as pg:
        _set(pg, m.latent[m.index("steel")])
        assert pg.text_content("#timing").startswith("1 image ·")
        prune = pg.evaluate("window.explore.state.info.prune")
        candidates = (
            (1 - t) * m.latent[i] + t * m.latent[j]
            for i in range(m.n)
            for j in range(m.n)
            if i != j
            for t in (0.02, 0.05, 0.1, 0.2)
        )
        x = next(
            x for x in candidates if 1 < len(m.prune(m.weights(x)[1], prune)[0]) < m.n
        )  # some pruned
        _set(pg, x)
        pg.wait_for_function("(x) => window.explore.state.material.x[0] === x", arg=float(x[0]))
        n = pg.evaluate("window.explore.state.material.n_kept")
        assert re.match(rf"{n} images ·", pg.text_content("#timing"))
        assert (
            pg.locator("#weights .name.kept").count() == n
            and pg.locator("#weights .name.pruned").count() >= 1
        )
        assert "kept after pruning" in pg.inner_text("#weights-note")


@browser_only
@pytest.mark.parametrize("width,height", [(1280, 800), (1600, 1000), (1920, 1080)])
def test_confidence_meter_has_a_width(browser, server, width, height):
    with _page(browser, server, width, height) as pg:
        pg.click("#material-details summary")  # the confidence meter is a detail
        meter = pg.locator("#conf-bar").locator("..").bounding_box()
        assert meter["width"] >= 60, meter
        bar = pg.evaluate("getComputedStyle(document.getElementById('conf-bar')).width")
        assert float(bar[:-2]) > 0, bar


@browser_only
def test_double_click_resets_the_zoom_and_keeps_the_point(browser, server, small_manifold_paper):
    x = Manifold.load(small_manifold_paper).latent[
        Manifold.load(small_manifold_paper).index("pink-fabric")
    ]
    with _page(browser, server) as pg:
        _set(pg, x)
        full, box = (
            pg.evaluate("window.explore.state.map.extent"),
            pg.locator("#map").bounding_box(),
        )
        pg.mouse.move(box["x"] + box["width"] * 0.3, box["y"] + box["height"] * 0.6)
        for _ in range(4):
            pg.mouse.wheel(0, -100)
        pg.wait_for_function(
            "(f) => window.explore.state.map.extent[1] - window.explore.state.map.extent[0] < "
            "0.8 * (f[1] - f[0])",
            arg=full,
        )
        pg.mouse.dblclick(box["x"] + box["width"] * 0.7, box["y"] + box["height"] * 0.3)
        pg.wait_for_function("window.explore.state.zoom === null")
        _wait_displayed(pg, x)
        np.testing.assert_array_equal(pg.evaluate("window.explore.state.x"), x)
        assert pg.evaluate("window.explore.state.map.extent") == full


@browser_only
def test_links_out_of_range_or_malformed_leave_the_page_usable(
    browser, server, small_manifold_paper
):
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server + "#x=1e7,0") as pg:
        x = pg.evaluate("window.explore.state.x")
        assert abs(x[0]) < 100 and x[1] == 0 and "moved inside" in pg.inner_text("#status")
        _wait_displayed(pg, x)
        assert pg.evaluate("window.explore.state.map.extent")
        pg.goto("about:blank")
        for bad in ("1_0,0", "nan,0", "1,2,3", "no-such"):
            pg.goto(server + "#x=" + bad)
            pg.wait_for_function(READY, timeout=60000)
            assert "ignored" in pg.inner_text("#status"), bad
            pg.goto("about:blank")
        pg.goto(server + "#x=chrome")
        pg.wait_for_function(READY, timeout=60000)
        _wait_displayed(pg, m.latent[m.index("chrome")])
        assert not pg.errors


@browser_only
def test_q3_snapping_keeps_the_slice_and_a_click_reslices(browser, q3_basis):
    basis, manifold = q3_basis
    m = Manifold.load(manifold)
    proc, url = launch.start([basis], manifold, ["--no-tables"])
    try:
        with _page(browser, url) as pg:
            i = int(
                np.argmax(np.abs(m.latent[:, 2] - m.latent[:, 2].mean()))
            )  # a material off the middle slice
            start = m.latent.mean(axis=0)
            start[2] = m.latent[:, 2].mean()
            _set(pg, start)
            far = start.copy()
            far[:2] = m.latent[i, :2] + np.array([0.3, 0.3]) * np.ptp(m.latent[:, :2], axis=0)
            a, b = _map_position(pg, far), _map_position(pg, m.latent[i])
            pg.mouse.move(*a)
            pg.mouse.down()
            for t in np.linspace(0, 1, 10)[1:]:
                pg.mouse.move(a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]))
            x = np.array(pg.evaluate("window.explore.state.x"))
            np.testing.assert_array_equal(
                x[:2], m.latent[i, :2]
            )  # snapped in the map's coordinates
            assert x[2] == start[2]  # the slice stays
            pg.mouse.up()
            pg.wait_for_timeout(700)
            pg.mouse.click(*b)  # a click takes the whole point ...
            _wait_displayed(pg, m.latent[i])
            pg.wait_for_function(
                "(z) => window.explore.state.map.slice[1][0] === z",
                arg=float(m.latent[i, 2]),
                timeout=30000,
            )  # ... and the map re-slices through it
            assert pg.evaluate("+document.querySelector('#sliders input').value") == pytest.approx(
                m.latent[i, 2], abs=1e-2
            )
    finally:
        code, out = launch.stop(proc)
        assert code == 0, out[-3000:]


@browser_only
def test_search_by_name_goes_to_the_material(browser, server, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server) as pg:
        pg.fill("#search", "Blue-Acrylic")
        _wait_displayed(pg, m.latent[m.index("blue-acrylic")])
        assert pg.inner_text("#material-name") == "blue-acrylic"
        pg.fill("#search", "blue-acrylc")  # a typo and Enter: told why nothing happened
        pg.press("#search", "Enter")
        assert "no measured material" in pg.evaluate(
            "document.getElementById('search').validationMessage"
        )
        pg.fill("#search", "chrom")  # a unique part of a name and Enter: there
        pg.press("#search", "Enter")
        _wait_displayed(pg, m.latent[m.index("chrome")])
        assert (
            pg.evaluate("document.getElementById('search').validationMessage") == ""
            and not pg.errors
        )


@browser_only
def test_release_refines_the_point_to_its_full_gi_image(browser, small_basis, small_manifold_paper):
    """With --refine-spp, choosing a point (a drag's end) renders its L2+ light in the background and
    says whether the blend shown agrees with that unbiased render within its measured noise; the blend
    stays. The basis is of the convex sphere (no path touches it twice), so the refinement is the blend
    itself: it agrees. "show refined" draws the refined image of the point; the next move goes back to
    blends (the decision itself: test_explore_artist)."""
    m = Manifold.load(small_manifold_paper)
    proc, url = launch.start(
        [small_basis], small_manifold_paper, ["--no-thumbnails", "--refine-spp", "8"], refine=True
    )
    pixels = "() => Array.from(document.getElementById('scene').getContext('2d').getImageData(0, 0, 32, 32).data)"
    try:
        with _page(browser, url) as pg:
            assert pg.eval_on_selector("#refine-spp", "s => s.value") == "8"
            _set(pg, 0.5 * (m.latent[m.index("gold-paint")] + m.latent[m.index("blue-acrylic")]))
            blend = np.array(pg.evaluate(pixels), float)
            pg.evaluate("() => window.explore.commitPoint()")
            pg.wait_for_function(
                "document.getElementById('refine-status').textContent.includes('full GI checked')",
                timeout=120000,
            )
            status = pg.text_content("#refine-status")
            assert "agrees with the unbiased render" in status and "spp" in status, status
            assert not pg.evaluate("document.getElementById('scene').dataset.refined")
            np.testing.assert_array_equal(np.array(pg.evaluate(pixels), float), blend)
            pg.click("#refine-show")  # the user asks for the refined image
            pg.wait_for_function("document.getElementById('scene').dataset.refined === 'r1'")
            assert "showing the unbiased render" in pg.text_content("#refine-status")
            refined = np.array(pg.evaluate(pixels), float)
            assert np.abs(refined - blend).max() <= 2 and blend.max() > 0
            # a new exposure re-exposes the refined image (the server tonemaps it again), not the blend
            pg.eval_on_selector(
                "#exposure", "e => { e.value = '1.5'; e.dispatchEvent(new Event('input')); }"
            )
            pg.wait_for_function(
                "document.getElementById('scene').dataset.refinedExposure === '1.5'"
            )
            brighter = np.array(pg.evaluate(pixels), float)
            assert pg.evaluate("document.getElementById('scene').dataset.refined") == "r1"
            assert brighter.mean() > refined.mean() + 5, (brighter.mean(), refined.mean())
            pg.wait_for_timeout(
                500
            )  # nothing arriving later (a frame, another tonemap) replaces it
            np.testing.assert_array_equal(np.array(pg.evaluate(pixels), float), brighter)
            assert pg.evaluate("document.getElementById('scene').dataset.refined") == "r1"
            assert "showing the unbiased render" in pg.text_content(
                "#refine-status"
            )  # no later poll's check
            _set(pg, m.latent[m.index("gold-paint")])  # a move: blends again
            assert not pg.evaluate("document.getElementById('scene').dataset.refined")
            assert pg.text_content("#refine-status") == "" and not pg.errors
    finally:
        launch.stop(proc)


@browser_only
def test_the_tooltip_goes_when_the_pointer_is_released(browser, server, small_manifold_paper):
    """Hovering a measured material shows its name; a press and release on it, or a drag from it
    released outside the map (the pointer captured), leaves no tooltip on screen."""
    m = Manifold.load(small_manifold_paper)
    hidden = "document.getElementById('tooltip').hidden"
    with _page(browser, server) as pg:
        for name in ("gold-paint", "blue-acrylic"):
            px, py = _map_position(pg, m.latent[m.index(name)])
            pg.mouse.move(px + 20, py + 20)
            pg.mouse.move(px, py)
            assert not pg.evaluate(hidden) and name in pg.inner_text("#tooltip")
            pg.mouse.down()
            pg.mouse.up()
            assert pg.evaluate(hidden)
            pg.mouse.move(px + 1, py)  # hovering again: back
            assert not pg.evaluate(hidden)
            pg.mouse.down()
            box = pg.eval_on_selector(
                "#map", "c => { const r = c.getBoundingClientRect(); return [r.right, r.bottom]; }"
            )
            for k in range(1, 6):
                pg.mouse.move(px + k / 5 * (box[0] + 40 - px), py + k / 5 * (box[1] + 40 - py))
            pg.mouse.up()
            assert pg.evaluate(hidden)
        assert not pg.errors


@browser_only
def test_a_drag_from_a_material_in_another_slice_asks_for_one_full_map(browser, q3_basis):
    """q = 3: a press on a material off the map's slice moves the slice (to its whole point) and
    the drag from it stays there: the page asks for that slice's map once, in full (no coarse map
    first); a slider moving the slice asks for coarse maps while it moves."""
    basis, manifold = q3_basis
    m = Manifold.load(manifold)
    proc, url = launch.start([basis], manifold, ["--no-tables"])
    try:
        with _page(browser, url) as pg:
            i = int(np.argmax(np.abs(m.latent[:, 2] - m.latent[:, 2].mean())))
            start = m.latent.mean(axis=0)
            start[2] = m.latent[:, 2].mean()
            _set(pg, start)
            pg.evaluate("""() => { const ch = window.explore.channel, send = ch.send.bind(ch);
                window.__maps = []; ch.send = (body, kinds) => { const seq = send(body, kinds);
                if (kinds.includes("map")) window.__maps.push([body.type, body.map_coarse === true || (body.type === "move" && body.map_coarse === undefined && body.coarse)]);
                return seq; }; }""")
            a = _map_position(pg, m.latent[i])
            pg.mouse.move(*a)
            pg.mouse.down()  # on the material: its whole point, a new slice
            for k in range(1, 8):
                pg.mouse.move(a[0] + 4 * k, a[1] + 3 * k)
                pg.wait_for_timeout(20)
            pg.mouse.up()
            pg.wait_for_function(
                "(z) => window.explore.state.map.slice[1][0] === z && window.explore.channel.pending() === 0",
                arg=float(m.latent[i, 2]),
                timeout=30000,
            )
            assert pg.evaluate("window.__maps") == [["move", False]]
            pg.evaluate("() => { window.__maps = []; }")
            pg.eval_on_selector(
                "#sliders input",
                """(s) => { for (const f of [0.2, 0.4, 0.6]) { s.value = +s.min + f * (s.max - s.min);
                    s.dispatchEvent(new Event('input')); } }""",
            )
            pg.wait_for_function("window.__maps.length >= 1", timeout=30000)
            assert pg.evaluate("window.__maps")[0] == ["move", True]
    finally:
        code, out = launch.stop(proc)
        assert code == 0, out[-3000:]


@browser_only
def test_the_page_opens_on_the_coarse_map_then_the_full_one(browser, server):
    """The first map the page asks for is the coarse one (shown in a fraction of the full one's
    time); once it is shown the page asks for the full one, and that is the map left shown."""
    ctx = browser.new_context(viewport={"width": 1500, "height": 1000})
    try:
        pg = ctx.new_page()
        pg.add_init_script("""window.__maps = []; const send = WebSocket.prototype.send;
            WebSocket.prototype.send = function (text) { const m = JSON.parse(text);
                if (m.type === "map" || (m.want || []).includes("map"))
                    window.__maps.push(m.type === "map" ? false : m.map_coarse === true);
                return send.call(this, text); };""")
        pg.goto(server)
        pg.wait_for_function(
            "window.explore && window.explore.state.mapImage && "
            "window.explore.state.mapImage.naturalWidth === 192 && window.explore.channel.pending() === 0",
            timeout=60000,
        )
        maps = pg.evaluate("window.__maps")
        assert maps[0] is True and False in maps, maps
    finally:
        ctx.close()

"""The page keeps one state: every part follows the point after undo/redo, drags, search and path
scrubbing (tooltip, gallery filter, highlights, refine status, header errors, path kind), fits
an 800x600 window, and background jobs of a closed page neither run on nor stop the next ones."""

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("starlette")
pytestmark = pytest.mark.render

import test_explore  # noqa: E402
import test_explore_browser  # noqa: E402

from mitsuba_manifold.apps.explore.web import launch  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402

small_basis, server, browser = (
    test_explore.small_basis,
    test_explore.server,
    test_explore_browser.browser,
)
browser_only, _page, _set = (
    test_explore.browser_only,
    test_explore_browser._page,
    test_explore_browser._set,
)
_map_position = test_explore._map_position


def _click(pg, m, name):
    """Click a material on the map (a committed move) and wait for its frame."""
    x = m.latent[m.index(name)]
    pg.mouse.click(*_map_position(pg, x))
    test_explore._wait_displayed(pg, x)
    return x


@browser_only
def test_the_tooltip_is_hidden_until_a_material_is_hovered(browser, server, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    shown = "getComputedStyle(document.getElementById('tooltip')).display !== 'none'"
    with _page(browser, server) as pg:
        assert not pg.evaluate(shown)  # no empty box on the map from the start
        px, py = _map_position(pg, m.latent[m.index("chrome")])
        pg.mouse.move(px, py)
        assert pg.evaluate(shown)
        pg.mouse.move(px + 300, py + 300)
        assert not pg.evaluate(shown)


@browser_only
def test_a_move_elsewhere_ends_the_search_filter(browser, server, small_manifold_paper):
    """A partial name filters the gallery (the heading counts what is shown); a drag, a click or
    undo to another point ends the search: all tiles, the heading counts them all."""
    m = Manifold.load(small_manifold_paper)
    n = len(m.names)
    tiles = "document.querySelectorAll('#gallery .tile').length"
    with _page(browser, server) as pg:
        _click(pg, m, "chrome")
        _click(pg, m, "steel")
        pg.fill("#search", "paint")
        k = sum("paint" in name for name in m.names)
        assert pg.evaluate(tiles) == k and pg.inner_text("#gallery-count").startswith(f"{k} of {n}")
        _click(pg, m, "blue-acrylic")  # a click on the map
        assert pg.evaluate(tiles) == n and pg.inner_text("#gallery-count") == f"{n} materials"
        assert pg.input_value("#search") == "blue-acrylic"
        pg.fill("#search", "paint")
        pg.click("#undo")  # back to steel
        test_explore._wait_displayed(pg, m.latent[m.index("steel")])
        assert pg.evaluate(tiles) == n and pg.inner_text("#gallery-count") == f"{n} materials"
        assert pg.input_value("#search") == "steel" and not pg.errors


@browser_only
def test_compare_and_favourite_highlights_follow_undo_and_redo(
    browser, server, small_manifold_paper
):
    m = Manifold.load(small_manifold_paper)
    here = """() => ({cmp: [...document.querySelectorAll('#compare .cmp')].map((e) => e.classList.contains('here')),
                     fav: [...document.querySelectorAll('#favs .fav')].map((e) => e.classList.contains('here')),
                     button: document.getElementById('fav').textContent})"""
    with _page(browser, server) as pg:
        pg.evaluate("localStorage.clear()")
        _click(pg, m, "gold-paint")
        pg.click("#fav")
        pg.click("#compare-add")
        _click(pg, m, "pink-fabric")
        pg.click("#compare-add")
        assert pg.evaluate(here) == {"cmp": [False, True], "fav": [False], "button": "☆ favourite"}
        pg.click("#undo")
        test_explore._wait_displayed(pg, m.latent[m.index("gold-paint")])
        assert pg.evaluate(here) == {"cmp": [True, False], "fav": [True], "button": "★ favourite"}
        pg.click("#redo")
        test_explore._wait_displayed(pg, m.latent[m.index("pink-fabric")])
        assert pg.evaluate(here) == {"cmp": [False, True], "fav": [False], "button": "☆ favourite"}
        assert not pg.errors


@browser_only
def test_a_later_valid_export_clears_the_header_error(browser, server, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server) as pg:
        _set(pg, m.latent[m.index("chrome")])
        pg.click("#set-a")
        _set(pg, m.latent[m.index("steel")])
        pg.click("#set-b")
        pg.fill("#steps", "1")
        pg.click("#export-path")
        pg.wait_for_function("document.getElementById('status').classList.contains('error')")
        assert "steps" in pg.inner_text("#status")
        pg.fill("#steps", "12")
        pg.click("#export-path")
        pg.wait_for_function("!document.getElementById('path-cmd').hidden")
        assert "--steps 12" in pg.inner_text("#path-cmd")
        assert not pg.evaluate("document.getElementById('status').classList.contains('error')")


@browser_only
def test_switching_the_path_kind_keeps_the_point_at_the_scrubbers_place(
    browser, server, small_manifold_paper
):
    m = Manifold.load(small_manifold_paper)
    on_path = "() => { const e = window.explore; return e.state.x.every((v, k) => v === e.pointOnRoute(0.4)[k]); }"
    with _page(browser, server) as pg:
        pg.select_option("#path-kind", "straight")
        _set(pg, m.latent[m.index("gold-paint")])
        pg.click("#set-a")
        _set(pg, m.latent[m.index("black-obsidian")])
        pg.click("#set-b")
        pg.eval_on_selector(
            "#scrub", "s => { s.value = '400'; s.dispatchEvent(new Event('input')); }"
        )
        assert pg.evaluate(on_path)
        pg.select_option("#path-kind", "uniform")
        assert pg.evaluate(on_path)  # at once on the straight path shown meanwhile
        pg.wait_for_function(
            "document.getElementById('route-state').textContent.startsWith('uniform ·')",
            timeout=60000,
        )
        assert pg.evaluate("window.explore.state.route.kind") == "uniform"
        assert pg.evaluate(on_path)  # then on the uniform one
        pg.select_option("#path-kind", "straight")
        assert pg.evaluate(on_path) and not pg.errors


@browser_only
def test_nothing_is_off_screen_at_800x600(browser, server):
    with _page(browser, server, width=800, height=600) as pg:
        pg.wait_for_timeout(300)
        off = pg.evaluate("""() => {
            const out = [], w = document.documentElement.clientWidth;
            for (const el of document.querySelectorAll('body *')) {
                const r = el.getBoundingClientRect(), s = getComputedStyle(el);
                if (!r.width || s.visibility === 'hidden' || el.closest('.snippet, .gallery, #path-cmd')) continue;
                if (r.right > w + 0.5 || r.left < -0.5) out.push(el.id || el.className || el.tagName);
            }
            return {out, scroll: document.documentElement.scrollWidth, w};
        }""")
        assert off["out"] == [] and off["scroll"] <= off["w"], off
        for sel in (
            "#fav",
            "#compare-add",
            "#status",
            "#undo",
            "#search",
        ):  # the header wrapped, all in view
            box = pg.locator(sel).bounding_box()
            assert box["x"] >= 0 and box["x"] + box["width"] <= 800, (sel, box)


@pytest.fixture(scope="module")
def refine_server(small_basis, small_manifold_paper):
    proc, url = launch.start(
        [small_basis], small_manifold_paper, ["--refine-spp", "8"], refine=True
    )
    yield url
    launch.stop(proc)


@browser_only
def test_refine_turned_off_leaves_no_status_and_stops_refining(
    browser, refine_server, small_manifold_paper
):
    m = Manifold.load(small_manifold_paper)
    with _page(browser, refine_server) as pg:
        _set(pg, m.latent[m.index("chrome")])
        pg.evaluate("() => window.explore.commitPoint()")
        pg.wait_for_function(
            "document.getElementById('refine-status').textContent !== ''", timeout=60000
        )
        pg.uncheck("#refine-auto")
        assert pg.text_content("#refine-status") == ""
        _click(pg, m, "steel")
        pg.wait_for_timeout(1500)  # a refinement would say so within this
        assert (
            pg.text_content("#refine-status") == ""
            and pg.is_hidden("#refine-show")
            and not pg.errors
        )


@browser_only
def test_closing_pages_mid_job_stops_their_jobs_and_the_next_of_each_kind_completes(
    browser, refine_server, small_manifold_paper
):
    """A page with a geodesic, a long reference and a refinement under way is closed (three times);
    its reference and refinement are cancelled; a new page then gets a geodesic, a reference and a
    refinement, and the thumbnails (a server-wide job) still complete."""
    import json
    import urllib.request

    m = Manifold.load(small_manifold_paper)
    mid = 0.5 * (m.latent[m.index("gold-paint")] + m.latent[m.index("blue-acrylic")])
    started = []
    for k in range(3):
        with _page(browser, refine_server) as pg:
            pg.select_option("#path-kind", "geodesic")
            _set(pg, m.latent[k])
            pg.click("#set-a")
            _set(pg, m.latent[k + 4])
            pg.click("#set-b")  # the geodesic computes in the background
            pg.select_option("#ref-spp", "4096")
            pg.click("#ref-start")
            pg.wait_for_function("window.explore.state.referenceJob", timeout=30000)
            started.append(pg.evaluate("window.explore.state.referenceJob"))
            pg.wait_for_timeout(200 * k)

    def status(job):
        with urllib.request.urlopen(f"{refine_server}api/reference/{job}") as r:
            return json.load(r)

    deadline = test_explore.time.monotonic() + 30
    while (
        any(status(j)["state"] in ("queued", "rendering") for j in started)
        and test_explore.time.monotonic() < deadline
    ):
        test_explore.time.sleep(0.2)
    assert [status(j)["state"] for j in started] == ["cancelled"] * 3
    with _page(browser, refine_server) as pg:
        pg.select_option("#path-kind", "geodesic")
        _set(pg, m.latent[m.index("chrome")])
        pg.click("#set-a")
        _set(pg, m.latent[m.index("pink-fabric")])
        pg.click("#set-b")
        pg.wait_for_function(
            "document.getElementById('route-state').textContent.startsWith('geodesic ·')",
            timeout=90000,
        )
        pg.select_option("#ref-spp", "64")
        pg.click("#ref-start")
        pg.wait_for_function("!document.getElementById('ref-result').hidden", timeout=90000)
        assert "PSNR" in pg.inner_text("#ref-metrics")
        _set(pg, mid)
        pg.evaluate("() => window.explore.commitPoint()")
        pg.wait_for_function(
            "document.getElementById('refine-status').textContent.includes('full GI checked')",
            timeout=90000,
        )
        pg.wait_for_function(
            "window.explore.state.info.thumbs === null || window.explore.state.thumbs"
            " || document.getElementById('thumbs-state').textContent.includes('unavailable')",
            timeout=120000,
        )
        assert "unavailable" not in pg.inner_text("#thumbs-state") and not pg.errors


@browser_only
@pytest.mark.parametrize("name", ["chrome", "steel"])
def test_the_preview_sphere_has_no_point_light_speckles(
    browser, server, small_manifold_paper, name
):
    """Lit by the studio environment, a shiny sphere shows smooth reflections: next to no pixel
    stands out from its 5x5 neighbourhood's median (16 point lights made 15-20 pinpoints, 1% of
    the pixels; the sun's mirror image, a small disc, stays under 0.2%)."""
    from scipy.ndimage import median_filter

    m = Manifold.load(small_manifold_paper)
    with _page(browser, server) as pg:
        x = m.latent[m.index(name)]
        pg.evaluate("(x) => window.explore.setX(x)", [float(v) for v in x])
        pg.wait_for_function(
            "(x) => { const p = window.explore.state.previewX; return p && p.every((v, k) => v === x[k]); }",
            arg=[float(v) for v in x],
            timeout=30000,
        )
        pg.wait_for_function(
            "window.explore.preview.envReady && !window.explore.preview.fast && !window.explore.preview.pending"
        )
        pg.wait_for_timeout(1500)
        size, pixels = pg.evaluate("""() => { const s = document.getElementById('sphere');
            const c = document.createElement('canvas'); c.width = s.width; c.height = s.height;
            const g = c.getContext('2d'); g.drawImage(s, 0, 0);
            return [s.width, Array.from(g.getImageData(0, 0, s.width, s.height).data)]; }""")
    img = np.array(pixels, dtype=np.float64).reshape(size, size, 4)[..., :3].mean(-1) / 255
    j, i = np.meshgrid(np.arange(size), np.arange(size))
    r2 = ((j + 0.5) / size * 2 - 1) ** 2 + (1 - (i + 0.5) / size * 2) ** 2
    inside = r2 * 1.08**2 < 0.9
    spikes = np.abs(img - median_filter(img, size=5))[inside] > 0.12
    assert img[inside].max() > 0.3 and spikes.mean() < 2e-3, (
        img[inside].max(),
        spikes.sum(),
    )  # the sun: a small clean disc


#: Every part of the page that follows the point, against the state: the list of the parts that
#: disagree (empty: consistent). The answers of the point (frame, material, snippet) are awaited.
INCONSISTENT = """() => {
  const e = window.explore, s = e.state, x = s.x, key = x.join(","), bad = [];
  const same = (text) => text === key;
  const name = (() => { const i = s.info.latent.findIndex((p) => p.every((v, k) => v === x[k])); return i >= 0 ? s.info.names[i] : ""; })();
  if (!same(document.getElementById('material-name').dataset.x)) bad.push('name');
  if (!s.displayed || !same(s.displayed.x.join(",")) || !same(document.getElementById('scene').dataset.x)) bad.push('frame');
  if (!s.material || !same(s.material.x.join(",")) || document.getElementById('material-panel').classList.contains('stale')) bad.push('material');
  if (!s.snippet || !same(document.getElementById('snippet').dataset.x) || document.getElementById('use-box').classList.contains('stale')) bad.push('snippet');
  if (document.getElementById('search').value !== name) bad.push('search box');
  const n = s.info.names.length, tiles = document.querySelectorAll('#gallery .tile').length;
  if (s.filter) bad.push('filter left over');
  if (tiles !== n || document.getElementById('gallery-count').textContent !== n + ' materials') bad.push('gallery');
  for (const el of document.querySelectorAll('#compare .cmp, #favs .fav'))
    if (el.classList.contains('here') !== same(el.dataset.x)) bad.push('highlight ' + el.className);
  const fav = JSON.parse(localStorage.getItem(Object.keys(localStorage).find((k) => k.includes('favourites')) || 'null') || '[]');
  if ((document.getElementById('fav').textContent[0] === '★') !== fav.some((f) => f.x.join(",") === key)) bad.push('favourite button');
  if (new URLSearchParams(document.getElementById('save-png').search).get('x') !== key) bad.push('save link');
  if (new URLSearchParams(location.hash.slice(1)).get('x') !== key) bad.push('address');
  if (s.errors.length) bad.push('status error: ' + s.errors.map((e) => e.text).join('; '));
  if (e.channel.pending() !== 0) bad.push('answers pending');
  return bad;
}"""


def _consistent(pg, what):
    both = f"() => ({INCONSISTENT})().concat(({DRAWN})())"
    try:
        pg.wait_for_function(f"({both})().length === 0", timeout=30000)
    except Exception:
        raise AssertionError(f"after {what}: {pg.evaluate(both)}") from None


@browser_only
def test_every_part_follows_the_point_through_undo_redo_search_drag_and_scrub(
    browser, server, small_manifold_paper
):
    """One walk through the ways the point changes; after each, every part of the page (name,
    frame, material panel, snippet, search box, gallery, highlights, favourite button, save link,
    address, header status) shows the point the state holds."""
    m = Manifold.load(small_manifold_paper)
    with _page(browser, server) as pg:
        pg.evaluate("localStorage.clear()")
        _click(pg, m, "chrome")
        pg.click("#compare-add")
        pg.click("#set-a")
        _click(pg, m, "steel")
        pg.click("#fav")
        pg.click("#set-b")
        _consistent(pg, "clicks, compare, favourite, path ends")
        pg.fill("#search", "blue-acrylic")  # a full name goes there
        test_explore._wait_displayed(pg, m.latent[m.index("blue-acrylic")])
        _consistent(pg, "search")
        a = _map_position(pg, m.latent[m.index("blue-acrylic")])
        b = _map_position(pg, 0.5 * (m.latent[m.index("chrome")] + m.latent[m.index("steel")]))
        pg.mouse.move(*a)
        pg.mouse.down()
        for k in range(1, 13):  # a drag off the materials
            pg.mouse.move(a[0] + (b[0] - a[0]) * k / 12, a[1] + (b[1] - a[1]) * k / 12 + 7)
        pg.mouse.up()
        dragged = pg.evaluate("window.explore.state.x")
        _consistent(pg, "drag")
        pg.click("#undo")
        test_explore._wait_displayed(pg, m.latent[m.index("blue-acrylic")])
        _consistent(pg, "undo of the drag")
        pg.click("#undo")
        test_explore._wait_displayed(pg, m.latent[m.index("steel")])
        _consistent(pg, "undo of the search")
        pg.click("#redo")
        pg.click("#redo")
        test_explore._wait_displayed(pg, dragged)
        _consistent(pg, "redo twice")
        pg.fill("#search", "paint")  # a partial name filters the gallery ...
        assert pg.evaluate("window.explore.state.filter") == "paint"
        pg.eval_on_selector(
            "#scrub", "s => { s.value = '500'; s.dispatchEvent(new Event('input')); }"
        )
        pg.dispatch_event("#scrub", "change")  # ... until the point moves: along the path
        assert pg.evaluate(
            "() => { const e = window.explore; return e.state.x.every((v, k) => v === e.pointOnRoute(0.5)[k]); }"
        )
        _consistent(pg, "scrub")
        pg.click("#undo")
        test_explore._wait_displayed(pg, dragged)
        _consistent(pg, "undo of the scrub")
        assert not pg.errors


#: The parts kept in the state besides the point, against what the page shows: the favourites and
#: compare lists and their highlights, the favourite button, the refine status, the reference
#: render's controls and the header's error (the list of the parts that disagree).
DRAWN = """() => {
  const s = window.explore.state, $ = (id) => document.getElementById(id), bad = [], key = s.x.join(",");
  const listed = (sel) => [...document.querySelectorAll(sel)].map((e) => e.dataset.x).join(";");
  if (listed('#favs .fav') !== s.favs.map((f) => f.x.join(",")).join(";")) bad.push('favourites');
  if (listed('#compare .cmp') !== s.compare.map((c) => c.x.join(",")).join(";")) bad.push('compare');
  for (const el of document.querySelectorAll('#compare .cmp, #favs .fav'))
    if (el.classList.contains('here') !== (el.dataset.x === key)) bad.push('highlight ' + el.className);
  if (($('fav').textContent[0] === '★') !== s.favs.some((f) => f.x.join(",") === key)) bad.push('favourite button');
  const r = s.refine;
  if ($('refine-status').textContent !== (r ? r.text : '') || $('refine-detail').textContent !== (r ? r.detail : '')
      || $('refine-show').hidden !== !(r && r.offer)) bad.push('refine');
  const ref = s.reference, running = !!ref && ['starting', 'queued', 'rendering'].includes(ref.state);
  if ($('ref-progress').hidden === running || $('ref-cancel').hidden === running || (running && !$('ref-start').disabled)
      || (running && !$('ref-progress').textContent.includes(ref.message))
      || $('ref-note-cancel').hidden !== !(ref && ref.state === 'cancelled')
      || $('ref-result').hidden !== !(ref && ref.state === 'done')) bad.push('reference');
  const err = s.errors[s.errors.length - 1];
  if ($('status').classList.contains('error') !== !!err || (err && $('status').textContent !== err.text)) bad.push('header error');
  return bad;
}"""


@browser_only
def test_lists_refine_status_reference_and_errors_are_drawn_from_the_state(
    browser, server, small_manifold_paper
):
    """Favourites, compare, refine status, reference render and header errors live in the state:
    whatever changes them (a click, a remove, a move, undo, a state update), the page shows the
    state; a move ends another point's refine status, a later success clears its source's error."""
    m = Manifold.load(small_manifold_paper)
    bad = []

    def drawn(what, wait=False):
        if wait:
            try:
                pg.wait_for_function(f"({DRAWN})().length === 0", timeout=10000)
            except Exception:
                pass
        bad.extend(f"{what}: {part}" for part in pg.evaluate(DRAWN))

    with _page(browser, server) as pg:
        pg.evaluate("localStorage.clear()")
        chrome = _click(pg, m, "chrome")
        pg.click("#fav")
        pg.click("#compare-add")
        _click(pg, m, "steel")
        pg.click("#compare-add")
        drawn("favourite and compares added")
        assert pg.evaluate("window.explore.state.compare.length") == 2
        remove = "(sel) => { const b = document.querySelector(sel); if (b) b.click(); return !!b; }"
        steel = [float(v) for v in m.latent[m.index("steel")]]
        pg.evaluate(
            "(x) => window.explore.update({favs: [{x, label: 'steel'}].concat(window.explore.state.favs)})",
            steel,
        )
        drawn("favourites updated")
        if not pg.evaluate(remove, "#favs .fav:nth-child(2) .x"):  # chrome's favourite removed
            bad.append("favourites: no chrome entry to remove")
        assert "chrome" not in pg.evaluate("JSON.stringify(localStorage)") or bad
        drawn("a favourite removed")
        if not pg.evaluate(remove, "#compare .cmp:nth-child(2) .x"):  # steel's compare slot removed
            bad.append("compare: no steel slot to remove")
        drawn("a compare slot removed")
        pg.click("#undo")  # back to chrome: the highlights follow
        test_explore._wait_displayed(pg, chrome)
        drawn("undo")
        pg.evaluate(
            "(x) => window.explore.update({refine: {x, basis: window.explore.state.basis, text: 'refining…',"
            " detail: 'refinement: checked', offer: {show() {}}}})",
            [float(v) for v in chrome],
        )
        drawn("refine status")
        _click(pg, m, "steel")  # a move: the status of chrome goes
        assert pg.evaluate("window.explore.state.refine") is None
        drawn("refine status after a move")
        for ref in (
            "{id: 'j', state: 'rendering', progress: 0.5, message: 'pass 1 of 4'}",
            "{id: 'j', state: 'cancelled', progress: 0.5, message: 'cancelled after 1 pass'}",
        ):
            pg.evaluate(f"window.explore.update({{reference: {ref}}})")
            drawn("reference " + ref)
        pg.select_option("#ref-spp", "4096")  # a real reference, cancelled with the button
        pg.click("#ref-start")
        pg.wait_for_function(
            "['queued', 'rendering'].includes((window.explore.state.reference || {}).state)",
            timeout=30000,
        )
        drawn("reference rendering")
        pg.click("#ref-cancel")
        pg.wait_for_function(
            "(window.explore.state.reference || {}).state === 'cancelled'", timeout=30000
        )
        drawn("reference cancelled")
        assert "cancel" in pg.inner_text("#ref-note-cancel")
        pg.evaluate("window.explore.setStatus('snippet: no answer', true, 'snippet')")
        drawn("header error")
        pg.click("#copy-xml")  # a later success of the snippet clears its error
        pg.wait_for_function("window.explore.state.errors.length === 0", timeout=10000)
        drawn("header error cleared", wait=True)
        assert not pg.errors
    assert bad == [], "; ".join(bad)

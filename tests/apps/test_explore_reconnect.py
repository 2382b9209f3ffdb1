"""The page's state across a server restart, and what it says at a measured material: while the
server is away what is not the point's is dimmed; when it is back the page asks again for its
whole state (no stale error, the sphere and the scene of the point); at a measured material's own
point the page names it, and the refinement says there is nothing to render (no "refining…")."""

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("starlette")
pytestmark = pytest.mark.render

import test_explore  # noqa: E402
import test_explore_browser  # noqa: E402
import test_explore_state  # noqa: E402

from mitsuba_manifold.apps.explore.web import launch  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402

small_basis, browser, refine_server = (
    test_explore.small_basis,
    test_explore_browser.browser,
    test_explore_state.refine_server,
)
browser_only, _page, _set = (
    test_explore.browser_only,
    test_explore_browser._page,
    test_explore_browser._set,
)
SPHERE_READY = (
    "window.explore.state.previewX !== null && window.explore.state.previewX !== undefined"
)


def _classes(pg, selector):
    return pg.evaluate(f"document.querySelector('{selector}').className")


@browser_only
def test_a_restarted_server_gives_back_the_whole_page_and_stale_parts_are_dimmed(
    browser, small_basis, small_manifold_paper
):
    m = Manifold.load(small_manifold_paper)
    proc, url = launch.start([small_basis], small_manifold_paper)
    port = url.rstrip("/").rsplit(":", 1)[1]
    try:
        with _page(browser, url) as pg:
            pg.wait_for_function(SPHERE_READY, timeout=60000)
            first = m.latent[m.index("chrome")]
            _set(pg, first)
            assert "stale" not in _classes(pg, "#scene")
            launch.stop(proc)
            pg.wait_for_function("!window.explore.state.connected", timeout=20000)
            there = m.latent[m.index("gold-paint")]
            pg.evaluate("(x) => window.explore.setX(x)", [float(v) for v in there])
            # the scene and the sphere still show chrome's, under gold-paint's name: dimmed
            assert "stale" in _classes(pg, "#scene") and "stale" in _classes(pg, "#sphere")
            assert "stale" in _classes(pg, "#material-panel")
            pg.click("#ref-start")  # fails while the server is away: an error in the header
            pg.wait_for_function(
                "window.explore.state.errors.some((e) => e.source === 'reference')",
                timeout=20000,
            )
            proc, url2 = launch.start(
                [small_basis], small_manifold_paper, ["--port", port], timeout=300
            )
            assert url2 == url
            pg.wait_for_function("window.explore.state.connected", timeout=60000)
            test_explore._wait_displayed(pg, there)
            pg.wait_for_function(
                "(x) => { const s = window.explore.state; return s.previewX && "
                "s.previewX.every((v, k) => v === x[k]) && s.material && "
                "s.material.x.every((v, k) => v === x[k]); }",
                arg=[float(v) for v in there],
                timeout=60000,
            )
            state = pg.evaluate(
                "({errors: window.explore.state.errors, tables: window.explore.state.info.tables,"
                " status: document.getElementById('status').textContent})"
            )
            assert state["errors"] == [] and state["tables"] == "ready", state
            assert "Failed to fetch" not in state["status"] and "loading" not in state["status"]
            for sel in ("#scene", "#sphere", "#material-panel"):
                assert "stale" not in _classes(pg, sel), sel
            np.testing.assert_array_equal(pg.evaluate("window.explore.state.x"), there)
            # back with other bases: the page's lists are not the server's; it says so and shows
            # none of the new server's answers
            launch.stop(proc)
            pg.wait_for_function("!window.explore.state.connected", timeout=20000)
            proc, _ = launch.start(
                [small_basis, small_basis], small_manifold_paper, ["--port", port], timeout=300
            )
            pg.wait_for_function(
                "document.getElementById('status').textContent.includes('reload the page')",
                timeout=60000,
            )
            seq = pg.evaluate("window.explore.state.displayed.seq")
            pg.evaluate("(x) => window.explore.setX(x)", [float(v) for v in first])
            pg.wait_for_timeout(1500)
            assert pg.evaluate("window.explore.state.displayed.seq") == seq
            assert "stale" in _classes(pg, "#scene")
            assert not pg.errors
    finally:
        if proc.poll() is None:
            launch.stop(proc)


@browser_only
def test_at_a_measured_material_the_page_names_it_and_refine_has_nothing_to_render(
    browser, refine_server, small_manifold_paper
):
    m = Manifold.load(small_manifold_paper)
    with _page(browser, refine_server) as pg:
        pg.wait_for_function(
            "document.getElementById('measured').textContent.includes('is the measured')"
            " || document.getElementById('measured').textContent.includes('close')",
            timeout=60000,
        )  # the perceptual metric is ready
        # the server's answer for a refinement at a training material of a basis with its L2+
        # part (the control variate's correction is 0: nothing to render), as reference.py gives it
        done = {
            "id": "r999",
            "state": "done",
            "progress": 1.0,
            "kind": "refine",
            "message": "exact at a training material: nothing to render",
            "error": {"noise_rel_mse": None, "blend_rel_mse": None, "agrees": None},
            "images": ["blend", "refined"],
        }
        pg.route(
            "**/api/reference",
            lambda route: route.fulfill(json=dict(done, state="queued", message="")),
        )
        pg.route("**/api/reference/r999", lambda route: route.fulfill(json=done))
        x = m.latent[m.index("steel")]
        _set(pg, x)
        pg.evaluate("() => window.explore.commitPoint()")
        pg.wait_for_function(
            "document.getElementById('refine-status').textContent.includes('nothing to render')",
            timeout=60000,
        )
        pg.wait_for_timeout(700)  # the refinement's polls are over: its status stays
        status = pg.text_content("#refine-status")
        assert not status.startswith("refining") and "nothing to render" in status, status
        pg.wait_for_function(
            "(x) => window.explore.state.material && window.explore.state.material.measured && "
            "window.explore.state.material.x.every((v, k) => v === x[k])",
            arg=[float(v) for v in x],
            timeout=30000,
        )
        measured = pg.text_content("#measured")
        assert "is the measured" in measured and "steel" in measured, measured
        assert "very close" not in measured

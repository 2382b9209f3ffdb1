"""The explore benchmark: its upsampled basis, and the drags it times in headless Chromium.

The small basis, the browser and the check for Chromium are the explorer tests' own."""

import os
import sys

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("starlette")
pytestmark = pytest.mark.render

sys.path.insert(
    0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "apps")
)
import test_explore  # noqa: E402
import test_explore_browser  # noqa: E402

from benchmarks.explore import DRIVERS, _drag, _drag_numbers, _rates, upsampled_basis
from benchmarks.explore import browser as bench_browser  # noqa: E402
from mitsuba_manifold.apps.explore.web import launch  # noqa: E402
from mitsuba_manifold.basis.blend import blend  # noqa: E402
from mitsuba_manifold.basis.folder import Basis  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402

small_basis, browser = test_explore.small_basis, test_explore_browser.browser


def test_upsampled_basis_blends_as_the_original(small_basis, small_manifold_paper, tmp_path):
    big = upsampled_basis(small_basis, str(tmp_path / "x2"))
    x = Manifold.load(small_manifold_paper).latent[2]
    small_img, _ = blend(Basis.load(small_basis), small_manifold_paper, x=x)
    big_img, _ = blend(Basis.load(big), small_manifold_paper, x=x)
    np.testing.assert_array_equal(big_img, small_img.repeat(2, 0).repeat(2, 1))


@test_explore.browser_only
def test_browser_benchmark_measures_drags(browser, small_basis, small_manifold_paper):
    r = bench_browser(small_basis, small_manifold_paper, drags=2, moves=8, chromium=browser)
    ref = r["with_reference"]  # the 4096-spp render of this 32x32 basis may end before the drags do
    assert (
        (
            ref["cancel_s"] is None
            and ref["reference_progress_at_cancel"] == 1.0
            or ref["cancel_s"] < 10
        )
        and ref["moves"] >= 8
        and ref["images"] > 0
    )
    # the page's moves went where a real mouse's go (the map, holding the press's capture)
    assert r["driver"] == "page" and all(
        d["captured"] and d["targets"] == {"map": d["delivered"]} for d in r["delivery"]
    )
    assert r["moves"] == sum(d["delivered"] for d in r["delivery"]) >= 2
    assert 0 < r["images"] <= r["moves"]
    assert (
        0
        < r["move_to_frame_ms"]["median"]
        <= r["move_to_frame_ms"]["p90"]
        <= r["move_to_frame_ms"]["max"]
    )
    assert (
        r["images_per_s"] > 0
        and r["pointer_moves_per_s"] > 0
        and r["tables_ready_s"] > 0
        and set(r["meets_targets"])
        == {"median", "p90", "images_per_s", "tables_ready", "rate_with_reference"}
    )


@test_explore.browser_only
def test_both_drivers_drag_the_point_the_same_way(browser, small_basis, small_manifold_paper):
    """A drag of the page driver's dispatched moves ends where the same drag of Playwright's
    trusted moves does, each move handled by the map's own handlers (snapping, the point, its
    frame), with the press's pointer capture held."""
    proc, url = launch.start([small_basis], small_manifold_paper, ["--no-thumbnails"])
    try:
        page = browser.new_page(viewport={"width": 1500, "height": 1000})
        page.goto(url)
        page.wait_for_function(test_explore_browser.READY, timeout=60000)
        box = page.locator("#map").bounding_box()
        ends, got = [], {}
        for fa, fb in ((0.3, 0.6), (0.7, 0.35)):  # one end off the materials, one near one
            ends.append((box["x"] + fa * box["width"], box["y"] + fb * box["height"]))
        for driver in DRIVERS:
            got[driver] = [_drag(page, ends[0], ends[1], 6, 20.0, driver)]
            got[driver].append(page.evaluate("window.explore.state.x"))
            got[driver].append(page.evaluate("window.__moves.map((m) => m.x)"))
        pixel = page.evaluate("""() => { const e = window.explore.state.map.extent;
            return (e[1] - e[0]) / document.getElementById("map").getBoundingClientRect().width; }""")
        page.close()
    finally:
        launch.stop(proc)
    (p, xp, mp), (w, xw, mw) = got["page"], got["playwright"]
    d = p["delivery"]  # a busy page may have had some of the page driver's moves coalesced
    assert (
        w["moves"] == 6 and p["moves"] == d["delivered"] == len(d["steps"]) and d["steps"][-1] == 6
    )
    assert p["images"] >= 1 and w["images"] >= 1
    assert d["captured"] and d["targets"] == {"map": d["delivered"]}
    # the same points, move by move (to a tenth of a pixel: trusted moves' coordinates are rounded)
    np.testing.assert_allclose(xp, xw, rtol=0, atol=0.1 * pixel)
    np.testing.assert_allclose(mp, [mw[k - 1] for k in d["steps"]], rtol=0, atol=0.1 * pixel)


def test_images_per_second_counts_each_point_once_up_to_its_last_image():
    """Frames of points no move of the drag set (the press's, an earlier drag's) and a point's
    frame drawn again (its rest frame) are not images of the drag; the time runs from the first
    move to the last image drawn, not to the last move."""
    moves = [{"t": 100.0 + 20 * k, "x": [k, 0.0]} for k in range(4)]
    frames = [
        {"x": [9.0, 9.0], "at": 90.0},  # before the drag
        {"x": [9.0, 9.0], "at": 105.0},  # the press's point
        {"x": [0.0, 0.0], "at": 115.0},
        {"x": [2.0, 0.0], "at": 160.0},
        {"x": [3.0, 0.0], "at": 200.0},
        {"x": [3.0, 0.0], "at": 400.0},  # the rest frame of the last point
    ]
    got = _drag_numbers({"moves": moves, "frames": frames, "draws": 0})
    assert got["images"] == 3 and got["image_span_s"] == pytest.approx(0.1)
    assert got["move_span_s"] == pytest.approx(0.06)
    assert got["latencies"] == pytest.approx([15.0, 40.0, 20.0, 40.0])
    r = _rates({**got, "delivery": [None]})
    assert r["images_per_s"] == pytest.approx(30.0)
    assert r["pointer_moves_per_s"] == pytest.approx(50.0)

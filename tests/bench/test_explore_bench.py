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

from benchmarks.explore import browser as bench_browser  # noqa: E402
from benchmarks.explore import upsampled_basis
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
        and ref["moves"] >= 16
        and ref["frames_drawn"] > 0
    )
    assert r["moves"] >= 16 and 0 < r["frames_drawn"] <= r["moves"] + 2
    assert (
        0
        < r["move_to_frame_ms"]["median"]
        <= r["move_to_frame_ms"]["p90"]
        <= r["move_to_frame_ms"]["max"]
    )
    assert (
        r["moves_per_s"] > 0
        and r["tables_ready_s"] > 0
        and set(r["meets_targets"])
        == {"median", "p90", "moves_per_s", "tables_ready", "rate_with_reference"}
    )

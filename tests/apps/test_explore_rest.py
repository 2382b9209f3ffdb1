"""The frame where a drag rests: denoised only where that changes the 8-bit image shown; else the
drag's own frame, with no denoiser run (it cost a second or more of the server's CPU per rest)."""

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
pytest.importorskip("pyoidn")  # the rest frame denoises (a GPU machine may lack OIDN)
pytestmark = pytest.mark.render

import mitsuba_manifold  # noqa: E402
from mitsuba_manifold.apps.explore import Explorer, fireflies  # noqa: E402
from mitsuba_manifold.basis import blend as blend_module  # noqa: E402
from mitsuba_manifold.basis.composition import compose  # noqa: E402
from mitsuba_manifold.render.jobs import render_basis  # noqa: E402


@pytest.fixture(scope="module")
def gi_explorer(small_manifold, tmp_path_factory):
    """An explorer of a full-GI basis of the table (L1- and L2+ parts), 24x24 at 4 spp: noisy."""
    mi.set_variant("llvm_ad_rgb")
    mitsuba_manifold.register()
    out = tmp_path_factory.mktemp("rest") / "basis"
    render_basis.render_basis(
        "table", small_manifold, out, spp=4, mode="onepass", components="full", resolution=24
    )
    ex = Explorer([str(out)], manifold=small_manifold, load_tables=False)
    yield ex
    ex.close()


def _pixels(data):
    return np.frombuffer(data, np.uint8)


def test_a_rest_frame_is_denoised_only_where_that_shows(gi_explorer, monkeypatch):
    ex = gi_explorer
    m = ex.manifold
    x = 0.5 * (m.latent[0] + m.latent[3])
    raw, info = ex.blend(None, x, "raw")
    assert info.l2 == "raw"
    l1, _, _ = compose(ex.basis(None), info.plan.keys, info.plan.image_weights, None)
    change = fireflies.rest_change(raw, l1, 0.0)
    drag, _ = ex.frame(None, x, 0.0, "rgba", coarse=True)
    exact, _ = ex.frame(None, x, 0.0, "rgba")  # the HTTP frame (save PNG): always denoised
    data, meta = ex.frame(None, x, 0.0, "rgba", rest=True)
    assert meta["rest"]["change"] == pytest.approx(change)
    assert meta["rest"]["denoised"] == (change > fireflies.REST_FRACTION)
    np.testing.assert_array_equal(
        _pixels(data), _pixels(exact if meta["rest"]["denoised"] else drag)
    )

    def no_denoiser(*args, **kwargs):
        raise AssertionError("the denoiser ran for a rest frame whose change does not show")

    monkeypatch.setattr(fireflies, "REST_FRACTION", 1.0)  # nothing would show: the drag's frame
    monkeypatch.setattr(blend_module, "denoised_l2", no_denoiser)
    y = 0.3 * m.latent[1] + 0.7 * m.latent[4]
    drag_y, _ = ex.frame(None, y, 1.0, "rgba", coarse=True)
    data, meta = ex.frame(None, y, 1.0, "rgba", rest=True)
    assert meta["rest"]["denoised"] is False and meta["l2"] == "raw"
    np.testing.assert_array_equal(_pixels(data), _pixels(drag_y))
    monkeypatch.undo()
    monkeypatch.setattr(fireflies, "REST_FRACTION", -1.0)  # everything shows: denoised
    data, meta = ex.frame(None, y, 1.0, "rgba", rest=True)
    exact_y, _ = ex.frame(None, y, 1.0, "rgba")
    assert meta["rest"]["denoised"] is True and meta["l2"] == "denoised"
    np.testing.assert_array_equal(_pixels(data), _pixels(exact_y))

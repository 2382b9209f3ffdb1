"""Acquisition from photos of the sphere scene: a known combination comes back, bad input is one
line, and match.py --render keeps its JSON keys."""

import json

import numpy as np
import pytest

from mitsuba_manifold.apps.cli import match as cli
from mitsuba_manifold.basis.inverse.acquisition import AcquireOptions
from mitsuba_manifold.errors import InputError
from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.render.inverse.acquire import Photo, acquire, render_weights
from mitsuba_manifold.render.scene import scenes

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]

RES = 16


def _photo(manifold_path, w, spp=256, seed=5):
    return render_weights(scenes.scene_path("sphere"), manifold_path, w, (RES, RES), spp, seed)


def _rel(a, b, mask):
    a, b = a[mask > 0], b[mask > 0]
    return float(np.sqrt(np.mean((a - b) ** 2 / (b * b + 0.01))))


def test_a_known_combination_is_acquired(small_manifold, tmp_path):
    """A photo of 0.6 gold-paint + 0.4 blue-acrylic: the acquired material's render is closer to
    it than the best single material's, its weights put most mass on the two, and a second photo
    of the same scene reuses the training images (basis_cache)."""
    m = Manifold.load(small_manifold)
    w_true = np.zeros(m.n)
    w_true[m.index("gold-paint")], w_true[m.index("blue-acrylic")] = 0.6, 0.4
    photo = _photo(small_manifold, w_true)
    opts = AcquireOptions(
        spp=64, bootstrap=2, render_spp=64, progress=False, basis_cache=str(tmp_path / "c")
    )
    got = acquire([Photo("sphere", photo)], small_manifold, opts)
    r = got.result
    mask = got.masks[0]
    assert _rel(got.renders[0], photo, mask) < _rel(got.singles[0], photo, mask)
    assert r.error < r.single["error"]
    assert r.weights["gold-paint"] > 0.2 and r.weights["blue-acrylic"] > 0.1
    assert r.coverage["views"][0]["pixels"] > 0 and r.spread["solutions"] == 3
    again = acquire([Photo("sphere", photo)], small_manifold, opts)
    assert again.result.views[0]["cached_training_images"]
    np.testing.assert_allclose(again.result.w, r.w, atol=1e-9)
    np.testing.assert_allclose(got.photos[0], photo, rtol=1e-6)  # the image matched, as read
    with pytest.warns(DeprecationWarning, match=r"AcquireOutput.targets is now spelled"):
        assert got.targets is got.photos


def test_bad_input_is_one_line(small_manifold, tmp_path):
    photo = np.full((RES, RES, 3), 0.2)
    with pytest.raises(InputError, match="no such file"):
        acquire([Photo("sphere", str(tmp_path / "missing.exr"))], small_manifold)
    with pytest.raises(InputError, match="must have the same size"):
        acquire([Photo("sphere", photo, mask=np.ones((RES + 1, RES)))], small_manifold)
    with pytest.raises(InputError, match="RGB image"):
        acquire([Photo("sphere", np.ones((RES, RES)))], small_manifold)
    with pytest.raises(InputError, match="`method`"):
        acquire([Photo("sphere", photo)], small_manifold, AcquireOptions(method="magic"))


def test_match_render_tool_acquires_by_default(small_manifold, tmp_path, capsys):
    """tools/match.py --render: the acquisition is the default; the JSON keeps `weights` (every
    material's name) and `single` (`name`); the render, the contact sheet and the snippet are
    written; a wrong-size mask is one error line."""
    m = Manifold.load(small_manifold)
    w_true = np.zeros(m.n)
    w_true[m.index("gold-paint")] = 1.0
    tpath = str(tmp_path / "t.exr")
    imageio.write_exr(tpath, _photo(small_manifold, w_true, spp=64))
    out, js = str(tmp_path / "o.exr"), str(tmp_path / "j.json")
    snippet = str(tmp_path / "m.xml")
    args = ["--render", "--manifold", small_manifold, "--scene", "sphere", "--image", tpath]
    assert (
        cli.main(
            args
            + ["--out", out, "--json", js, "--snippet", snippet, "--spp", "32", "--bootstrap", "0"]
            + ["--no-progress"]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "best single training material" in text and "outgoing elevation" in text
    got = json.load(open(js))
    assert set(got["weights"]) == set(m.names) and got["single"]["name"] in m.names
    assert imageio.read_exr(out).shape == (RES, RES, 3)
    assert (tmp_path / "o_sheet.png").stat().st_size > 0
    assert 'type="manifold_brdf"' in open(snippet).read()
    mpath = str(tmp_path / "mask.exr")
    imageio.write_exr(mpath, np.ones((RES + 2, RES, 3), dtype=np.float32))
    with pytest.raises(SystemExit):
        cli.main(args + ["--mask", mpath, "--no-progress"])
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "mask" in err


def test_training_images_given_are_used(small_manifold):
    """A caller with the scene's training images (a basis) passes them: the same weights, nothing
    rendered for them."""
    from mitsuba_manifold.render.inverse.acquire import render_training_images

    m = Manifold.load(small_manifold)
    w_true = np.zeros(m.n)
    w_true[m.index("gold-paint")] = 1.0
    photo = _photo(small_manifold, w_true, spp=64)
    opts = AcquireOptions(spp=32, bootstrap=0, render_spp=0, progress=False)
    own = acquire([Photo("sphere", photo)], small_manifold, opts)
    tr = render_training_images(scenes.scene_path("sphere"), small_manifold, (RES, RES), opts)
    given = acquire([Photo("sphere", photo)], small_manifold, opts, training_images=[tr])
    # two renders with the same seed agree to float rounding only (the one-pass integrator's
    # splats are summed by threads in no fixed order): the weights to 1e-6, far below any change
    np.testing.assert_allclose(given.result.w, own.result.w, rtol=0, atol=1e-6)
    assert given.renders == [] and given.result.views[0]["cached_training_images"]

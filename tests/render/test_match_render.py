"""match on a rendered basis: a target rendered with Mitsuba's path, and the tool's full-GI render of the result."""

import json
import os

import pytest

from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.render import render_basis, scenes
from mitsuba_manifold.basis import match as mt
from mitsuba_manifold.basis.folder import Basis
from mitsuba_manifold.basis.blend import blend
from mitsuba_manifold.apps.cli import match as cli
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.imaging.metrics import rel_mse

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]

RES = 24


def test_match_of_a_path_render_and_the_tools_reference(tmp_path, small_manifold, capsys):
    sphere = scenes.scene_path("sphere")
    m = Manifold.load(small_manifold)
    out = str(tmp_path / "basis")
    render_basis.render_basis(sphere, small_manifold, out, spp=64, resolution=RES, mode="onepass")
    b = Basis.load(out, manifold=m)
    x_true = 0.6 * m.latent[m.index("gold-paint")] + 0.4 * m.latent[m.index("blue-acrylic")]
    target = scenes.render_reference(sphere, small_manifold, x_true, 256, seed=3, resolution=RES)
    r = mt.match(b, target, manifold=m)
    own = rel_mse(blend(b, m, x=x_true, prune=0.0)[0], target)
    assert r.rel_mse <= 1.5 * own  # the accuracy criterion
    assert r.rel_mse < r.single.error

    tpath = str(tmp_path / "target.exr")
    imageio.write_exr(tpath, target)
    best, js = str(tmp_path / "best.exr"), str(tmp_path / "best.json")
    assert cli.main(["--basis", out, "--target", tpath, "--out", best, "--render-reference", "--spp", "64",
                     "--json", js]) == 0
    assert "wrote full-GI render of the best point" in capsys.readouterr().out
    ref = imageio.read_exr(str(tmp_path / "best_reference.exr"))
    got = json.load(open(js))
    assert ref.shape == (RES, RES, 3) and got["reference"].endswith("best_reference.exr")
    # the sphere has no L2+: the render of the point and its blend agree up to noise
    assert abs(ref.mean() - imageio.read_exr(best).mean()) < 0.05 * ref.mean()
    assert os.path.isfile(best)

"""match on a rendered basis: a target rendered with Mitsuba's path, and the tool's full-GI render of the result."""

import json
import os

import numpy as np

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

    # the differentiable match starts from the basis match too
    from mitsuba_manifold.render import match_render as mr
    opts = mr.MatchRenderOptions(iterations=2, spp=2, eval_spp=16, starts=1, max_depth=2, progress=False)
    rr = mr.match_render([mr.View(sphere, target)], small_manifold, opts, basis=out)
    assert [s["start"] for s in rr.starts][:2] == ["basis match"] * 2
    assert rr.starts[0]["iterate"] == "start" and np.allclose(rr.starts[0]["x"], r.x)


def test_match_render_converges_without_a_basis(tmp_path, small_manifold):
    """The differentiable x (no basis): a target rendered with path at a point between materials is
    matched to within 1.5x the noise floor of its own point, better than the best training material."""
    from mitsuba_manifold.render import match_render as mr

    sphere = scenes.scene_path("sphere")
    m = Manifold.load(small_manifold)
    x_true = 0.5 * m.latent[m.index("gold-paint")] + 0.5 * m.latent[m.index("blue-acrylic")]
    target = scenes.render_reference(sphere, small_manifold, x_true, 256, seed=3, resolution=16, max_depth=3)
    opts = mr.MatchRenderOptions(iterations=12, spp=4, eval_spp=64, starts=2, max_depth=3, progress=False,
                                 plot=str(tmp_path / "convergence.png"))
    r = mr.match_render([mr.View(sphere, target)], small_manifold, opts)
    problem = mr._Problem([mr.View(sphere, target)], small_manifold, opts)
    floor = problem.evaluate(x_true, 1.0, opts.eval_spp, opts.seed + 55)[0]
    assert r.error <= 1.5 * floor
    assert r.error < r.single["error"]
    assert os.path.getsize(r.plot) > 0 and len(r.history) == 2 and len(r.history[0]) == 12
    # every start's own point is a candidate, as are its iterates and 3 single materials; the best is the result
    assert [s["iterate"] for s in r.starts].count("start") == 2 and r.extra["scan"]["candidates"]
    assert sum(s["iterate"] == "none" for s in r.starts) == 3
    assert min(s["error"] for s in r.starts) == pytest.approx(float(np.mean(r.errors)), rel=1e-5)
    assert r.w.sum() == pytest.approx(1.0) and r.images[0].shape == (16, 16, 3)
    json.dumps(r.to_dict(m))


def test_match_render_tool(tmp_path, small_manifold, capsys):
    """tools/match.py --render: the point, weights and image error printed; the render, the plot and the
    JSON written; option names in its errors."""
    sphere = scenes.scene_path("sphere")
    m = Manifold.load(small_manifold)
    target = scenes.render_reference(sphere, small_manifold, m.latent[m.index("gold-paint")], 64, seed=3,
                                     resolution=12, max_depth=2)
    tpath = str(tmp_path / "target.exr")
    imageio.write_exr(tpath, target)
    best, js, png = str(tmp_path / "best.exr"), str(tmp_path / "m.json"), str(tmp_path / "conv.png")
    common = ["--render", "--manifold", small_manifold, "--scene", sphere, "--target", tpath, "--max-depth", "2",
              "--no-progress"]
    assert cli.main(common + ["--iterations", "3", "--spp", "2", "--eval-spp", "8", "--starts", "1",
                              "--out", best, "--json", js, "--plot", png]) == 0
    out = capsys.readouterr().out
    assert "largest weights:" in out and "image error: relative MSE" in out and "not identifiable" in out
    got = json.load(open(js))
    assert len(got["x"]) == m.q and abs(sum(got["weights"].values()) - 1) < 1e-6 and got["renders"] == [best]
    assert imageio.read_exr(best).shape == (12, 12, 3) and os.path.getsize(png) > 0
    with pytest.raises(SystemExit):
        cli.main(common + ["--iterations", "0"])
    assert "--iterations must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(common + ["--scan-spp", "0"])
    assert "--scan-spp must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(common + ["--target", tpath, "--mask", tpath])
    assert "--mask is given 1 times for 2 targets" in capsys.readouterr().err


def test_match_render_fits_an_exposure(small_manifold):
    """exposure=True: a target 2.5x brighter than a training material's render is matched with a
    fitted scale near 2.5 (least squares at every step), and the images returned are scaled."""
    from mitsuba_manifold.render import match_render as mr

    sphere = scenes.scene_path("sphere")
    m = Manifold.load(small_manifold)
    target = 2.5 * scenes.render_reference(sphere, small_manifold, m.latent[m.index("gold-paint")], 128, seed=3,
                                           resolution=12, max_depth=2)
    opts = mr.MatchRenderOptions(iterations=3, spp=4, eval_spp=64, starts=1, max_depth=2, progress=False,
                                 exposure=True)
    r = mr.match_render([mr.View(sphere, target)], small_manifold, opts)
    assert r.exposure == pytest.approx(2.5, rel=0.15)
    assert np.mean(r.images[0]) == pytest.approx(np.mean(target), rel=0.15)

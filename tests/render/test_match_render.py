"""match on a rendered basis: a target rendered with Mitsuba's path, and the tool's full-GI render of the result."""

import json
import os

import numpy as np
import pytest

from mitsuba_manifold.apps.cli import match as cli
from mitsuba_manifold.basis.blend import blend
from mitsuba_manifold.basis.folder import Basis
from mitsuba_manifold.basis.inverse import match as mt
from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.imaging.metrics import rel_mse
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.render.jobs import render_basis
from mitsuba_manifold.render.scene import scenes

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
    assert (
        cli.main(
            [
                "--basis",
                out,
                "--image",
                tpath,
                "--out",
                best,
                "--render-reference",
                "--spp",
                "64",
                "--json",
                js,
            ]
        )
        == 0
    )
    assert "wrote full-GI render of the best point" in capsys.readouterr().out
    ref = imageio.read_exr(str(tmp_path / "best_reference.exr"))
    got = json.load(open(js))
    assert ref.shape == (RES, RES, 3) and got["reference"].endswith("best_reference.exr")
    # the sphere has no L2+: the render of the point and its blend agree up to noise
    assert abs(ref.mean() - imageio.read_exr(best).mean()) < 0.05 * ref.mean()
    assert os.path.isfile(best)

    # the differentiable match starts from the basis match too
    from mitsuba_manifold.render.inverse import match_render as mr

    opts = mr.MatchRenderOptions(
        iterations=2, spp=2, eval_spp=16, starts=1, max_depth=2, progress=False
    )
    rr = mr.match_render([mr.View(sphere, target)], small_manifold, opts, basis=out)
    assert [s["start"] for s in rr.starts][:2] == ["basis match"] * 2
    assert rr.starts[0]["iterate"] == "start" and np.allclose(rr.starts[0]["x"], r.x)


def test_match_render_converges_without_a_basis(tmp_path, small_manifold):
    """The differentiable x (no basis): a target rendered with path at a point between materials is
    matched to within 1.5x the noise floor of its own point, better than the best training material."""
    from mitsuba_manifold.render.inverse import match_render as mr

    sphere = scenes.scene_path("sphere")
    m = Manifold.load(small_manifold)
    x_true = 0.5 * m.latent[m.index("gold-paint")] + 0.5 * m.latent[m.index("blue-acrylic")]
    target = scenes.render_reference(
        sphere, small_manifold, x_true, 256, seed=3, resolution=16, max_depth=3
    )
    opts = mr.MatchRenderOptions(
        iterations=12,
        spp=4,
        eval_spp=64,
        starts=2,
        max_depth=3,
        progress=False,
        plot=str(tmp_path / "convergence.png"),
    )
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
    target = scenes.render_reference(
        sphere,
        small_manifold,
        m.latent[m.index("gold-paint")],
        64,
        seed=3,
        resolution=12,
        max_depth=2,
    )
    tpath = str(tmp_path / "target.exr")
    imageio.write_exr(tpath, target)
    best, js, png = str(tmp_path / "best.exr"), str(tmp_path / "m.json"), str(tmp_path / "conv.png")
    common = [
        "--render",
        "--method",
        "latent",
        "--manifold",
        small_manifold,
        "--scene",
        sphere,
        "--image",
        tpath,
        "--max-depth",
        "2",
        "--no-progress",
    ]
    assert (
        cli.main(
            common
            + [
                "--iterations",
                "3",
                "--spp",
                "2",
                "--eval-spp",
                "8",
                "--starts",
                "1",
                "--out",
                best,
                "--json",
                js,
                "--plot",
                png,
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert (
        "largest weights:" in out
        and "image error: relative MSE" in out
        and "not identifiable" in out
    )
    got = json.load(open(js))
    assert (
        len(got["x"]) == m.q
        and abs(sum(got["weights"].values()) - 1) < 1e-6
        and got["renders"] == [best]
    )
    assert imageio.read_exr(best).shape == (12, 12, 3) and os.path.getsize(png) > 0
    with pytest.raises(SystemExit):
        cli.main(common + ["--iterations", "0"])
    assert "--iterations must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(common + ["--scan-spp", "0"])
    assert "--scan-spp must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(common + ["--image", tpath, "--mask", tpath])
    assert "--mask is given 1 times for 2 images to match" in capsys.readouterr().err


def test_match_render_fits_an_exposure(small_manifold):
    """exposure=True: a target 2.5x brighter than a training material's render is matched with a
    fitted scale near 2.5 (least squares at every step), and the images returned are scaled."""
    from mitsuba_manifold.render.inverse import match_render as mr

    sphere = scenes.scene_path("sphere")
    m = Manifold.load(small_manifold)
    target = 2.5 * scenes.render_reference(
        sphere,
        small_manifold,
        m.latent[m.index("gold-paint")],
        128,
        seed=3,
        resolution=12,
        max_depth=2,
    )
    opts = mr.MatchRenderOptions(
        iterations=3, spp=4, eval_spp=64, starts=1, max_depth=2, progress=False, exposure=True
    )
    r = mr.match_render([mr.View(sphere, target)], small_manifold, opts)
    assert r.exposure == pytest.approx(2.5, rel=0.15)
    assert np.mean(r.images[0]) == pytest.approx(np.mean(target), rel=0.15)


def _no_render(monkeypatch):
    """Loading a scene (the first work of a match) fails the test: bad input is refused before it."""

    def refuse(*args, **kwargs):
        raise AssertionError("a scene was loaded before the input was checked")

    monkeypatch.setattr(scenes, "load_scene", refuse)


@pytest.mark.parametrize(
    "bad, option, says",
    [
        (["--sensor", "5"], "--sensor", "has 1 sensor(s)"),
        (["--sensor", "-1"], "--sensor", "from 0 to 0"),
        (
            ["--integrator", "nosuch"],
            "--integrator",
            "prb, prb_basic, prbvolpath, direct_projective",
        ),
        (["--lr", "-1"], "--lr", "finite number > 0"),
        (["--lr", "nan"], "--lr", "finite number > 0"),
        (["--lr", "inf"], "--lr", "finite number > 0"),
        (["--seed", "-1"], "--seed", "integer >= 0"),
        (["--scene", "nosuch"], "--scene 'nosuch'", "no such file nor shipped scene"),
    ],
)
def test_match_render_tool_refuses_bad_settings_before_any_work(
    tmp_path, small_manifold, capsys, monkeypatch, bad, option, says
):
    """tools/match.py --render: a bad --sensor, --integrator, --lr, --seed or --scene ends as one
    ``error:`` line naming the option (exit 2), before any scene is loaded or any output is made."""
    tpath = str(tmp_path / "target.exr")
    imageio.write_exr(tpath, np.full((8, 8, 3), 0.5, dtype=np.float32))
    _no_render(monkeypatch)
    out = tmp_path / "out"
    args = [
        "--render",
        "--method",
        "latent",
        "--manifold",
        small_manifold,
        "--image",
        tpath,
        "--no-progress",
        "--out",
        str(out / "best.exr"),
        "--json",
        str(out / "m.json"),
        "--plot",
        str(out / "conv.png"),
    ]
    with pytest.raises(SystemExit) as e:
        cli.main(
            args + ([] if "--scene" in bad else ["--scene", scenes.scene_path("sphere")]) + bad
        )
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and err.startswith("error: ")
    assert option in err and says in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize(
    "change, param",
    [
        ({"sensor": 1}, "`sensor`"),
        ({"sensor": -1}, "`sensor`"),
        ({"integrator": "nosuch"}, "`integrator`"),
        ({"lr": 0.0}, "`lr`"),
        ({"lr": float("nan")}, "`lr`"),
        ({"seed": -1}, "`seed`"),
        ({"seed": 1.5}, "`seed`"),
        ({"scene": "nosuch"}, "`scene`"),
    ],
)
def test_match_render_refuses_bad_parameters(small_manifold, monkeypatch, change, param):
    """The library names the Python parameter of a bad view or option (InputError), before any work."""
    from mitsuba_manifold.errors import InputError
    from mitsuba_manifold.render.inverse import match_render as mr

    _no_render(monkeypatch)
    view = mr.View(
        change.get("scene", scenes.scene_path("sphere")),
        np.full((8, 8, 3), 0.5),
        sensor=change.get("sensor", 0),
    )
    opts = mr.MatchRenderOptions(
        progress=False, **{k: v for k, v in change.items() if k not in ("scene", "sensor")}
    )
    with pytest.raises(InputError, match=param):
        mr.match_render([view], small_manifold, opts)


def test_match_render_tool_takes_a_shipped_scene_name(tmp_path, small_manifold, capsys):
    """--scene sphere (a shipped scene's name, as render_basis.py and blend.py take) matches that scene."""
    x = Manifold.load(small_manifold).latent[0]
    target = scenes.render_reference(
        scenes.scene_path("sphere"), small_manifold, x, 16, seed=3, resolution=8, max_depth=1
    )
    tpath, js = str(tmp_path / "target.exr"), str(tmp_path / "m.json")
    imageio.write_exr(tpath, target)
    assert (
        cli.main(
            [
                "--render",
                "--method",
                "latent",
                "--manifold",
                small_manifold,
                "--scene",
                "sphere",
                "--image",
                tpath,
                "--max-depth",
                "1",
                "--iterations",
                "1",
                "--spp",
                "1",
                "--eval-spp",
                "2",
                "--scan-spp",
                "2",
                "--starts",
                "1",
                "--no-progress",
                "--json",
                js,
            ]
        )
        == 0
    )
    assert "image error: relative MSE" in capsys.readouterr().out
    assert json.load(open(js))["views"][0]["scene"] == scenes.scene_path("sphere")


def test_a_view_and_a_photo_take_the_image_to_match_by_its_former_name_target():
    from mitsuba_manifold.render.inverse import match_render as mr
    from mitsuba_manifold.render.inverse.acquire import Photo

    image = np.zeros((2, 3, 3))
    for cls in (mr.View, Photo):
        with pytest.warns(
            DeprecationWarning, match=rf"{cls.__name__}\(target=...\) is now spelled"
        ):
            old = cls("sphere", target=image, sensor=1)
        assert old == cls("sphere", image, sensor=1) and old.image is image
        with pytest.warns(DeprecationWarning, match=rf"{cls.__name__}.target is now spelled"):
            assert old.target is image
        with pytest.raises(TypeError, match="give `image` only"):
            cls("sphere", image, target=image)

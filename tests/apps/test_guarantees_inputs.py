"""Nothing silently wrong (issue 10): inputs that cannot make an image, unusable variants,
impossible sizes and latent dimensions are refused in one line naming the option, before
anything is written; the plugin keeps its state when an update is refused.

Tools run in-process through their ``main(argv)`` (:mod:`guarantees_helpers`). Fixtures:
``tests/apps/conftest.py``.
"""

import os

import numpy as np
import pytest
from guarantees_helpers import assert_one_error, run_render_basis, run_tool, snapshot

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("plugins")]
mi = pytest.importorskip("mitsuba")
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402

# ------------------------------------------------------------ 4. / 9. blend inputs


@pytest.mark.parametrize("exposure", ["nan", "inf", "-inf", "1e10", "-1e10"])
def test_blend_refuses_exposures_that_cannot_make_an_image(tmp_path, tiny, exposure):
    before = snapshot(tmp_path)
    rc, _, err = run_tool(
        "blend",
        "--basis",
        tiny["basis"],
        "--x",
        "0,0",
        "--out",
        tmp_path / "img.exr",
        "--png",
        f"--exposure={exposure}",
    )
    assert_one_error(rc, err, "--exposure")
    assert snapshot(tmp_path) == before


# ---------------------------------------------------- 9. tracebacks -> messages


def test_fit_manifold_plot_into_a_file_is_refused_before_fitting(tmp_path, tiny):
    (tmp_path / "plots").write_text("a file")
    before = snapshot(tmp_path)
    for plot in (tmp_path / "plots", tmp_path / "plots" / "sub"):
        rc, _, err = run_tool(
            "fit_manifold", tiny["db"], "--out", tmp_path / "m.npz", "--plot", plot
        )
        assert_one_error(rc, err, "--plot")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize(
    "variant, words",
    [
        ("bogus", ["--variant", "bogus"]),
        ("scalar_rgb", ["--variant", "scalar_rgb"]),
        ("llvm_ad_spectral_polarized", ["--variant"]),
    ],
)
def test_render_basis_refuses_unusable_variants_and_leaves_nothing(tmp_path, tiny, variant, words):
    out = tmp_path / "basis"
    rc, _, err = run_render_basis(tiny["manifold"], out, "--variant", variant)
    assert_one_error(rc, err, *words)
    assert not out.exists() or not [f for f in os.listdir(out) if not f.startswith(".")]
    rc, _, err = run_render_basis(
        tiny["manifold"], out, "--materials", "steel", "--variant", "llvm_ad_rgb"
    )
    assert rc == 0, err  # the corrected rerun is accepted


def test_make_database_refuses_impossible_resolutions_before_writing(tmp_path):
    out = tmp_path / "db"
    for res in ("100000,100000,100000", "4096,4096,4096", "0,8,16", "8,8"):
        rc, _, err = run_tool(
            "make_database", "--out", out, "--resolution", res, "--materials", "steel"
        )
        assert_one_error(rc, err, "--resolution")
        assert not out.exists() or not os.listdir(out)
    rc, _, err = run_tool(
        "make_database", "--out", out, "--resolution", "8,8,16", "--materials", "steel"
    )
    assert rc == 0, err


def test_make_database_refuses_a_negative_seed_before_writing(tmp_path):
    out = tmp_path / "noisy"
    rc, _, err = run_tool(
        "make_database",
        "--out",
        out,
        "--resolution",
        "8,8,16",
        "--noise",
        "0.05",
        "--seed",
        "-1",
        "--materials",
        "chrome",
    )
    assert_one_error(rc, err, "--seed")
    assert not out.exists()
    from mitsuba_manifold.data.database import make_database
    from mitsuba_manifold.errors import InputError

    with pytest.raises(InputError, match="`seed` must be an integer from 0"):
        make_database(out, (8, 8, 16), ["chrome"], noise=0.05, seed=-1)
    assert not out.exists()


# --------------------------------------------------- 10. latent dimension of scenes


def test_render_basis_on_a_shipped_scene_with_q3_and_given_x(tmp_path, tiny):
    m3 = tmp_path / "m3.npz"
    rc, _, err = run_tool("fit_manifold", tiny["db"], "--q", "3", "--out", m3)
    assert rc == 0, err
    rc, _, err = run_render_basis(m3, tmp_path / "b", "--materials", "steel")
    assert rc == 0, err
    rc, _, err = run_render_basis(m3, tmp_path / "b2", "--materials", "steel", "--x", "0.1,0.2,0.3")
    assert rc == 0, err
    rc, _, err = run_render_basis(m3, tmp_path / "b3", "--x", "0.1,0.2")
    assert_one_error(rc, err, "--x", "3")


# ------------------------------------------------------------ 13. the plugin


def _bsdf(manifold, **props):
    return mi.load_dict({"type": "manifold_brdf", "manifold": manifold, **props})


def test_refused_parameter_update_keeps_the_previous_state(tiny):
    man = Manifold.load(tiny["manifold"])
    scene = mi.load_dict(
        {
            "type": "scene",
            "s": {
                "type": "sphere",
                "bsdf": {
                    "type": "manifold_brdf",
                    "id": "material",
                    "manifold": tiny["manifold"],
                    "x": "0, 0",
                },
            },
        }
    )
    params = mi.traverse(scene)
    key = [k for k in params.keys() if k.endswith(".x")][0]
    params[key] = [float("nan"), 0.0]
    with pytest.raises(Exception, match="x"):
        params.update()
    assert np.isfinite(np.array(params[key])).all()
    good = man.latent[man.index("steel")]
    params[key] = good.tolist()
    params.update()
    bsdf = [s.bsdf() for s in scene.shapes()][0]
    assert np.allclose(bsdf.latent, good.astype(np.float32))
    for wrong in (
        [1.0],
        [0.1, 0.2, 0.3],
    ):  # too short, too long: refused with the plugin's message,
        params[key] = wrong  # and the parameter is the rendered x again, whole
        with pytest.raises(Exception, match=f"x must be {man.q} finite numbers"):
            params.update()
        assert np.allclose(np.array(params[key]), good.astype(np.float32))
        params.set_dirty(key)  # a later update (of anything) works
        params.update()


@pytest.mark.parametrize(
    "props, words",
    [
        ({"x": "0, 0", "prune": "abc"}, ["prune", "abc"]),
        ({"weights": "steel:1e30, chrome:-1e30, gold-paint:1"}, ["weights"]),
        ({"weights": "steel:1, chrome:-1"}, ["sum to zero"]),
        ({"x": "nan, 0"}, ["x"]),
        ({"x": "0, 0", "sampling": "bogus"}, ["sampling"]),
        ({"material": "chrom"}, ["chrom", "did you mean"]),
    ],
)
def test_plugin_errors_are_one_clean_line(tiny, props, words):
    from mitsuba_manifold import errors

    with pytest.raises(Exception) as info:
        _bsdf(tiny["manifold"], **props)
    msg = errors.plugin_message(info.value)
    assert "\n" not in msg and "Traceback" not in msg and msg.startswith("manifold_brdf: "), msg
    assert msg.count("manifold_brdf:") == 1, msg
    for w in words:
        assert w in msg, msg
    if "1e30" in props.get("weights", ""):
        assert "sum to zero" not in msg


def test_shipped_scenes_load_with_a_manifold_of_any_latent_dimension(tmp_path, tiny):
    from mitsuba_manifold.render.scene.scenes import scene_path

    m3 = tmp_path / "m3.npz"
    Manifold.fit(tiny["db"], q=3).save(m3)
    man = Manifold.load(m3)
    for name in ("sphere", "table", "cbox"):
        scene = mi.load_file(scene_path(name), manifold=str(m3), res="8")
        (bsdf,) = [s.bsdf() for s in scene.shapes() if getattr(s.bsdf(), "is_manifold_brdf", False)]
        assert np.array_equal(bsdf.latent, man.latent[0]) and bsdf.used_names == [man.names[0]]


def test_sizes_beyond_the_memory_available_are_refused_before_anything_is_written(
    tmp_path, tiny, monkeypatch
):
    from mitsuba_manifold._util import checks as validate

    monkeypatch.setattr(validate, "available_memory", lambda: 1 << 30)  # a 1 GiB machine
    rc, _, err = run_render_basis(tiny["manifold"], tmp_path / "b", res=4096)
    assert_one_error(rc, err, "resolution", "GiB")
    rc, _, err = run_tool(
        "make_database",
        "--out",
        tmp_path / "db",
        "--resolution",
        "256,256,512",
        "--materials",
        "steel",
    )
    assert_one_error(rc, err, "--resolution", "GiB")
    rc, _, err = run_tool(
        "blend",
        "--basis",
        tiny["basis"],
        "--path",
        "steel",
        "chrome",
        "--steps",
        10**7,
        "--out",
        tmp_path / "seq.exr",
    )
    assert_one_error(rc, err, "--steps", "from 2 to 1000")  # the limit comes before memory
    assert os.listdir(tmp_path) == []


def test_fit_manifold_plots_a_one_dimensional_latent_space(tmp_path, tiny):
    rc, _, err = run_tool(
        "fit_manifold", tiny["db"], "--q", 1, "--out", tmp_path / "m.npz", "--plot", tmp_path / "p"
    )
    assert rc == 0, err
    from PIL import Image

    with Image.open(tmp_path / "p" / "latent_map.png") as im:
        assert im.size[0] > 500 and im.size[1] > 300


def test_fit_manifold_names_materials_it_cannot_find_with_a_did_you_mean(tmp_path, tiny):
    out = tmp_path / "m.npz"
    rc, _, err = run_tool("fit_manifold", tiny["db"], "--out", out, "--materials", "chrome,stel")
    assert_one_error(rc, err, "--materials")
    assert "did you mean 'steel'" in err and not out.exists()


@pytest.mark.parametrize(
    "tool, args, option",
    [
        ("blend", ["--path", "0,0", "nan,1", "--out", "{tmp}/seq.exr"], "--path"),
        ("blend", ["--path", "0,0", "1,2,3", "--out", "{tmp}/seq.exr"], "--path"),
        ("match", ["--image", "{tmp}/t.exr", "--starts", "0"], "--starts"),
        ("match", ["--image", "{tmp}/t.exr", "--scan", "-1"], "--scan"),
        ("blend", ["--x", "-1,,0", "--out", "{tmp}/o.exr"], "empty place"),
        (
            "blend",
            ["--x", "steel", "--x", "chrome", "--out", "{tmp}/o.exr"],
            "--x is given 2 times",
        ),
        (
            "blend",
            ["--x", "steel", "--out", "{tmp}/t.exr/o.exr"],
            "--out {tmp}/t.exr/o.exr: folder",
        ),
    ],
)
def test_bad_values_are_named_by_their_option(tmp_path, tiny, tool, args, option):
    """Each bad value is named by the one option at fault, in the tool's words."""
    from mitsuba_manifold.imaging import io as imageio

    imageio.write_exr(tmp_path / "t.exr", np.full((8, 8, 3), 0.5, np.float32))
    before = snapshot(tmp_path)
    rc, _, err = run_tool(tool, "--basis", tiny["basis"], *[a.format(tmp=tmp_path) for a in args])
    assert_one_error(rc, err, option.format(tmp=tmp_path))
    others = {"--starts", "--scan", "--max-iter", "--spp"} - {option}
    assert not any(o in err for o in others) and "(a or b)" not in err, err
    assert snapshot(tmp_path) == before


def test_a_file_given_as_a_basis_folder_is_called_a_file(tmp_path, tiny):
    target = tmp_path / "t.exr"
    from mitsuba_manifold.imaging import io as imageio

    imageio.write_exr(target, np.full((8, 8, 3), 0.5, np.float32))
    rc, _, err = run_tool("blend", "--basis", target, "--x", "0,0", "--out", tmp_path / "o.exr")
    assert_one_error(rc, err, "is a file, not a basis folder")


def test_render_basis_names_a_bad_max_depth_before_rendering(tmp_path, tiny):
    out = tmp_path / "b"
    rc, _, err = run_render_basis(tiny["manifold"], out, "--max-depth", -7)
    assert_one_error(rc, err, "--max-depth")
    assert not out.exists()


def test_an_exposure_free_match_of_a_black_target_is_refused(tmp_path, tiny):
    from mitsuba_manifold.imaging import io as imageio

    imageio.write_exr(tmp_path / "black.exr", np.zeros((8, 8, 3), np.float32))
    rc, _, err = run_tool(
        "match", "--basis", tiny["basis"], "--image", tmp_path / "black.exr", "--exposure-free"
    )
    assert_one_error(rc, err, "--exposure-free")
    assert "black" in err

"""Scenes: the shipped scenes found by name, and reference renders of interpolated materials."""

import itertools
import os
import re

import numpy as np
import pytest

from mitsuba_manifold.errors import MismatchError
from mitsuba_manifold.imaging import metrics
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.render.scene import scenes


@pytest.fixture(scope="module")
def manifold(small_manifold):
    return Manifold.load(small_manifold)


def test_shipped_scenes_are_found_by_name_or_path(tmp_path):
    assert {"sphere", "table", "cbox"} <= set(scenes.shipped_scenes())
    path = scenes.scene_path("table")
    assert os.path.isfile(path) and path.endswith(os.path.join("scenes", "table.xml"))
    assert scenes.scene_path(path) == path
    mine = tmp_path / "table"  # a file of that name wins over the shipped scene
    mine.write_text("<scene version='3.0.0'/>")
    assert scenes.scene_path(str(mine)) == str(mine)
    with pytest.raises(MismatchError, match="does not exist.*table"):
        scenes.scene_path("no-such-scene")


NOT_SCENES = {
    "chrome.binary": b"\x10\x00\x00\x00\x10\x00\x00\x00\xe5\xff" + bytes(64),  # a MERL table
    "photo.png": b"\x89PNG\r\n\x1a\n" + bytes(32),
    "empty.xml": b"",
    "notes.txt": "r\u00e9sum\u00e9 of the scene".encode("latin-1"),
    "other.xml": b"<bsdf type='diffuse'/>",
}


@pytest.mark.parametrize("name", sorted(NOT_SCENES))
def test_a_file_that_is_not_a_scene_xml_is_refused_in_one_line(tmp_path, name):
    """Every way a scene comes in (a name or path, its parameters, its hash for a basis check)
    refuses a table, an image or another XML with one line naming the file."""
    from mitsuba_manifold.basis import folder as basis

    path = tmp_path / name
    path.write_bytes(NOT_SCENES[name])
    for check in (scenes.scene_path, scenes.scene_parameters, basis.scene_hash):
        with pytest.raises(MismatchError, match=f"^{path} is not a Mitsuba scene XML \\(") as e:
            check(str(path))
        assert "\n" not in str(e.value)


def test_tools_refuse_a_scene_that_is_not_xml_before_any_work(tmp_path, small_manifold, capsys):
    from mitsuba_manifold.apps.cli import main_job, render_basis

    png = tmp_path / "photo.png"
    png.write_bytes(NOT_SCENES["photo.png"])
    for tool, argv in (
        (render_basis, [str(png), "--manifold", small_manifold, "--out", str(tmp_path / "b")]),
        (main_job, ["--out", str(tmp_path / "job"), "--resolution", "4,4,8", "--scene", str(png)]),
    ):
        with pytest.raises(SystemExit) as e:
            tool.main(argv)
        err = capsys.readouterr().err
        assert (
            e.value.code == 2
            and err.startswith("error: ")
            and f"{png} is not a Mitsuba scene XML (" in err
        )
        assert err.count("\n") == 1 and "Traceback" not in err
    assert sorted(os.listdir(tmp_path)) == ["photo.png"]  # nothing made


@pytest.mark.render
def test_a_scene_naming_another_manifold_is_refused_naming_it(tmp_path, small_db, small_manifold):
    """A scene with the manifold written in (not $manifold) and --manifold another one: one
    line naming both and the fix, not the latent-dimension error of loading it with x."""
    import shutil

    pytest.importorskip("mitsuba")
    other = tmp_path / "other.npz"
    Manifold.fit(small_db, q=3).save(other)  # another latent dimension than small_manifold's 2
    shutil.copy(small_manifold, tmp_path / "same.npz")
    shutil.copy(os.path.join(scenes.SCENES_DIR, "sky.exr"), tmp_path / "sky.exr")
    text = open(scenes.scene_path("sphere")).read()
    for name, value in (("other", str(other)), ("same", "same.npz")):
        (tmp_path / f"{name}.xml").write_text(text.replace('value="$manifold"', f'value="{value}"'))
    with pytest.raises(MismatchError) as e:
        scenes.load_scene(str(tmp_path / "other.xml"), small_manifold, spp=1, resolution=8)
    assert str(e.value) == (
        f"scene {tmp_path / 'other.xml'}: material 'material' names the manifold {other}, not "
        f'{small_manifold}: use value="$manifold" in the scene, or pass `manifold_path`={other}'
    )
    loaded = scenes.load_scene(
        str(tmp_path / "same.xml"), small_manifold, spp=1, resolution=8
    )  # same content
    assert len(loaded.targets) == 1


@pytest.mark.render
def test_render_reference_is_the_interpolated_material(small_manifold, manifold, tmp_path):
    """On the convex sphere scene (no path scatters twice off the sphere) the full-GI
    reference of x equals, within noise, the affine blend of full renders of the training
    materials (sum w_i = 1, so each full render brings one copy of the base). x is a
    genuine mix of two materials whose interpolated table has no negative bins for the
    plugin to clamp (clamping is the one non-linearity)."""
    scene = scenes.scene_path("sphere")
    res, spp = 24, 32
    renders = np.stack(
        [
            scenes.render_reference(
                scene, small_manifold, x, spp, seed=1 + i, resolution=(res, res)
            )
            for i, x in enumerate(manifold.latent)
        ]
    )
    assert renders.shape == (manifold.n, res, res, 3) and renders.dtype == np.float32
    assert np.isfinite(renders).all() and renders.min() >= 0
    best = (0.0, None)
    for i, j in itertools.permutations(range(manifold.n), 2):
        for a in (0.5, 0.7, 0.9):
            x = a * manifold.latent[i] + (1 - a) * manifold.latent[j]
            _, w = manifold.weights(x)
            table, _, _ = manifold.interpolate(x, prune=0.0)
            # the albedo of x farthest from every training material's, among the unclamped
            gap = np.abs(manifold.albedos - w @ manifold.albedos).sum(axis=1).min()
            if table.min() >= 0 and np.abs(w).sum() < 1.3 and gap > best[0]:
                best = (gap, x)
    assert best[0] > 0.05, "no point mixing materials without clamping on this manifold"
    x = best[1]
    _, w = manifold.weights(x)
    blended = np.tensordot(w, renders.astype(np.float64), axes=1)
    ref = scenes.render_reference(scene, small_manifold, x, spp, seed=100, resolution=(res, res))
    ref2 = scenes.render_reference(scene, small_manifold, x, spp, seed=200, resolution=(res, res))
    noise = metrics.rel_mse(ref2, ref)
    err = metrics.rel_mse(blended, ref)
    assert err < 2.0 * noise
    assert np.allclose(blended.mean(axis=(0, 1)), ref.mean(axis=(0, 1)), rtol=0.02)
    # the material really is x: every training material's render is further off
    assert min(metrics.rel_mse(r, ref) for r in renders) > 2.0 * err
    with pytest.raises(MismatchError, match="renders 256x256, not 24x12"):
        scenes.render_reference(scene, small_manifold, x, spp, resolution=(24, 12))
    with pytest.raises(MismatchError, match="manifold .* does not exist"):
        scenes.render_reference(scene, str(tmp_path / "none.npz"), x, spp)


@pytest.mark.render
def test_load_scene_renders_in_the_active_variant_and_switches_only_when_asked(
    variant, small_manifold, tmp_path
):
    import mitsuba as mi

    from mitsuba_manifold.errors import InputError
    from mitsuba_manifold.render.jobs import render_basis

    sphere = scenes.scene_path("sphere")
    mi.set_variant("scalar_rgb")
    loaded = scenes.load_scene(sphere, small_manifold, spp=1, resolution=8)
    assert mi.variant() == "scalar_rgb" and len(loaded.targets) == 1  # the active one, kept
    with pytest.raises(InputError, match="needs an RGB JIT variant.*pass `variant`"):
        render_basis.render_basis(sphere, small_manifold, tmp_path / "b", spp=1, resolution=8)
    assert mi.variant() == "scalar_rgb" and not (tmp_path / "b").exists()  # refused, not switched
    mi.set_variant("scalar_spectral")
    with pytest.raises(InputError, match="active Mitsuba variant 'scalar_spectral' cannot be used"):
        scenes.load_scene(sphere, small_manifold, spp=1, resolution=8)
    assert mi.variant() == "scalar_spectral"
    scenes.load_scene(
        sphere, small_manifold, spp=1, resolution=8, variant="llvm_ad_rgb"
    )  # asked for
    assert mi.variant() == "llvm_ad_rgb"
    with mi.util.scoped_set_variant("scalar_rgb"):  # Mitsuba's own, for a while
        assert scenes.load_scene(sphere, small_manifold, spp=1, resolution=8).targets
    assert mi.variant() == "llvm_ad_rgb"


@pytest.mark.render
def test_render_reference_renders_the_sensor_asked_for(variant, small_manifold, manifold, tmp_path):
    """A basis of view 1 gets its reference from view 1 (issue 20: references came from sensor 0)."""
    import mitsuba as mi

    text = open(scenes.scene_path("sphere")).read()
    start, end = text.index("<sensor"), text.index("</sensor>") + len("</sensor>")
    second = text[start:end]
    second = re.sub(r'origin="[^"]*"', 'origin="3, 1, 3"', second, count=1)
    scene = tmp_path / "two_views.xml"
    scene.write_text(text[:end] + second + text[end:])
    os.symlink(
        os.path.join(os.path.dirname(scenes.scene_path("sphere")), "sky.exr"), tmp_path / "sky.exr"
    )
    x = manifold.latent[0]
    views = [
        scenes.render_reference(
            str(scene), small_manifold, x, 4, seed=3, resolution=(16, 16), sensor=s
        )
        for s in (0, 1)
    ]
    assert metrics.rel_mse(views[0], views[1]) > 1e-3  # the two cameras see different images
    loaded = scenes.load_scene(str(scene), small_manifold, 4, (16, 16), None, x)
    direct = np.array(mi.render(loaded.scene, spp=4, seed=3, sensor=1), dtype=np.float32)[..., :3]
    assert metrics.rel_mse(views[1], direct) < metrics.rel_mse(views[0], direct)
    with pytest.raises(Exception, match="`sensor` 2 does not exist"):
        scenes.render_reference(str(scene), small_manifold, x, 1, resolution=(16, 16), sensor=2)

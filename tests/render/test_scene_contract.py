"""The scene as written is the contract: a basis and its references render what the scene's XML says
(its integrator's type, max_depth, rr_depth, hide_emitters; its film's filter, crop window and pixel
format; its camera; a manifold_brdf inside twosided or in instances), and what cannot be rendered is
refused before any work, naming the setting and what works instead.

The scenes are written here as a user writes them (no ``$parameters`` but the manifold; Mitsuba's
defaults where they say nothing: a Gaussian film filter, no integrator)."""

import json
import os

import mitsuba as mi  # noqa: E402
import numpy as np
import pytest

import mitsuba_manifold.render  # noqa: F401  (a working libLLVM before drjit loads; the plugins)
from mitsuba_manifold.basis import folder as bf  # noqa: E402
from mitsuba_manifold.basis.blend import blend  # noqa: E402
from mitsuba_manifold.errors import InputError, MitsubaManifoldError  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.render.integrators import manifold_bsdfs  # noqa: E402
from mitsuba_manifold.render.jobs import render_basis
from mitsuba_manifold.render.scene import scenes  # noqa: E402

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]

MATERIAL = "gold-paint"
OTHER = "white-diffuse-bball"
LOOKAT = '<transform name="to_world"><lookat origin="0, 0, 3.9" target="0, 0, 0" up="0, 1, 0"/></transform>'
MAT = (
    '<bsdf type="manifold_brdf" id="mat"><string name="manifold" value="$manifold"/>'
    f'<string name="material" value="{MATERIAL}"/></bsdf>'
)
SPHERE = (
    '<shape type="sphere"><point name="center" value="0.3, -0.55, 0.2"/><float name="radius" value="0.45"/>'
    '<ref id="mat"/></shape>'
)


def cbox(  # noqa: PLR0913  one keyword per element of the scene text
    folder,
    name,
    integrator="",
    camera="perspective",
    camera_props='<float name="fov" value="39.3"/>',
    transform=LOOKAT,
    size=(16, 16),
    film="",
    material=MAT,
    shape=SPHERE,
    floor="mat",
    extra="",
):
    """A Cornell box as users write it (Mitsuba's defaults where it says nothing), its floor and a
    sphere of the manifold material by default (they see each other: L2+); returns its path."""
    text = f"""<?xml version="1.0"?>
<scene version="3.0.0">
  <default name="manifold" value="manifold.npz"/>
  {integrator}
  <sensor type="{camera}">
    {camera_props}
    {transform}
    <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
    <film type="hdrfilm"><integer name="width" value="{size[0]}"/><integer name="height" value="{size[1]}"/>{film}</film>
  </sensor>
  {extra}
  {material}
  <bsdf type="diffuse" id="white"><rgb name="reflectance" value="0.8, 0.7, 0.66"/></bsdf>
  <bsdf type="diffuse" id="red"><rgb name="reflectance" value="0.57, 0.04, 0.04"/></bsdf>
  <bsdf type="diffuse" id="green"><rgb name="reflectance" value="0.1, 0.38, 0.08"/></bsdf>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/><translate value="0, -1, 0"/></transform><ref id="{floor}"/></shape>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="90"/><translate value="0, 1, 0"/></transform><ref id="white"/></shape>
  <shape type="rectangle"><transform name="to_world"><translate value="0, 0, -1"/></transform><ref id="white"/></shape>
  <shape type="rectangle"><transform name="to_world"><rotate y="1" angle="-90"/><translate value="1, 0, 0"/></transform><ref id="green"/></shape>
  <shape type="rectangle"><transform name="to_world"><rotate y="1" angle="90"/><translate value="-1, 0, 0"/></transform><ref id="red"/></shape>
  {shape}
  <shape type="rectangle"><transform name="to_world"><scale value="0.3, 0.25, 0.25"/><rotate x="1" angle="90"/><translate value="0, 0.99, 0"/></transform>
    <ref id="white"/><emitter type="area"><rgb name="radiance" value="14, 11, 6"/></emitter></shape>
</scene>
"""
    path = os.path.join(folder, name + ".xml")
    with open(path, "w") as f:
        f.write(text)
    return path


@pytest.fixture
def folder(tmp_path, small_manifold):
    """A scene folder holding the manifold as the scenes name it (``manifold.npz`` beside them)."""
    os.symlink(small_manifold, tmp_path / "manifold.npz")
    return str(tmp_path)


def developed_rgb(film):
    """The film's RGB (its raw storage over the filter weights), whatever its pixel format."""
    raw = np.array(film.bitmap(raw=True), dtype=np.float64)
    return (raw[..., :3] / np.where(raw[..., -1:] > 0, raw[..., -1:], 1.0)).astype(np.float32)


def mitsuba_renders(path, spp, seeds, x=None, material=MATERIAL, sensor=0):
    """Mitsuba's own images of the scene file (its integrator; RGB of the film), one per seed."""
    scene = mi.load_file(path)
    for bsdf in manifold_bsdfs(scene):
        bsdf.set_material(material) if x is None else bsdf.set_latent(x)
    integ = scene.integrator() or mi.load_dict({"type": "path"})
    out = []
    for s in seeds:
        mi.render(scene, integrator=integ, spp=spp, seed=s, sensor=sensor)
        out.append(developed_rgb(scene.sensors()[sensor].film()))
    return np.stack(out)


def onepass_gi(path, spp, seeds, **props):
    """``base + touch + L2+`` of MATERIAL from the one-pass renderer with the scene's own settings."""
    loaded = scenes.load_scene(path, os.path.join(os.path.dirname(path), "manifold.npz"))
    integ = mi.load_dict({"type": "manifold_path", **loaded.integrator.path_properties(), **props})
    out = []
    for s in seeds:
        r = integ.render_onepass_gi(
            loaded.scene, materials=[MATERIAL, OTHER], spp=spp, seed=s, levels=4
        )
        out.append(r.base + r.touch[MATERIAL] + r.rest[MATERIAL])
    return np.stack(out)


def basis_blend(path, out, x=None, spp=64, **options):
    """Render the default basis (one pass, full GI) of the scene and blend it at MATERIAL (or ``x``)."""
    manifold = os.path.join(os.path.dirname(path), "manifold.npz")
    render_basis.render_basis(
        path,
        manifold,
        out,
        spp=spp,
        mode="onepass",
        components="full",
        seed=3,
        materials=[MATERIAL, OTHER],
        **options,
    )
    m = Manifold.load(manifold)
    point = m.latent[m.index(MATERIAL)] if x is None else x
    img, _ = blend(bf.Basis.load(out), m, x=point, l2="raw", prune=0.0)
    return img, bf.Manifest.read(out)


def assert_same_mean(a, b, what, block=8, z_max=5.0):
    """Two sets of independent images (K, H, W, 3) estimate one image: per block of pixels and over
    the image, the difference of the means within ``z_max`` standard errors, estimated from the
    spread of the per-image means (a film filter correlates neighbouring pixels: their variances
    do not add)."""

    def means(x):
        k, h, w, c = x.shape
        return (
            x[:, : h // block * block, : w // block * block]
            .reshape(k, h // block, block, w // block, block, c)
            .mean((2, 4))
        )

    for pa, pb, where in ((means(a), means(b), "block"), (a.mean((1, 2)), b.mean((1, 2)), "image")):
        se = np.sqrt(pa.var(0, ddof=1) / len(pa) + pb.var(0, ddof=1) / len(pb))
        d = pa.mean(0) - pb.mean(0)
        z = np.where(d == 0, 0.0, d / np.where(se > 0, se, 1e-30))
        assert np.abs(z).max() < z_max, f"{what}: {where} z up to {np.abs(z).max():.2f}"


def _mean_close(img, refs, what, z=4.5):
    """The image mean of ``img`` (one basis, whose own noise is not known) within ``z`` standard errors
    of the references' mean, the error taken from the references' per-seed spread (scaled to one image
    of the basis's samples by ``scale``)."""
    means = refs.mean(axis=(1, 2, 3))
    se = means.std(ddof=1)  # one reference image's spread: about the basis's own at these spp
    assert abs(img.mean() - means.mean()) <= z * se + 1e-6, (what, img.mean(), means.mean(), se)


# ------------------------------------------------------------------ the scene's integrator


def test_the_scene_integrators_depth_is_rendered_not_the_tools(folder):
    """A Cornell box whose integrator says max_depth 2 (direct light only): the default full-GI basis
    renders depth 2 (no L2+: left out and said why), and its blend is Mitsuba's render of the file;
    the unbounded render (what the tool used to render) is far brighter."""
    path = cbox(
        folder,
        "depth2",
        '<integrator type="path"><integer name="max_depth" value="2"/></integrator>',
    )
    img, manifest = basis_blend(path, os.path.join(folder, "b"), spp=128)
    assert manifest.max_depth == 2 and manifest.integrator["source"] == "scene"
    assert "l2+" in manifest.left_out and "scatter once" in manifest.left_out["l2+"]
    refs = mitsuba_renders(path, 128, range(6))
    _mean_close(img, refs, "depth 2 blend vs Mitsuba")
    unbounded = mitsuba_renders(cbox(folder, "deep", ""), 64, range(2))
    assert unbounded.mean() > 1.1 * refs.mean()


def test_direct_integrator_and_hidden_emitters(folder):
    """``direct`` with ``hide_emitters``: the basis renders it (as path of depth 2, emitters hidden)
    and the light the camera sees directly is hidden in the blend as in Mitsuba's render."""
    path = cbox(
        folder,
        "direct",
        '<integrator type="direct"><boolean name="hide_emitters" value="true"/></integrator>',
    )
    img, manifest = basis_blend(path, os.path.join(folder, "b"), spp=128)
    assert manifest.integrator == {
        "kind": "direct",
        "max_depth": 2,
        "rr_depth": 5,
        "hide_emitters": True,
        "source": "scene",
    }
    refs = mitsuba_renders(path, 128, range(6))
    _mean_close(img, refs, "direct, hidden emitters")
    shown = mitsuba_renders(cbox(folder, "shown", '<integrator type="direct"/>'), 64, [0])[0]
    assert shown.max() > 5 and img.max() < 0.5 * shown.max()  # the light's pixels: dark in both
    assert refs.mean(axis=0).max() < 0.5 * shown.max()


def test_explicit_max_depth_overrides_the_scene_and_rr_depth_is_kept(folder):
    path = cbox(
        folder,
        "rr",
        '<integrator type="path"><integer name="max_depth" value="6"/>'
        '<integer name="rr_depth" value="2"/></integrator>',
    )
    loaded = scenes.load_scene(path, os.path.join(folder, "manifold.npz"))
    assert (loaded.integrator.max_depth, loaded.integrator.rr_depth, loaded.integrator.source) == (
        6,
        2,
        "scene",
    )
    over = scenes.load_scene(path, os.path.join(folder, "manifold.npz"), max_depth=3).integrator
    assert (over.kind, over.max_depth, over.rr_depth, over.source) == ("path", 3, 2, "option")
    none = scenes.load_scene(cbox(folder, "none"), os.path.join(folder, "manifold.npz")).integrator
    assert (none.max_depth, none.source) == (-1, "default")


@pytest.mark.parametrize(
    "integrator",
    [
        '<integrator type="ptracer"/>',
        '<integrator type="depth"/>',
        '<integrator type="aov"><string name="aovs" value="d:depth"/></integrator>',
    ],
)
def test_integrators_the_basis_cannot_reproduce_are_refused_before_rendering(folder, integrator):
    path = cbox(folder, "odd", integrator)
    out = os.path.join(folder, "b")
    with pytest.raises(InputError, match=r'integrator.*cannot reproduce.*<integrator type="path">'):
        render_basis.render_basis(
            path, os.path.join(folder, "manifold.npz"), out, spp=4, mode="onepass"
        )
    assert not os.path.exists(out)


def test_blend_reference_renders_the_scene_integrator(folder, tmp_path, capsys):
    """``blend.py --render-reference`` renders the basis's scene with its integrator (depth 2 here):
    its reference is Mitsuba's render of the file, not the tool's unbounded path."""
    from mitsuba_manifold.apps.cli import blend as blend_cli

    path = cbox(
        folder, "ref2", '<integrator type="path"><integer name="max_depth" value="2"/></integrator>'
    )
    out = os.path.join(folder, "b")
    render_basis.render_basis(
        path,
        os.path.join(folder, "manifold.npz"),
        out,
        spp=8,
        mode="onepass",
        components="full",
        materials=[MATERIAL, OTHER],
    )
    blend_cli.main(
        [
            "--basis",
            out,
            "--x",
            MATERIAL,
            "--out",
            str(tmp_path / "o.exr"),
            "--render-reference",
            "--spp",
            "128",
        ]
    )
    assert "max_depth 2" in capsys.readouterr().out
    from mitsuba_manifold.imaging import io as imageio

    ref = imageio.read_exr(str(tmp_path / "o_reference.exr"))
    refs = mitsuba_renders(path, 128, range(4))
    assert abs(ref.mean() - refs.mean()) <= 4.5 * refs.mean(axis=(1, 2, 3)).std(ddof=1)


# ------------------------------------------------------------------ films and cameras


def test_full_gi_basis_with_mitsubas_default_gaussian_filter_equals_mitsuba(folder):
    """The film says nothing of its filter (Mitsuba's Gaussian): the one-pass full-GI image of a
    material (floor and sphere see each other: L2+) equals Mitsuba's render, block and image z-tests."""
    path = cbox(
        folder,
        "gauss",
        '<integrator type="path"><integer name="max_depth" value="4"/></integrator>',
    )
    assert not mi.load_file(path).sensors()[0].film().rfilter().is_box_filter()
    img = onepass_gi(path, 8, range(6))
    ref = mitsuba_renders(path, 8, range(100, 106))
    assert_same_mean(img, ref, "one-pass full GI with a Gaussian filter vs Mitsuba")


def test_the_filter_weights_each_splat_as_the_film_weighs_its_sample(folder):
    """A wide Gaussian (stddev 1 pixel) spreads a sample over many pixels: the touch image of the
    one pass equals the ``touch`` component rendered through Mitsuba's own film, in every block; its
    splats are put as the film puts samples (same weights, to float precision)."""
    from mitsuba_manifold.render.integrators.splats import FilterTaps

    path = cbox(
        folder,
        "wide",
        '<integrator type="path"><integer name="max_depth" value="3"/></integrator>',
        film='<rfilter type="gaussian"><float name="stddev" value="1"/></rfilter>',
    )
    loaded = scenes.load_scene(path, os.path.join(folder, "manifold.npz"))
    film = loaded.scene.sensors()[0].film()
    film.prepare([])
    block = film.create_block()
    rng = np.random.default_rng(1)
    pos = mi.Vector2f(*(rng.uniform(0, 16, 3000).astype(np.float32) for _ in range(2)))
    block.put(pos, [mi.Float(1.0)] * 4)
    weights = np.zeros(256)
    for pixel, w in FilterTaps(block, film.rfilter()).taps(pos):
        np.add.at(weights, pixel.numpy(), w.numpy())
    np.testing.assert_allclose(
        weights, np.array(block.tensor())[..., -1].ravel(), rtol=1e-4, atol=1e-4
    )
    integ = mi.load_dict({"type": "manifold_path", "max_depth": 3})
    one = np.stack(
        [
            integ.render_onepass(loaded.scene, materials=[MATERIAL], spp=8, seed=s).images[MATERIAL]
            for s in range(6)
        ]
    )
    loaded.targets[0].set_material(MATERIAL)
    touch = mi.load_dict({"type": "manifold_path", "component": "touch", "max_depth": 3})
    ref = np.stack(
        [
            np.array(mi.render(loaded.scene, integrator=touch, spp=8, seed=50 + s))[..., :3]
            for s in range(6)
        ]
    )
    assert_same_mean(one, ref, "touch image with a wide Gaussian filter")


def test_orthographic_camera(folder):
    """An orthographic camera's rays share one direction: the one-pass images are not black."""
    path = cbox(
        folder,
        "ortho",
        camera="orthographic",
        camera_props="",
        transform='<transform name="to_world"><lookat origin="0, 0, 3.9" target="0, 0, 0" up="0, 1, 0"/>'
        '<scale value="1.1, 1.1, 1"/></transform>',
    )
    loaded = scenes.load_scene(path, os.path.join(folder, "manifold.npz"))
    integ = mi.load_dict({"type": "manifold_path", "max_depth": 3})
    img = np.stack(
        [
            integ.render_onepass(loaded.scene, materials=[MATERIAL], spp=8, seed=s).images[MATERIAL]
            for s in range(6)
        ]
    )
    loaded.targets[0].set_material(MATERIAL)
    touch = mi.load_dict({"type": "manifold_path", "component": "touch", "max_depth": 3})
    ref = np.stack(
        [
            np.array(mi.render(loaded.scene, integrator=touch, spp=8, seed=50 + s))[..., :3]
            for s in range(6)
        ]
    )
    assert img.std() > 0.1 * ref.std()
    assert_same_mean(img, ref, "orthographic one pass vs Mitsuba")


def test_crop_window_luminance_film_and_a_second_non_square_sensor(folder):
    """A crop window: the basis's images are the crop's size and blend; a luminance film: the basis
    and its reference are RGB; the reference of a second, non-square sensor of a scene taking $res is
    rendered at the basis's size."""
    manifold = os.path.join(folder, "manifold.npz")
    crop = cbox(
        folder,
        "crop",
        size=(20, 16),
        film='<string name="pixel_format" value="luminance"/>'
        '<integer name="crop_offset_x" value="4"/><integer name="crop_offset_y" value="2"/>'
        '<integer name="crop_width" value="12"/><integer name="crop_height" value="10"/>',
    )
    img, manifest = basis_blend(crop, os.path.join(folder, "b1"), spp=16)
    assert manifest.resolution == (12, 10) and img.shape == (10, 12, 3)
    m = Manifold.load(manifold)
    ref = scenes.render_reference(
        crop,
        manifold,
        m.latent[m.index(MATERIAL)],
        16,
        resolution=scenes.scene_resolution(manifest),
    )
    assert ref.shape == img.shape

    second = (
        '<sensor type="perspective"><float name="fov" value="50"/>'
        + LOOKAT
        + '<film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="8"/></film>'
        "</sensor>"
    )
    views = cbox(folder, "views", extra=second).replace("views.xml", "views.xml")
    text = (
        open(views)
        .read()
        .replace(
            '<default name="manifold"',
            '<default name="res" value="16"/>\n  <default name="manifold"',
        )
    )
    with open(views, "w") as f:
        f.write(text)
    out = os.path.join(folder, "b2")
    render_basis.render_basis(
        views,
        manifold,
        out,
        spp=4,
        mode="onepass",
        sensor=1,
        resolution=12,
        materials=[MATERIAL, OTHER],
    )
    manifest = bf.Manifest.read(out)
    assert manifest.resolution == (12, 8)
    ref = scenes.render_reference(
        views, manifold, m.latent[0], 4, resolution=scenes.scene_resolution(manifest), sensor=1
    )
    assert ref.shape == (8, 12, 3)


# ------------------------------------------------------------------ materials as users nest them


def test_twosided_material_seen_from_its_back(folder):
    """A twosided manifold material whose back faces the camera: the one-pass full-GI image equals
    Mitsuba's render (the back side's records are mirrored into the front's frame)."""
    two = (
        '<bsdf type="twosided" id="mat"><bsdf type="manifold_brdf"><string name="manifold" value="$manifold"/>'
        f'<string name="material" value="{MATERIAL}"/></bsdf></bsdf>'
    )
    panel = (
        '<shape type="rectangle"><transform name="to_world"><scale value="0.5"/><rotate y="1" angle="200"/>'
        '<translate value="0, -0.3, 0"/></transform><ref id="mat"/></shape>'
    )
    path = cbox(
        folder,
        "two",
        '<integrator type="path"><integer name="max_depth" value="4"/></integrator>',
        material=two,
        shape=panel,
    )
    img = onepass_gi(path, 8, range(6))
    ref = mitsuba_renders(path, 8, range(100, 106))
    assert_same_mean(img, ref, "twosided (back side) one pass vs Mitsuba")


def test_instanced_material_is_found_and_rendered(folder):
    group = (
        '<shape type="shapegroup" id="grp">' + SPHERE + "</shape>"
        '<shape type="instance"><ref id="grp"/><transform name="to_world"><translate value="-0.6, 0, 0"/>'
        "</transform></shape>"
    )
    path = cbox(
        folder,
        "inst",
        '<integrator type="path"><integer name="max_depth" value="4"/></integrator>',
        shape=group,
        floor="white",
    )
    loaded = scenes.load_scene(path, os.path.join(folder, "manifold.npz"))
    assert [b.id() for b in loaded.targets] == ["mat"]
    img = onepass_gi(path, 8, range(6))
    ref = mitsuba_renders(path, 8, range(100, 106))
    assert_same_mean(img, ref, "instanced material, one pass vs Mitsuba")


def test_normalmap_around_the_material_is_refused_naming_it(folder):
    nm = (
        '<bsdf type="normalmap" id="bumpy"><texture name="normalmap" type="checkerboard"/>'
        '<ref id="inner"/></bsdf>' + MAT.replace('id="mat"', 'id="inner"')
    )
    path = cbox(folder, "nm", material=nm.replace('id="bumpy"', 'id="mat"'))
    with pytest.raises(
        MitsubaManifoldError, match="inside the normalmap BSDF 'mat'.*without the normalmap"
    ):
        scenes.load_scene(path, os.path.join(folder, "manifold.npz"))


def test_manifest_records_what_was_rendered(folder):
    path = cbox(
        folder,
        "rec",
        '<integrator type="path"><integer name="max_depth" value="4"/>'
        '<boolean name="hide_emitters" value="true"/></integrator>',
        floor="white",
    )
    out = os.path.join(folder, "b")
    render_basis.render_basis(
        path, os.path.join(folder, "manifold.npz"), out, spp=2, mode="onepass", materials=[MATERIAL]
    )
    with open(os.path.join(out, "manifest.json")) as f:
        m = json.load(f)
    assert (
        m["integrator"]["hide_emitters"] is True
        and m["max_depth"] == 4
        and m["scene_resolution"] is None
    )

"""Basis rendering: selection, resume after interruption, refusals, linearity of the blend."""

import os
import subprocess
import sys

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from mitsuba_manifold.basis import folder as bf  # noqa: E402
from mitsuba_manifold.basis.blend import blend  # noqa: E402
from mitsuba_manifold.errors import MismatchError  # noqa: E402
from mitsuba_manifold.imaging import io as imageio  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.render.jobs import render_basis
from mitsuba_manifold.render.scene import scenes  # noqa: E402

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SPHERE = scenes.scene_path("sphere")
RES = 24


def test_basis_options_take_their_fields_by_name_into_their_groups():
    """``render_basis(..., spp=8, mode="onepass")`` sets the fields of the groups they belong to;
    a name that is no field is refused naming the options."""
    o = render_basis.BasisOptions().updated(spp=8, mode="onepass", levels=3, force=True, x=[0.1])
    assert (o.sampling.spp, o.sampling.mode, o.gi.levels, o.run.force, o.scene.x) == (
        8,
        "onepass",
        3,
        True,
        [0.1],
    )
    assert o.selection == render_basis.Selection() and o.sampling.seed == 0
    gi = render_basis.FullGI(components="full")
    assert o.updated(gi=gi).gi == gi and o.keywords("spp", "levels") == {"spp": 8, "levels": 3}
    with pytest.raises(TypeError, match="'sppp'.*spp"):
        o.updated(sppp=8)


def test_select_materials(small_manifold):
    m = Manifold.load(small_manifold)
    assert render_basis.select_materials(m) == m.names
    assert render_basis.select_materials(m, ["steel", "chrome"]) == [
        n for n in m.names if n in ("steel", "chrome")
    ]
    near = render_basis.select_materials(m, near=m.latent[0], radius=1e-9)
    assert near == [m.names[0]]
    assert render_basis.select_materials(m, near=m.names[0], radius=1e-9) == near  # a name
    with pytest.raises(render_basis.InputError, match="unknown material"):
        render_basis.select_materials(m, ["steel", "adamantium"])
    with pytest.raises(render_basis.InputError, match="2 finite numbers"):
        render_basis.select_materials(m, near=[0.0], radius=1.0)
    with pytest.raises(render_basis.InputError, match="no material lies within"):
        render_basis.select_materials(m, near=m.latent.max(0) + 100, radius=0.5)


def test_a_misspelt_material_gets_a_suggestion(small_manifold, tmp_path):
    from guarantees_helpers import assert_one_error, run_tool

    rc, _, err = run_tool(
        "render_basis",
        "sphere",
        "--manifold",
        small_manifold,
        "--materials",
        "chrme,steel",
        "--res",
        8,
        "--spp",
        1,
        "--out",
        tmp_path / "b",
    )
    assert_one_error(rc, err, "'chrme'", "did you mean 'chrome'")
    assert not (tmp_path / "b").exists() or not os.listdir(tmp_path / "b")


def test_the_centre_of_a_near_basis_can_be_blended(tmp_path, small_manifold):
    """A radius that holds only one of two neighbours still renders what the blend at the
    centre needs: blending there works without --renormalise."""
    m = Manifold.load(small_manifold)
    d = np.linalg.norm(m.latent[:, None] - m.latent[None], axis=-1) + np.eye(m.n) * 1e9
    i, j = np.unravel_index(np.argmin(d), d.shape)
    centre = m.latent[i] + 0.45 * (m.latent[j] - m.latent[i])
    chosen = render_basis.select_materials(m, near=centre, radius=0.5 * d[i, j])
    assert m.names[i] in chosen and m.names[j] in chosen
    assert set(m.names[k] for k in m.prune(m.weights(centre).w).keep) <= set(chosen)
    out = tmp_path / "basis"
    render_basis.render_basis(
        SPHERE, small_manifold, out, spp=2, near=centre, radius=0.5 * d[i, j], resolution=8
    )
    image, info = blend(out, x=centre)
    assert image.shape == (8, 8, 3) and not info.renormalised and not info.missing


def test_the_library_takes_a_shipped_scenes_name_like_the_tools(tmp_path, small_manifold):
    m = Manifold.load(small_manifold)
    manifest = render_basis.render_basis(
        "sphere", small_manifold, tmp_path / "b", spp=1, resolution=8, materials=[m.names[0]]
    )
    assert manifest.scene == SPHERE and len(manifest.images) == 2
    with pytest.raises(render_basis.InputError, match="spherre"):
        render_basis.render_basis("spherre", small_manifold, tmp_path / "c", spp=1, resolution=8)


def test_an_unknown_components_value_is_refused_not_rendered_as_l1(tmp_path, small_manifold):
    # the library and the command line share one word, "full"; another value is not read as l1
    with pytest.raises(render_basis.InputError, match="`components` must be 'full'.*got 'l2\\+'"):
        render_basis.render_basis(
            "sphere",
            small_manifold,
            tmp_path / "b",
            spp=1,
            resolution=8,
            mode="onepass",
            components="l2+",
        )
    assert not (tmp_path / "b").exists()


def test_scene_without_manifold_material_is_refused(tmp_path, small_manifold):
    scene = tmp_path / "plain.xml"
    scene.write_text("""<scene version="3.0.0">
      <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
      <integer name="height" value="8"/></film></sensor>
      <shape type="sphere"><bsdf type="diffuse"/></shape>
      <emitter type="constant"/></scene>""")
    with pytest.raises(MismatchError, match="no manifold_brdf material"):
        render_basis.render_basis(str(scene), small_manifold, str(tmp_path / "out"), spp=1)
    r = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "tools", "render_basis.py"),
            str(scene),
            "--manifold",
            small_manifold,
            "--out",
            str(tmp_path / "out2"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "no manifold_brdf material" in r.stderr


def test_interrupted_run_resumes_without_corrupt_files(tmp_path, small_manifold, monkeypatch):
    out = tmp_path / "basis"
    real_write = imageio.write_exr
    calls = {"n": 0}

    def flaky(path, img, metadata=None):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt("killed")  # dies while writing the 4th image
        return real_write(path, img, metadata)

    monkeypatch.setattr(imageio, "write_exr", flaky)
    with pytest.raises(KeyboardInterrupt):
        render_basis.render_basis(
            SPHERE, small_manifold, str(out), spp=4, resolution=RES, mode="per-material"
        )
    monkeypatch.setattr(imageio, "write_exr", real_write)
    manifest = bf.Manifest.read(str(out))
    assert len(manifest.images) == 3
    assert not [f for f in os.listdir(out) if f.endswith(".tmp")]
    for entry in manifest.images.values():  # every listed image is whole
        assert imageio.read_exr(out / entry.file).shape == (RES, RES, 3)
    before = {k: os.stat(out / e.file).st_mtime_ns for k, e in manifest.images.items()}

    manifest = render_basis.render_basis(
        SPHERE, small_manifold, str(out), spp=4, resolution=RES, mode="per-material"
    )
    m = Manifold.load(small_manifold)
    assert set(manifest.images) == {"base", *m.names}
    assert all(os.stat(out / manifest.images[k].file).st_mtime_ns == t for k, t in before.items())
    b = bf.Basis.load(str(out), manifold=small_manifold, scene=SPHERE, verify=True)
    assert b.materials == [m.names]

    # other settings in the same folder: refused, nothing touched
    snapshot = {f: (out / f).read_bytes() for f in os.listdir(out)}
    with pytest.raises(render_basis.InputError, match="other settings.*spp"):
        render_basis.render_basis(
            SPHERE, small_manifold, str(out), spp=8, resolution=RES, mode="per-material"
        )
    assert {f: (out / f).read_bytes() for f in os.listdir(out)} == snapshot


def _render_l1(scene, spp, seed):
    integrator = mi.load_dict({"type": "manifold_path", "component": "l1"})
    return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed))[..., :3]


def _assert_same_mean(a, b, what):
    """Two unbiased estimates of one image agree: means over the image and its quadrants."""
    d = (a - b).astype(np.float64)
    h = d.shape[0] // 2
    for part in (d, d[:h, :h], d[:h, h:], d[h:, :h], d[h:, h:]):
        flat = part.reshape(-1, 3)
        se = flat.std(axis=0) / np.sqrt(len(flat))
        assert np.all(np.abs(flat.mean(axis=0)) <= 4.5 * se + 1e-7), (what, flat.mean(axis=0), se)


def test_blend_equals_direct_l1_render(tmp_path, small_manifold):
    """Linearity: base + sum_i w_i I_i is an unbiased estimate of the L1- image of sum_i w_i rho_i."""
    out = tmp_path / "basis"
    m = Manifold.load(small_manifold)
    render_basis.render_basis(
        SPHERE,
        small_manifold,
        str(out),
        spp=32,
        resolution=RES,
        mode="per-material",
        materials=["gold-paint", "steel", "pink-fabric"],
    )
    b = bf.Basis.load(str(out), manifold=small_manifold)
    w = np.zeros(m.n)
    w[m.index("gold-paint")], w[m.index("steel")], w[m.index("pink-fabric")] = 0.5, 0.2, 0.3
    img, info = blend(b, m, w=w, prune=0.0)
    scene, (target,), _ = scenes.load_scene(SPHERE, small_manifold, 32, RES)
    target.set_weights(w)
    assert target.clamped_bins == 0
    direct = _render_l1(scene, 128, seed=12345)
    assert direct.mean() > 0.01
    _assert_same_mean(img, direct, "blend vs direct")


def test_onepass_basis_through_the_tool(tmp_path, small_manifold):
    """render_basis in one-pass mode: every image written once, listed once, reusable by blend."""
    out = tmp_path / "onepass"
    names = ["gold-paint", "steel", "pink-fabric"]
    manifest = render_basis.render_basis(
        SPHERE, small_manifold, str(out), spp=8, resolution=RES, mode="onepass", materials=names
    )
    assert manifest.mode == "onepass" and set(manifest.images) == {"base", *names}
    b = bf.Basis.load(str(out), manifold=small_manifold, scene=SPHERE, verify=True)
    assert all(np.isfinite(b.image(k)).all() for k in ["base", *names])
    assert b.image("steel").mean() > 0
    images = sorted(f for f in os.listdir(out) if f.endswith(".exr"))
    assert len(images) == 4
    stamp = {f: os.stat(out / f).st_mtime_ns for f in images}
    render_basis.render_basis(
        SPHERE, small_manifold, str(out), spp=8, resolution=RES, mode="onepass", materials=names
    )
    assert {f: os.stat(out / f).st_mtime_ns for f in images} == stamp  # nothing re-rendered


def _two_sphere_scene(path, manifold, xa, xb):
    path.write_text(f"""<scene version="3.0.0">
      <default name="manifold" value="{manifold}"/><default name="spp" value="4"/>
      <default name="res" value="{RES}"/>
      <sensor type="perspective"><float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 0, 6" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/>
          <rfilter type="box"/></film></sensor>
      <bsdf type="manifold_brdf" id="left"><string name="manifold" value="$manifold"/>
        <string name="x" value="{xa}"/></bsdf>
      <bsdf type="manifold_brdf" id="right"><string name="manifold" value="$manifold"/>
        <string name="x" value="{xb}"/></bsdf>
      <shape type="sphere"><point name="center" value="-1.1, 0, 0"/><ref id="left"/></shape>
      <shape type="sphere"><point name="center" value="1.1, 0, 0"/><ref id="right"/></shape>
      <emitter type="constant"/></scene>""")


def test_two_identical_manifold_materials_stay_two_targets(tmp_path, small_manifold):
    """Mitsuba merges identical BSDF definitions by default: two manifold materials given the
    same x (the natural start) must still be two targets of a multilinear basis."""
    scene = tmp_path / "same.xml"
    _two_sphere_scene(scene, small_manifold, "", "")
    loaded = scenes.load_scene(str(scene), small_manifold, spp=4, resolution=RES)
    assert [t.id() for t in loaded.targets] == ["left", "right"]


def test_two_manifold_materials_give_a_multilinear_basis(tmp_path, small_manifold):
    """Two targets: one full L1- image per pair of materials; a training pair blends to its image."""
    m = Manifold.load(small_manifold)
    a, b = "gold-paint", "steel"
    xa, xb = (", ".join(repr(float(v)) for v in m.latent[m.index(n)]) for n in (a, b))
    scene = tmp_path / "two.xml"
    _two_sphere_scene(scene, small_manifold, xa, xb)
    out = tmp_path / "basis2"
    manifest = render_basis.render_basis(
        str(scene), small_manifold, str(out), spp=4, materials=[a, b]
    )
    assert manifest.targets == ["left", "right"]
    assert set(manifest.images) == {f"{p}+{q}" for p in (a, b) for q in (a, b)}
    with pytest.raises(render_basis.InputError, match="one manifold material"):
        render_basis.render_basis(
            str(scene), small_manifold, str(tmp_path / "b3"), spp=4, materials=[a], mode="onepass"
        )
    bb = bf.Basis.load(str(out), manifold=small_manifold, scene=str(scene))
    img, _ = blend(bb, m, x=np.stack([m.latent[m.index(b)], m.latent[m.index(a)]]))
    assert np.array_equal(img, bb.image(f"{b}+{a}"))
    assert not np.array_equal(bb.image(f"{a}+{b}"), bb.image(f"{b}+{a}"))


def test_the_tool_renders_at_the_scenes_sample_count_and_says_when_res_is_not_square(
    tmp_path, small_manifold, capsys
):
    """Without ``--spp`` a basis has the samples per pixel the scene declares (its ``$spp``
    default); ``--spp`` overrides them; ``--res`` on a scene whose film fixes its height says in
    one line on stderr what size the images are."""
    from mitsuba_manifold.apps.cli import render_basis as tool

    scene = tmp_path / "wide.xml"
    scene.write_text("""<scene version="3.0.0">
      <default name="spp" value="3"/><default name="res" value="16"/>
      <default name="manifold" value="m.npz"/><default name="x" value=""/>
      <sensor type="perspective"><sampler type="independent">
      <integer name="sample_count" value="$spp"/></sampler>
      <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="6"/>
      </film></sensor>
      <bsdf type="manifold_brdf" id="ball"><string name="manifold" value="$manifold"/>
      <string name="x" value="$x"/></bsdf>
      <shape type="sphere"><ref id="ball"/><transform name="to_world">
      <translate value="0, 0, 4"/></transform></shape>
      <emitter type="constant"/></scene>""")
    m = Manifold.load(small_manifold)
    common = [str(scene), "--manifold", small_manifold, "--mode", "per-material"]
    common += ["--materials", ",".join(m.names[:2]), "--res", "8"]
    tool.main(common + ["--out", str(tmp_path / "a")])
    err = capsys.readouterr().err
    manifest = bf.Manifest.read(tmp_path / "a")
    assert manifest.spp == 3 and manifest.resolution == (8, 6)
    notes = [ln for ln in err.splitlines() if ln.startswith("note:")]  # besides the progress bar
    assert len(notes) == 1 and "--res 8 gave 8x6 images" in notes[0]
    tool.main(common + ["--out", str(tmp_path / "b"), "--spp", "2"])
    assert bf.Manifest.read(tmp_path / "b").spp == 2


def test_scene_and_manifold_by_their_former_names_scene_path_and_manifold_path(
    tmp_path, small_manifold
):
    """The former keywords still reach the same checks, each with a DeprecationWarning."""
    with pytest.warns(DeprecationWarning) as caught:
        with pytest.raises(render_basis.InputError, match="`spp` must be >= 1"):
            render_basis.render_basis(
                scene_path="sphere", manifold_path=small_manifold, out=str(tmp_path / "b"), spp=0
            )
    said = {str(w.message).split(";")[0] for w in caught}
    assert said == {
        "render_basis(scene_path=...) is now spelled render_basis(scene=...)",
        "render_basis(manifold_path=...) is now spelled render_basis(manifold=...)",
    }
    with pytest.raises(TypeError, match="give `scene` only"):
        render_basis.render_basis("sphere", small_manifold, str(tmp_path / "b"), scene_path="x")
    assert not (tmp_path / "b").exists()

"""EXR I/O, metrics, basis folders and the blend (paper Eq. 13 and Sec. 6) on synthetic images."""

import json
import os
import shutil
from dataclasses import replace

import numpy as np
import pytest
from helpers import write_basis

from mitsuba_manifold.basis import blend as bl
from mitsuba_manifold.basis import folder as bf
from mitsuba_manifold.basis.folder import Basis
from mitsuba_manifold.errors import InputError, MismatchError
from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.imaging import metrics
from mitsuba_manifold.manifold import paths
from mitsuba_manifold.manifold.file.identity import manifold_identity
from mitsuba_manifold.manifold.model import Manifold

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
RES = (12, 9)  # width, height


@pytest.fixture(scope="module")
def manifold(small_manifold):
    return Manifold.load(small_manifold)


@pytest.fixture(scope="module")
def cli():
    from mitsuba_manifold.apps.cli import blend as blend_cli

    return blend_cli


def _scene(folder, text="a"):
    path = os.path.join(folder, "scene.xml")
    with open(path, "w") as f:
        f.write(f'<scene version="3.0.0"><!-- {text} --><shape type="sphere"/></scene>\n')
    return path


def _make_basis(folder, manifold_path, names, rng, targets=("material",), with_base=True):
    """Random images for ``names`` (keys) and a manifest; returns (folder, scene, images)."""
    w, h = RES
    keys = ([bf.BASE] if with_base else []) + list(names)
    images = {key: rng.uniform(0.0, 2.0, size=(h, w, 3)).astype(np.float32) for key in keys}
    scene = write_basis(folder, manifold_path, images, targets)
    return folder, scene, images


@pytest.fixture
def basis1(tmp_path, small_manifold, manifold):
    """One-target basis with every material of the manifold."""
    return _make_basis(
        str(tmp_path / "basis"), small_manifold, manifold.names, np.random.default_rng(1)
    )


# ------------------------------------------------------------------ images


def test_blend_is_the_weighted_sum(basis1, manifold):
    folder, _, images = basis1
    basis = Basis.load(folder, manifold=manifold)
    rng = np.random.default_rng(2)
    for x in manifold.latent.mean(0) + rng.normal(scale=0.7, size=(3, manifold.q)):
        img, info = bl.blend(basis, manifold, x=x, prune=0.0)
        _, w = manifold.weights(x)
        want = images["base"] + np.einsum(
            "i,ihwc->hwc", w, np.stack([images[n] for n in manifold.names]).astype(np.float64)
        )
        assert img.dtype == np.float32 and img.shape == (RES[1], RES[0], 3)
        assert np.allclose(img, want, rtol=1e-5, atol=1e-5 * np.abs(w).sum())
        assert info.time_ms >= 0 and not info.missing and np.allclose(info.x, x)
    # weights given directly: any weights (the touch images are linear in the BRDF)
    w = rng.normal(size=manifold.n)
    img, _ = bl.blend(basis, manifold, w=w, prune=0.0)
    want = images["base"] + sum(
        wi * images[n].astype(np.float64) for wi, n in zip(w, manifold.names)
    )
    assert np.allclose(img, want, rtol=1e-5, atol=1e-5)


def test_pruning_drops_small_weights_and_keeps_the_sum(basis1, manifold):
    folder, _, images = basis1
    x = manifold.latent[0] * 0.7 + manifold.latent[1] * 0.3
    _, w = manifold.weights(x)
    img, info = bl.blend(folder, manifold, x=x, prune=0.05)
    keep, wk, dropped = manifold.prune(w, 0.05)
    assert len(keep) < manifold.n and dropped > 0
    assert info.weights[0] == {manifold.names[i]: pytest.approx(v) for i, v in zip(keep, wk)}
    want = images["base"] + sum(
        v * images[manifold.names[i]].astype(np.float64) for i, v in zip(keep, wk)
    )
    assert np.allclose(img, want, rtol=1e-5, atol=1e-5)


def test_training_point_gives_base_plus_its_image_exactly(basis1, manifold):
    folder, _, images = basis1
    basis = Basis.load(folder)  # manifold taken from the manifest
    for i, name in enumerate(manifold.names):
        img, info = bl.blend(basis, x=manifold.latent[i])
        assert np.array_equal(img, images["base"] + images[name])
        assert info.plan.keys == [name]


def test_uniform_weights_give_base_plus_mean(basis1, manifold):
    folder, _, images = basis1
    img, info = bl.blend(folder, manifold, w=np.full(manifold.n, 1.0 / manifold.n), prune=0.0)
    mean = np.mean([images[n].astype(np.float64) for n in manifold.names], axis=0)
    assert len(info.plan.keys) == manifold.n
    assert np.allclose(img, images["base"] + mean, rtol=1e-6, atol=1e-6)


def test_missing_materials_raise_unless_pruned_or_renormalised(tmp_path, small_manifold, manifold):
    names = manifold.names[:3]
    folder, _, images = _make_basis(
        str(tmp_path / "near"), small_manifold, names, np.random.default_rng(3)
    )
    basis = Basis.load(folder, manifold=small_manifold)
    img, _ = bl.blend(basis, manifold, x=manifold.latent[1])  # only material 1 survives pruning
    assert np.array_equal(img, images["base"] + images[names[1]])
    with pytest.raises(MismatchError, match=manifold.names[5]) as e:
        bl.blend(basis, manifold, x=manifold.latent.mean(0), prune=0.0)
    assert "w=" in str(e.value) and "renormalise" in str(e.value)
    x = manifold.latent.mean(0)
    img, info = bl.blend(basis, manifold, x=x, prune=0.0, renormalise=True)
    _, w = manifold.weights(x)
    scaled = w[:3] * (w.sum() / w[:3].sum())
    want = images["base"] + sum(v * images[n].astype(np.float64) for v, n in zip(scaled, names))
    assert info.renormalised and set(info.missing) == set(manifold.names[3:])
    assert np.allclose(img, want, rtol=1e-5, atol=1e-5)


def test_wrong_x_dimension_is_a_clear_error(basis1, manifold):
    folder, _, _ = basis1
    for x in ([0.1], [0.1, 0.2, 0.3], [[0.1, 0.2], [0.3, 0.4]]):
        with pytest.raises(MismatchError, match=f"needs {manifold.q} numbers"):
            bl.blend(folder, manifold, x=x)
    with pytest.raises(MismatchError, match="NaN"):
        bl.blend(folder, manifold, x=[np.nan, 0.0])
    with pytest.raises(MismatchError, match="exactly one of `x`"):
        bl.blend(folder, manifold)


def test_cli_latent_point_too_far_out_is_one_line_without_warnings(
    basis1, manifold, tmp_path, cli, capsys
):
    import warnings

    folder, _, _ = basis1
    for big in ("1e308", "-1e200", "1e31"):
        x = ",".join([big] + ["0"] * (manifold.q - 1))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(SystemExit) as e:
                cli.main(["--basis", folder, "--x", x, "--out", str(tmp_path / "img.exr")])
        err = capsys.readouterr().err
        assert (
            e.value.code == 2
            and err.count("\n") == 1
            and "too far out" in err
            and "Warning" not in err
        )
    assert os.listdir(tmp_path) == ["basis"]


def test_bad_basis_folders_are_clear_errors(basis1, tmp_path, manifold):
    folder, scene, _ = basis1
    with pytest.raises(MismatchError, match="does not exist"):
        Basis.load(str(tmp_path / "nowhere"))
    with pytest.raises(MismatchError, match="no manifest.json"):
        Basis.load(str(tmp_path))
    manifest_path = os.path.join(folder, bf.MANIFEST)
    good = open(manifest_path).read()
    open(manifest_path, "w").write(good[:50])
    with pytest.raises(MismatchError, match="not valid JSON"):
        Basis.load(folder)
    for field, value, message in (
        ("resolution", [12], "resolution"),
        ("mode", "x", "mode"),
        ("manifold_hash", "abc", "SHA-256"),
        ("version", 99, "newer"),
        ("images", {"base": {"file": "../base.exr", "time_s": 0}}, "plain"),
    ):
        m = json.loads(good)
        m[field] = value
        open(manifest_path, "w").write(json.dumps(m))
        with pytest.raises(MismatchError, match=message):
            Basis.load(folder)
    m = json.loads(good)
    m["resolution"] = [12, 10]
    open(manifest_path, "w").write(json.dumps(m))
    with pytest.raises(MismatchError, match=r"image 'base'.*is 12x9, expected 12x10"):
        Basis.load(folder)
    m = json.loads(good)
    del m["images"]["base"]
    open(manifest_path, "w").write(json.dumps(m))
    with pytest.raises(MismatchError, match="no 'base' image"):
        Basis.load(folder)
    open(manifest_path, "w").write(good)
    assert Basis.load(folder, scene=scene).keys == manifold.names


def test_manifest_from_another_scene_or_manifold_is_refused(basis1, tmp_path, manifold):
    folder, scene, _ = basis1
    other_scene = _scene(str(tmp_path), "another scene")
    with pytest.raises(MismatchError, match="another scene"):
        Basis.load(folder, scene=other_scene)
    other = Manifold(
        manifold.names,
        manifold.latent + 0.01,
        manifold.database,
        manifold.hashes,
        manifold.length_scale,
        manifold.noise,
        albedos=manifold.albedos,
    )
    other_path = str(tmp_path / "other.npz")
    other.save(other_path)
    with pytest.raises(MismatchError, match="another manifold"):
        Basis.load(folder, manifold=other_path)
    with pytest.raises(MismatchError, match="another manifold"):
        bl.blend(folder, other_path, x=[0.0, 0.0])
    renamed = Manifold(
        ["a", "b"] + manifold.names[2:], manifold.latent, manifold.database, manifold.hashes
    )
    with pytest.raises(MismatchError, match="does not know"):
        bl.blend(folder, renamed, x=[0.0, 0.0])
    # a mesh the scene uses is part of its identity
    with open(scene, "w") as f:
        f.write(
            '<scene version="3.0.0"><shape type="ply"><string name="filename" value="m.ply"/></shape></scene>'
        )
    open(os.path.join(folder, "m.ply"), "w").write("one")
    h1 = bf.scene_hash(scene)
    open(os.path.join(folder, "m.ply"), "w").write("two")
    assert bf.scene_hash(scene) != h1


def test_missing_and_truncated_images(basis1, manifold):
    folder, _, images = basis1
    name = manifold.names[2]
    path = os.path.join(folder, name + ".exr")
    data = open(path, "rb").read()
    os.remove(path)
    with pytest.raises(
        MismatchError, match=f"image '{name}'.*{name}.exr: image file does not exist"
    ):
        Basis.load(folder)
    big = np.random.default_rng(5).uniform(size=(RES[1], RES[0], 3)).astype(np.float32)
    imageio.write_exr(path, big)
    data = open(path, "rb").read()
    open(path, "wb").write(data[: len(data) - 20])  # the header survives: found when read
    basis = Basis.load(folder)
    img, _ = bl.blend(basis, manifold, x=manifold.latent[0])  # the damaged image is not needed
    assert np.array_equal(img, images["base"] + images[manifold.names[0]])
    with pytest.raises(MismatchError, match=f"{name}.exr: truncated or corrupt"):
        bl.blend(basis, manifold, x=manifold.latent[2])
    with pytest.raises(MismatchError, match="truncated or corrupt"):
        Basis.load(folder, verify=True)


def test_manifest_helpers(tmp_path, small_manifold):
    scene = _scene(str(tmp_path))
    settings = bf.RenderSettings(
        resolution=(4, 3), spp=8, variant="llvm_ad_rgb", seed=1, max_depth=8, mode="onepass"
    )
    a = bf.Manifest.new(scene, small_manifold, settings, targets=["material"])
    assert a.scene == os.path.abspath(scene)
    assert a.manifold_hash == manifold_identity(
        Manifold.load(small_manifold)
    )  # content, not file bytes
    path = a.write(str(tmp_path))
    assert bf.Manifest.read(str(tmp_path)) == a and path.endswith("manifest.json")
    b = replace(
        a,
        settings=replace(a.settings, spp=16),
        images={"base": bf.ImageEntry(file="base.exr", time_s=1.0)},
    )
    assert a.differences(b) == ["spp"]
    with pytest.raises(MismatchError, match="mode"):
        bf.Manifest.new(scene, small_manifold, replace(settings, mode="fast"), targets=["material"])
    with pytest.raises(MismatchError, match="must name 2 material"):
        replace(a, targets=["a", "b"], images={"x": bf.ImageEntry("x.exr", 0)}).write(str(tmp_path))
    assert bf.Manifest.read(str(tmp_path)) == a  # the refused write left the old manifest
    assert bf.image_key(["gold-paint", "chrome"]) == "gold-paint+chrome"


# -------------------------------------------------------------- multilinear


def test_multilinear_two_target_blend(tmp_path, small_manifold, manifold):
    names = manifold.names
    keys = [a + "+" + b for a in names for b in names]
    folder, _, images = _make_basis(
        str(tmp_path / "two"),
        small_manifold,
        keys,
        np.random.default_rng(4),
        targets=("cup", "saucer"),
        with_base=False,
    )
    basis = Basis.load(folder, manifold=manifold)
    assert basis.p == 2 and basis.materials == [sorted(names)] * 2
    stack = np.stack([[images[a + "+" + b] for b in names] for a in names]).astype(np.float64)
    x = np.array([manifold.latent[0] * 0.6 + manifold.latent[3] * 0.4, manifold.latent.mean(0)])
    img, info = bl.blend(basis, manifold, x=x, prune=0.0)
    _, W = manifold.weights(x)
    assert np.allclose(img, np.einsum("i,j,ijhwc->hwc", W[0], W[1], stack), rtol=1e-5, atol=1e-5)
    assert len(info.weights) == 2
    img2, _ = bl.blend(basis, manifold, x=x.ravel(), prune=0.0)  # p*q numbers in target order
    assert np.array_equal(img, img2)
    # training points of both targets: exactly the image of that pair
    img, info = bl.blend(basis, manifold, x=[manifold.latent[2], manifold.latent[5]])
    assert np.array_equal(img, images[names[2] + "+" + names[5]]) and info.plan.keys == [
        names[2] + "+" + names[5]
    ]
    with pytest.raises(MismatchError, match=r"needs 4 numbers"):
        bl.blend(basis, manifold, x=manifold.latent[0])
    with pytest.raises(MismatchError, match="summing to 1 per target"):
        bl.blend(basis, manifold, w=np.ones((2, manifold.n)))
    # a pair missing from the basis, with weight: refused, naming it
    m = bf.Manifest.read(folder)
    del m.images[names[2] + "+" + names[5]]
    m.write(folder)
    with pytest.raises(MismatchError, match=f"{names[2]}\\+{names[5]}"):
        bl.blend(folder, manifold, x=[manifold.latent[2], manifold.latent[5]])


# -------------------------------------------------------------------- path


def test_blend_path_and_contact_sheet(basis1, manifold, tmp_path):
    from PIL import Image

    folder, _, images = basis1
    a, b = manifold.names[1], manifold.names[4]
    seq, xs, info = bl.blend_path(folder, manifold, a, b, steps=5, kind="straight")
    assert seq.shape == (5, RES[1], RES[0], 3)
    assert np.allclose(xs[2], 0.5 * (manifold.latent[1] + manifold.latent[4]))
    assert np.array_equal(seq[0], images["base"] + images[a]) and np.array_equal(
        seq[-1], images["base"] + images[b]
    )
    mid, _ = bl.blend(folder, manifold, x=xs[2])
    assert np.allclose(seq[2], mid, rtol=1e-6, atol=1e-6)
    sheet = str(tmp_path / "sheet.png")
    imageio.write_contact_sheet(sheet, seq, labels=[f"{i}" for i in range(5)], columns=5, pad=2)
    assert Image.open(sheet).size == (5 * RES[0] + 6 * 2, RES[1] + 14 + 2 * 2)
    with pytest.raises(MismatchError, match="steps"):
        bl.blend_path(folder, manifold, a, b, steps=1)


def test_blend_path_of_a_kind_or_of_given_points(basis1, manifold):
    """``kind`` walks :meth:`Manifold.path`; ``points`` blends exactly the latent points given."""
    folder, _, images = basis1
    a, b = manifold.names[1], manifold.names[4]
    seq, xs, _ = bl.blend_path(folder, manifold, a, b, steps=5, kind="uniform")
    assert np.allclose(xs, manifold.path(a, b, steps=5, kind="uniform"))
    assert np.array_equal(seq[0], images["base"] + images[a]) and np.array_equal(
        seq[-1], images["base"] + images[b]
    )
    # no kind: the package's one default path, as Manifold.path, blend.py --path and the explorer
    _, xs, _ = bl.blend_path(folder, manifold, a, b, steps=5)
    assert paths.DEFAULT_KIND == "faithful"
    assert np.allclose(xs, manifold.path(a, b, steps=5))
    assert np.allclose(xs, manifold.path(a, b, steps=5, kind="faithful"))
    pts = manifold.latent[[0, 2, 3]] + 0.01
    seq, xs, _ = bl.blend_path(folder, manifold, points=pts)
    assert np.array_equal(xs, pts) and len(seq) == 3
    for img, x in zip(seq, pts):
        assert np.allclose(img, bl.blend(folder, manifold, x=x)[0], rtol=1e-6, atol=1e-6)
    with pytest.raises(MismatchError, match="points"):
        bl.blend_path(folder, manifold, points=pts[:1])
    with pytest.raises(InputError, match="`kind`"):
        bl.blend_path(folder, manifold, a, b, steps=5, kind="scenic")


def test_blend_denoised_blend_and_blend_path_take_settings_the_same_two_ways(basis1, manifold):
    """Each takes ``settings=BlendSettings(...)`` and each field as a keyword, which wins."""
    folder, _, images = basis1
    a, b = manifold.names[1], manifold.names[4]
    x = manifold.latent.mean(0)
    loose = bl.BlendSettings(prune=0.5)
    by_object, info_o = bl.blend(folder, manifold, x=x, settings=loose)
    by_keyword, info_k = bl.blend(folder, manifold, x=x, prune=0.5)
    assert np.array_equal(by_object, by_keyword) and info_o.weights == info_k.weights
    exact, info_e = bl.blend(folder, manifold, x=x, settings=loose, prune=0.0)  # the keyword wins
    assert len(info_e.weights[0]) > len(info_o.weights[0])
    assert np.array_equal(exact, bl.blend(folder, manifold, x=x, prune=0.0)[0])
    path_o = bl.blend_path(folder, manifold, a, b, steps=3, kind="straight", settings=loose)[0]
    path_k = bl.blend_path(folder, manifold, a, b, steps=3, kind="straight", prune=0.5)[0]
    assert np.array_equal(path_o, path_k)
    steps = bl.blend_path(folder, manifold, a, b, steps=3, kind="straight", prune=0.5)[1]
    assert np.array_equal(path_k[1], bl.blend(folder, manifold, x=steps[1], prune=0.5)[0])
    for call in (
        lambda **kw: bl.blend(folder, manifold, x=x, **kw),
        lambda **kw: bl.blend_path(folder, manifold, a, b, steps=3, kind="straight", **kw),
    ):
        with pytest.raises(MismatchError, match="`component` must be one of"):
            call(component="rest")
        with pytest.raises(MismatchError, match="`l2` must be one of"):
            call(settings=bl.BlendSettings(l2="smooth"))
        with pytest.raises(MismatchError, match="`settings` must be a BlendSettings"):
            call(settings={"prune": 0.5})
        with pytest.raises(TypeError, match="the settings of a blend are prune, renormalise"):
            call(prunes=0.5)


def test_blend_path_refuses_ignored_x_and_identical_ends(basis1, manifold, tmp_path, cli, capsys):
    folder, _, _ = basis1
    a, b = manifold.names[0], manifold.names[1]
    with pytest.raises(MismatchError, match="one target"):
        bl.blend_path(folder, manifold, a, b, steps=3, moving=bl.MovingTarget(x=manifold.latent[2]))
    for ends in ((a, a), (manifold.latent[1], manifold.latent[1]), (a, manifold.latent[0])):
        with pytest.raises(MismatchError, match="same latent point"):
            bl.blend_path(folder, manifold, *ends, steps=3)
    out = str(tmp_path / "out" / "seq.exr")
    x = ",".join(str(v) for v in manifold.latent[2])
    for args, words in [
        (["--x", x, "--path", a, b], "drop --x"),
        (["--path", a, a], "same latent point"),
    ]:
        with pytest.raises(SystemExit) as e:
            cli.main(["--basis", folder, "--out", out] + args)
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.count("\n") == 1 and words in err
    assert not os.path.exists(tmp_path / "out")


# --------------------------------------------------------------------- CLI


def test_cli_blend_with_reference(basis1, manifold, tmp_path, cli, capsys):
    folder, _, images = basis1
    ref = images["base"] + images[manifold.names[3]] + 0.01
    ref_path = str(tmp_path / "ref.exr")
    imageio.write_exr(ref_path, ref)
    out = str(tmp_path / "out" / "img.exr")
    x = ",".join(str(v) for v in manifold.latent[3])
    cli.main(["--basis", folder, "--x", x, "--out", out, "--png", "--reference", ref_path])
    text = capsys.readouterr().out
    img = imageio.read_exr(out)
    assert np.array_equal(img, images["base"] + images[manifold.names[3]])
    stats = metrics.compare(img, ref)
    assert "blend time:" in text and f"relative MSE {stats['rel_mse']:.4g}" in text
    assert f"PSNR {stats['psnr']:.2f} dB" in text and f"max error {stats['max_abs']:.4g}" in text
    assert np.allclose(imageio.read_exr(str(tmp_path / "out" / "img_error.exr")), np.abs(img - ref))
    for name in ("img.png", "img_error.png"):
        assert os.path.getsize(str(tmp_path / "out" / name)) > 0


def test_cli_blend_again_removes_its_stale_companions_only(basis1, manifold, tmp_path, cli, capsys):
    """A second blend to the same --out without --png or a reference leaves no PNG or error image
    of the first point beside the new EXR; a file the user put there is kept."""
    folder, _, images = basis1
    ref_path = str(tmp_path / "ref.exr")
    imageio.write_exr(ref_path, images["base"] + 0.01)
    out = tmp_path / "out" / "img.exr"
    x = lambda i: ",".join(str(v) for v in manifold.latent[i])  # noqa: E731
    cli.main(["--basis", folder, "--x", x(3), "--out", str(out), "--png", "--reference", ref_path])
    assert {"img.png", "img_error.png", "img_error.exr"} <= set(os.listdir(out.parent))
    (out.parent / "img_reference.png").write_bytes(b"the user's own notes")
    cli.main(["--basis", folder, "--x", x(1), "--out", str(out)])
    left = {f for f in os.listdir(out.parent) if not f.startswith(".")}
    assert left == {"img.exr", "img_reference.png"}, left
    assert "removed" in capsys.readouterr().out


def test_cli_path_writes_sequence_and_sheet(basis1, manifold, tmp_path, cli, capsys, monkeypatch):
    folder, _, _ = basis1
    out = str(tmp_path / "seq" / "seq.exr")
    sheets, write = [], imageio.write_contact_sheet
    monkeypatch.setattr(
        imageio, "write_contact_sheet", lambda *a, **k: (sheets.append((a, k)), write(*a, **k))
    )
    cli.main(
        [
            "--basis",
            folder,
            "--path",
            manifold.names[0],
            manifold.names[1],
            "--steps",
            "4",
            "--out",
            out,
        ]
    )
    assert sorted(f for f in os.listdir(tmp_path / "seq") if not f.startswith(".")) == [
        "seq_0.exr",
        "seq_1.exr",
        "seq_2.exr",
        "seq_3.exr",
        "seq_sheet.png",
    ]
    assert "4 images blended" in capsys.readouterr().out
    (_, _, labels), kw = sheets[0]  # the sheet names its two ends
    a, b = manifold.names[:2]
    assert (
        labels[0].endswith(a) and labels[-1].endswith(b) and a in kw["title"] and b in kw["title"]
    )


def test_cli_bad_input_overwrites_nothing(basis1, manifold, tmp_path, cli, capsys):
    folder, _, _ = basis1
    out = str(tmp_path / "img.exr")
    for name in ("img.exr", "img_error.exr", "img_error.png"):
        open(str(tmp_path / name), "wb").write(b"precious")
    bad_ref = str(tmp_path / "ref.exr")
    open(bad_ref, "wb").write(b"v/1\x01" + b"\0" * 30)
    other_scene = _scene(str(tmp_path), "other")
    other_manifold = str(tmp_path / "other.npz")
    Manifold(manifold.names, manifold.latent * 1.01, manifold.database, manifold.hashes).save(
        other_manifold
    )
    x = ["--x", "0.1", "0.2"]
    cases = [
        (["--x", "0.1", "0.2", "0.3"], "needs 2 numbers"),
        (x + ["--reference", bad_ref], "ref.exr: truncated or corrupt"),
        (x + ["--reference", str(tmp_path / "none.exr")], "none.exr: image file does not exist"),
        (x + ["--scene", other_scene], "another scene"),
        (x + ["--manifold", other_manifold], "another manifold"),
    ]
    for extra, message in cases:
        with pytest.raises(SystemExit) as e:
            cli.main(["--basis", folder, "--out", out] + extra)
        assert e.value.code == 2
        assert message in capsys.readouterr().err
    shutil.copy(os.path.join(folder, manifold.names[0] + ".exr"), os.path.join(folder, "base.exr"))
    data = open(os.path.join(folder, "base.exr"), "rb").read()
    open(os.path.join(folder, "base.exr"), "wb").write(data[:-30])
    with pytest.raises(SystemExit):
        cli.main(["--basis", folder, "--out", out] + x)
    assert "base.exr: truncated or corrupt" in capsys.readouterr().err
    for name in ("img.exr", "img_error.exr", "img_error.png"):
        assert open(str(tmp_path / name), "rb").read() == b"precious"


# --------------------------------------------------------------- reference


def test_cli_several_targets_take_names_and_the_fixed_targets_of_a_path(
    tmp_path, small_manifold, manifold, cli, capsys
):
    """On a two-target basis: ``--x A B`` is ``--x A --x B``; ``--path A B --target T`` takes
    ``--x`` for the target that stays fixed only; a wrong count says what to pass, in one line
    (the library takes names where it takes a latent point too)."""
    names = manifold.names
    folder, _, _ = _make_basis(
        str(tmp_path / "two"),
        small_manifold,
        [a + "+" + b for a in names for b in names],
        np.random.default_rng(5),
        targets=("cup", "saucer"),
        with_base=False,
    )
    a, b, c = names[0], names[1], names[2]
    one, two = str(tmp_path / "one.exr"), str(tmp_path / "two.exr")
    cli.main(["--basis", folder, "--x", a, c, "--out", one])
    cli.main(["--basis", folder, "--x", a, "--x", c, "--out", two])
    want, _ = bl.blend(folder, manifold, x=[a, c])
    np.testing.assert_array_equal(imageio.read_exr(one), want)
    np.testing.assert_array_equal(imageio.read_exr(two), want)
    np.testing.assert_array_equal(
        want, bl.blend(folder, manifold, x=[manifold.latent[0], manifold.latent[2]])[0]
    )
    seq = str(tmp_path / "walk.exr")
    cli.main(
        [
            "--basis",
            folder,
            "--path",
            a,
            b,
            "--target",
            "saucer",
            "--x",
            c,
            "--steps",
            "3",
        ]
        + ["--out", seq]
    )  # the command line's default path kind is blend_path's
    images, _, _ = bl.blend_path(folder, manifold, a, b, steps=3, moving=bl.MovingTarget(1, [c, a]))
    np.testing.assert_array_equal(imageio.read_exr(str(tmp_path / "walk_1.exr")), images[1])
    capsys.readouterr()
    for args, words in [
        (["--path", a, b, "--target", "saucer"], "give one --x per target that stays fixed (cup"),
        (["--x", a], "repeat --x once per target"),
        (["--x", a, "0.3"], "repeat --x once per point"),
        (["--x", "nosuch", "--x", a], "unknown material 'nosuch'"),
    ]:
        with pytest.raises(SystemExit) as e:
            cli.main(["--basis", folder, "--out", str(tmp_path / "bad.exr")] + args)
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.count("\n") == 1 and words in err, err
    with pytest.raises(InputError, match="unknown material 'nosuch'"):
        bl.blend(folder, manifold, x="nosuch")


def test_a_material_name_is_taken_wherever_a_latent_point_is(basis1, manifold, tmp_path):
    """``blend(x="chrome")``, ``Manifold.point`` and every tool's latent-point option (one parser:
    ``render_basis.py --x/--near``, ``blend.py --x``) take a material's name for its point."""
    from mitsuba_manifold.apps.cli.common import parse_point, parse_points

    folder, _, _ = basis1
    name = manifold.names[2]
    np.testing.assert_array_equal(
        bl.blend(folder, manifold, x=name)[0], bl.blend(folder, manifold, x=manifold.latent[2])[0]
    )
    np.testing.assert_array_equal(manifold.point(name), manifold.latent[2])
    np.testing.assert_array_equal(manifold.point("0.5, -1"), [0.5, -1.0])
    assert parse_point(name) == name and parse_point("-0.5,1e-3") == [-0.5, 1e-3]
    assert parse_points([[name, "steel"], ["0.1", "0.2"]]) == [name, "steel", [0.1, 0.2]]
    with pytest.raises(InputError, match="did you mean"):
        manifold.point(name[:-1] + "x")


def test_a_folder_of_one_basis_per_view_names_them(tmp_path, small_manifold, manifold):
    """``render_basis.py --views all`` writes one basis per view into sub-folders: given the
    parent, loading names them instead of saying it is no basis."""
    for j in range(2):
        _make_basis(
            str(tmp_path / "views" / f"scene-view{j}"),
            small_manifold,
            manifold.names,
            np.random.default_rng(j),
        )
    with pytest.raises(
        MismatchError,
        match=r"no manifest.json; it holds 2 basis folder.*scene-view0, .*scene-view1\)",
    ):
        Basis.load(str(tmp_path / "views"), manifold=manifold)


def test_cross_terms_are_added_to_the_image_in_place():
    """Eq. 13's cross terms: ``image += sum_r p_r C[rows[r]]`` for one image (in place, term by
    term) and for a sequence (a new sum), to float32 rounding."""
    from mitsuba_manifold.basis.composition import _add_cross

    rng = np.random.default_rng(7)
    C = rng.normal(size=(5, 9, 11, 3)).astype(np.float32)

    class Cross:  # the two reads of the basis that _add_cross makes
        def cross_term(self, row):
            return C[row]

        def cross_terms(self):
            return {}, C.astype(np.float16)

    rows, p = np.array([4, 0, 2]), np.array([0.5, -1.25, 0.0], np.float32)
    image = rng.normal(size=(9, 11, 3)).astype(np.float32)
    want = image.astype(np.float64) + np.einsum("r,rhwc->hwc", p, C[rows].astype(np.float64))
    same = image
    _add_cross(image, Cross(), rows, p)
    assert image is same
    np.testing.assert_allclose(image, want, rtol=1e-5, atol=1e-5)

"""EXR I/O, metrics, basis folders and the blend (paper Eq. 13 and Sec. 6) on synthetic images."""

import importlib.util
import itertools
import json
import os
import shutil
import sys

import numpy as np
import pytest

from mitsuba_manifold import blend as bl
from mitsuba_manifold import imageio, metrics
from mitsuba_manifold.blend import Basis, BasisError
from mitsuba_manifold.imageio import ImageError
from mitsuba_manifold.manifold import Manifold

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RES = (12, 9)  # width, height


def _load_cli():
    tools = os.path.join(ROOT, "tools")
    if tools not in sys.path:
        sys.path.insert(0, tools)  # the tools import their _cli helpers as scripts do
    spec = importlib.util.spec_from_file_location("blend_cli", os.path.join(ROOT, "tools", "blend.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def manifold(small_manifold):
    return Manifold.load(small_manifold)


@pytest.fixture(scope="module")
def cli():
    return _load_cli()


def _scene(folder, text="a"):
    path = os.path.join(folder, "scene.xml")
    with open(path, "w") as f:
        f.write(f'<scene version="3.0.0"><!-- {text} --><shape type="sphere"/></scene>\n')
    return path


def _make_basis(folder, manifold_path, names, rng, targets=("material",), with_base=True):
    """Random images for ``names`` (keys) and a manifest; returns (folder, scene, images)."""
    os.makedirs(folder, exist_ok=True)
    scene = _scene(folder)
    w, h = RES
    images, entries = {}, {}
    keys = ([bl.BASE] if with_base else []) + list(names)
    for key in keys:
        img = rng.uniform(0.0, 2.0, size=(h, w, 3)).astype(np.float32)
        file = key.replace("+", "__") + ".exr"
        imageio.write_exr(os.path.join(folder, file), img)
        images[key] = img
        entries[key] = {"file": file, "time_s": 0.01}
    manifest = bl.make_manifest(scene, manifold_path, RES, 16, "llvm_ad_rgb", 0, 8, "per-material",
                                list(targets), entries)
    bl.write_manifest(folder, manifest)
    return folder, scene, images


@pytest.fixture
def basis1(tmp_path, small_manifold, manifold):
    """One-target basis with every material of the manifold."""
    return _make_basis(str(tmp_path / "basis"), small_manifold, manifold.names, np.random.default_rng(1))


# ------------------------------------------------------------------ images

def test_exr_round_trip_is_exact_and_keeps_metadata(tmp_path):
    rng = np.random.default_rng(0)
    img = (rng.normal(size=(7, 11, 3)) * 10.0 ** rng.integers(-6, 6, size=(7, 11, 3))).astype(np.float32)
    img[0, 0] = [0.0, -0.0, np.finfo(np.float32).max]
    path = str(tmp_path / "a.exr")
    imageio.write_exr(path, img, metadata={"scene": "x.xml", "spp": 64})
    back = imageio.read_exr(path)
    assert back.dtype == np.float32 and back.shape == (7, 11, 3)
    assert np.array_equal(back.view(np.uint32), img.view(np.uint32))  # bit exact, signed zero too
    header = imageio.read_exr_header(path)
    assert (header["width"], header["height"]) == (11, 7)
    assert header["attributes"]["scene"] == "x.xml" and json.loads(header["attributes"]["spp"]) == 64


def test_exr_read_errors_name_the_file(tmp_path):
    img = np.random.default_rng(0).uniform(size=(64, 80, 3)).astype(np.float32)
    good = str(tmp_path / "good.exr")
    imageio.write_exr(good, img)
    data = open(good, "rb").read()
    cases = {"missing.exr": (None, "does not exist"), "empty.exr": (b"", "not an OpenEXR"),
             "text.exr": (b"hello, not an image" * 10, "not an OpenEXR"),
             "trunc.exr": (data[: len(data) * 2 // 3], "truncated or corrupt"),
             "header.exr": (data[:40], "truncated or corrupt")}
    for name, (content, message) in cases.items():
        path = str(tmp_path / name)
        if content is not None:
            open(path, "wb").write(content)
        with pytest.raises(ImageError, match=message) as e:
            imageio.read_exr(path)
        assert path in str(e.value)
    import OpenEXR
    grey = str(tmp_path / "grey.exr")
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Y": img[..., 0].copy()}).write(grey)
    with pytest.raises(ImageError, match=r"grey.exr: EXR has channels \['Y'\], missing RGB"):
        imageio.read_exr(grey)
    with pytest.raises(ImageError, match="missing RGB"):
        imageio.check_exr_header(grey)
    with pytest.raises(ImageError, match="is 80x64, expected 80x65"):
        imageio.check_exr_header(good, (80, 65))


def test_writers_never_leave_a_half_written_file(tmp_path):
    path = str(tmp_path / "keep.exr")
    img = np.ones((4, 5, 3), np.float32)
    imageio.write_exr(path, img)
    before = open(path, "rb").read()
    bad = img.copy()
    bad[1, 1, 1] = np.nan
    with pytest.raises(ImageError, match="NaN"):
        imageio.write_exr(path, bad)
    with pytest.raises(ImageError, match="shape"):
        imageio.write_exr(path, img[..., :2])
    assert open(path, "rb").read() == before
    assert os.listdir(tmp_path) == ["keep.exr"]  # no temporary file left behind


def test_png_is_srgb_tonemapped(tmp_path):
    from PIL import Image
    img = np.array([[[0.0, 0.5, 1.0], [0.25, 2.0, -1.0]]], dtype=np.float32)
    path = str(tmp_path / "a.png")
    imageio.write_png(path, img)
    px = np.asarray(Image.open(path).convert("RGB"))
    # sRGB: 0.5 -> 1.055 * 0.5^(1/2.4) - 0.055 = 0.7354 -> 188; 0.25 -> 0.5371 -> 137; clipped above 1 and below 0
    assert px.tolist() == [[[0, 188, 255], [137, 255, 0]]]
    imageio.write_png(path, img, exposure=1.0)  # one stop up: 0.25 -> 0.5
    assert np.asarray(Image.open(path).convert("RGB"))[0, 1, 0] == 188


# ----------------------------------------------------------------- metrics

def test_metrics_against_hand_computed_values():
    ref = np.array([[[1.0, 2.0, 0.0], [4.0, 0.0, 0.0]]])
    a = np.array([[[1.5, 2.0, 0.1], [2.0, 0.0, 0.0]]])
    # squared errors 0.25, 0, 0.01, 4, 0, 0 over 6 values
    assert metrics.mse(a, ref) == pytest.approx(4.26 / 6)
    rel = (0.25 / 1.01 + 0.01 / 0.01 + 4.0 / 16.01) / 6
    assert metrics.rel_mse(a, ref) == pytest.approx(rel)
    assert metrics.psnr(a, ref) == pytest.approx(10 * np.log10(16.0 / (4.26 / 6)))  # peak = max(ref) = 4
    assert metrics.psnr(a, ref, peak=1.0) == pytest.approx(10 * np.log10(6 / 4.26))
    assert metrics.max_abs(a, ref) == pytest.approx(2.0)
    assert np.allclose(metrics.error_image(a, ref), np.abs(a - ref))
    s = metrics.compare(a, ref)
    assert s["rel_mse"] == pytest.approx(rel) and s["max_abs"] == pytest.approx(2.0)
    assert s["mean_abs"] == pytest.approx(2.6 / 6) and s["peak"] == 4.0
    assert metrics.compare(ref, ref)["psnr"] == float("inf")
    with pytest.raises(ValueError, match="shape"):
        metrics.compare(a, ref[:, :1])
    with pytest.raises(ValueError, match="reference contains NaN"):
        metrics.compare(a, np.where(ref == 0, np.nan, ref))


def test_false_colour_error_png(tmp_path):
    from PIL import Image
    ref = np.zeros((4, 6, 3))
    a = ref.copy()
    a[1, 2] = 3.0
    a[3, 5] = 1.5
    path = str(tmp_path / "err.png")
    vmax = metrics.write_error_png(path, a, ref)
    assert vmax == 3.0
    png = Image.open(path)
    assert png.size == (6, 4) and "0 .. 3" in png.text["error-scale"]
    px = np.asarray(png.convert("RGB")).astype(int)
    rgb, _ = metrics.false_colour(np.abs(a - ref), vmax=3.0)
    assert np.array_equal(px, rgb)
    assert (px[0, 0] == px[2, 2]).all() and not (px[1, 2] == px[0, 0]).all()  # zero error: one colour


# ------------------------------------------------------------------- basis

def test_blend_is_the_weighted_sum(basis1, manifold):
    folder, _, images = basis1
    basis = Basis.load(folder, manifold=manifold)
    rng = np.random.default_rng(2)
    for x in manifold.latent.mean(0) + rng.normal(scale=0.7, size=(3, manifold.q)):
        img, info = bl.blend(basis, manifold, x=x, prune=0.0)
        _, w = manifold.weights(x)
        want = images["base"] + np.einsum("i,ihwc->hwc", w, np.stack([images[n] for n in manifold.names]).astype(np.float64))
        assert img.dtype == np.float32 and img.shape == (RES[1], RES[0], 3)
        assert np.allclose(img, want, rtol=1e-5, atol=1e-5 * np.abs(w).sum())
        assert info["time_ms"] >= 0 and not info["missing"] and np.allclose(info["x"], x)
    # weights given directly: any weights (the touch images are linear in the BRDF)
    w = rng.normal(size=manifold.n)
    img, _ = bl.blend(basis, manifold, w=w, prune=0.0)
    want = images["base"] + sum(wi * images[n].astype(np.float64) for wi, n in zip(w, manifold.names))
    assert np.allclose(img, want, rtol=1e-5, atol=1e-5)


def test_pruning_drops_small_weights_and_keeps_the_sum(basis1, manifold):
    folder, _, images = basis1
    x = manifold.latent[0] * 0.7 + manifold.latent[1] * 0.3
    _, w = manifold.weights(x)
    img, info = bl.blend(folder, manifold, x=x, prune=0.05)
    keep, wk, dropped = manifold.prune(w, 0.05)
    assert len(keep) < manifold.n and dropped > 0
    assert info["weights"][0] == {manifold.names[i]: pytest.approx(v) for i, v in zip(keep, wk)}
    want = images["base"] + sum(v * images[manifold.names[i]].astype(np.float64) for i, v in zip(keep, wk))
    assert np.allclose(img, want, rtol=1e-5, atol=1e-5)


def test_training_point_gives_base_plus_its_image_exactly(basis1, manifold):
    folder, _, images = basis1
    basis = Basis.load(folder)  # manifold taken from the manifest
    for i, name in enumerate(manifold.names):
        img, info = bl.blend(basis, x=manifold.latent[i])
        assert np.array_equal(img, images["base"] + images[name])
        assert info["keys"] == [name]


def test_far_field_gives_base_plus_mean(basis1, manifold):
    folder, _, images = basis1
    img, info = bl.blend(folder, manifold, x=np.full(manifold.q, 1e3))
    mean = np.mean([images[n].astype(np.float64) for n in manifold.names], axis=0)
    assert len(info["keys"]) == manifold.n
    assert np.allclose(img, images["base"] + mean, rtol=1e-6, atol=1e-6)


def test_missing_materials_raise_unless_pruned_or_renormalised(tmp_path, small_manifold, manifold):
    names = manifold.names[:3]
    folder, _, images = _make_basis(str(tmp_path / "near"), small_manifold, names, np.random.default_rng(3))
    basis = Basis.load(folder, manifold=small_manifold)
    img, _ = bl.blend(basis, manifold, x=manifold.latent[1])  # only material 1 survives pruning
    assert np.array_equal(img, images["base"] + images[names[1]])
    with pytest.raises(BasisError, match=manifold.names[5]) as e:
        bl.blend(basis, manifold, x=manifold.latent.mean(0), prune=0.0)
    assert "w=" in str(e.value) and "renormalise" in str(e.value)
    x = manifold.latent.mean(0)
    img, info = bl.blend(basis, manifold, x=x, prune=0.0, renormalise=True)
    _, w = manifold.weights(x)
    scaled = w[:3] * (w.sum() / w[:3].sum())
    want = images["base"] + sum(v * images[n].astype(np.float64) for v, n in zip(scaled, names))
    assert info["renormalised"] and set(info["missing"]) == set(manifold.names[3:])
    assert np.allclose(img, want, rtol=1e-5, atol=1e-5)


def test_wrong_x_dimension_is_a_clear_error(basis1, manifold):
    folder, _, _ = basis1
    for x in ([0.1], [0.1, 0.2, 0.3], [[0.1, 0.2], [0.3, 0.4]]):
        with pytest.raises(BasisError, match=f"needs {manifold.q} numbers"):
            bl.blend(folder, manifold, x=x)
    with pytest.raises(BasisError, match="NaN"):
        bl.blend(folder, manifold, x=[np.nan, 0.0])
    with pytest.raises(BasisError, match="exactly one of x"):
        bl.blend(folder, manifold)


def test_bad_basis_folders_are_clear_errors(basis1, tmp_path, manifold):
    folder, scene, _ = basis1
    with pytest.raises(BasisError, match="does not exist"):
        Basis.load(str(tmp_path / "nowhere"))
    with pytest.raises(BasisError, match="no manifest.json"):
        Basis.load(str(tmp_path))
    manifest_path = os.path.join(folder, bl.MANIFEST)
    good = open(manifest_path).read()
    open(manifest_path, "w").write(good[:50])
    with pytest.raises(BasisError, match="not valid JSON"):
        Basis.load(folder)
    for field, value, message in (("resolution", [12], "resolution"), ("mode", "x", "mode"),
                                  ("manifold_hash", "abc", "SHA-256"), ("version", 99, "newer"),
                                  ("images", {"base": {"file": "../base.exr", "time_s": 0}}, "plain")):
        m = json.loads(good)
        m[field] = value
        open(manifest_path, "w").write(json.dumps(m))
        with pytest.raises(BasisError, match=message):
            Basis.load(folder)
    m = json.loads(good)
    m["resolution"] = [12, 10]
    open(manifest_path, "w").write(json.dumps(m))
    with pytest.raises(BasisError, match=r"image 'base'.*is 12x9, expected 12x10"):
        Basis.load(folder)
    m = json.loads(good)
    del m["images"]["base"]
    open(manifest_path, "w").write(json.dumps(m))
    with pytest.raises(BasisError, match="no 'base' image"):
        Basis.load(folder)
    open(manifest_path, "w").write(good)
    assert Basis.load(folder, scene=scene).keys == manifold.names


def test_manifest_from_another_scene_or_manifold_is_refused(basis1, tmp_path, manifold):
    folder, scene, _ = basis1
    other_scene = _scene(str(tmp_path), "another scene")
    with pytest.raises(BasisError, match="another scene"):
        Basis.load(folder, scene=other_scene)
    other = Manifold(manifold.names, manifold.latent + 0.01, manifold.database, manifold.hashes,
                     manifold.length_scale, manifold.noise, albedos=manifold.albedos)
    other_path = str(tmp_path / "other.npz")
    other.save(other_path)
    with pytest.raises(BasisError, match="another manifold"):
        Basis.load(folder, manifold=other_path)
    with pytest.raises(BasisError, match="another manifold"):
        bl.blend(folder, other_path, x=[0.0, 0.0])
    renamed = Manifold(["a", "b"] + manifold.names[2:], manifold.latent, manifold.database, manifold.hashes)
    with pytest.raises(BasisError, match="does not know"):
        bl.blend(folder, renamed, x=[0.0, 0.0])
    # a mesh the scene uses is part of its identity
    with open(scene, "w") as f:
        f.write('<scene version="3.0.0"><shape type="ply"><string name="filename" value="m.ply"/></shape></scene>')
    open(os.path.join(folder, "m.ply"), "w").write("one")
    h1 = bl.scene_hash(scene)
    open(os.path.join(folder, "m.ply"), "w").write("two")
    assert bl.scene_hash(scene) != h1


def test_missing_and_truncated_images(basis1, manifold):
    folder, _, images = basis1
    name = manifold.names[2]
    path = os.path.join(folder, name + ".exr")
    data = open(path, "rb").read()
    os.remove(path)
    with pytest.raises(BasisError, match=f"image '{name}'.*{name}.exr: image file does not exist"):
        Basis.load(folder)
    big = np.random.default_rng(5).uniform(size=(RES[1], RES[0], 3)).astype(np.float32)
    imageio.write_exr(path, big)
    data = open(path, "rb").read()
    open(path, "wb").write(data[: len(data) - 20])  # the header survives: found when read
    basis = Basis.load(folder)
    img, _ = bl.blend(basis, manifold, x=manifold.latent[0])  # the damaged image is not needed
    assert np.array_equal(img, images["base"] + images[manifold.names[0]])
    with pytest.raises(BasisError, match=f"{name}.exr: truncated or corrupt"):
        bl.blend(basis, manifold, x=manifold.latent[2])
    with pytest.raises(BasisError, match="truncated or corrupt"):
        Basis.load(folder, verify=True)


def test_manifest_helpers(tmp_path, small_manifold):
    scene = _scene(str(tmp_path))
    a = bl.make_manifest(scene, small_manifold, (4, 3), 8, "llvm_ad_rgb", 1, 8, "onepass", ["material"])
    assert a["scene"] == os.path.abspath(scene) and a["manifold_hash"] == bl.file_hash(small_manifold)
    path = bl.write_manifest(str(tmp_path), a)
    assert bl.read_manifest(str(tmp_path)) == a and path.endswith("manifest.json")
    b = dict(a, spp=16, images={"base": {"file": "base.exr", "time_s": 1.0}})
    assert bl.manifest_differences(a, b) == ["spp"]
    with pytest.raises(BasisError, match="mode"):
        bl.make_manifest(scene, small_manifold, (4, 3), 8, "llvm_ad_rgb", 1, 8, "fast", ["material"])
    with pytest.raises(BasisError, match="must name 2 material"):
        bl.write_manifest(str(tmp_path), dict(a, targets=["a", "b"], images={"x": {"file": "x.exr", "time_s": 0}}))
    assert bl.read_manifest(str(tmp_path)) == a  # the refused write left the old manifest
    assert bl.image_key(["gold-paint", "chrome"]) == "gold-paint+chrome"


# -------------------------------------------------------------- multilinear

def test_multilinear_two_target_blend(tmp_path, small_manifold, manifold):
    names = manifold.names
    keys = [a + "+" + b for a in names for b in names]
    folder, _, images = _make_basis(str(tmp_path / "two"), small_manifold, keys, np.random.default_rng(4),
                                    targets=("cup", "saucer"), with_base=False)
    basis = Basis.load(folder, manifold=manifold)
    assert basis.p == 2 and basis.materials == [sorted(names)] * 2
    stack = np.stack([[images[a + "+" + b] for b in names] for a in names]).astype(np.float64)
    x = np.array([manifold.latent[0] * 0.6 + manifold.latent[3] * 0.4, manifold.latent.mean(0)])
    img, info = bl.blend(basis, manifold, x=x, prune=0.0)
    _, W = manifold.weights(x)
    assert np.allclose(img, np.einsum("i,j,ijhwc->hwc", W[0], W[1], stack), rtol=1e-5, atol=1e-5)
    assert len(info["weights"]) == 2
    img2, _ = bl.blend(basis, manifold, x=x.ravel(), prune=0.0)  # p*q numbers in target order
    assert np.array_equal(img, img2)
    # training points of both targets: exactly the image of that pair
    img, info = bl.blend(basis, manifold, x=[manifold.latent[2], manifold.latent[5]])
    assert np.array_equal(img, images[names[2] + "+" + names[5]]) and info["keys"] == [names[2] + "+" + names[5]]
    with pytest.raises(BasisError, match=r"needs 4 numbers"):
        bl.blend(basis, manifold, x=manifold.latent[0])
    with pytest.raises(BasisError, match="summing to 1 per target"):
        bl.blend(basis, manifold, w=np.ones((2, manifold.n)))
    # a pair missing from the basis, with weight: refused, naming it
    m = bl.read_manifest(folder)
    del m["images"][names[2] + "+" + names[5]]
    bl.write_manifest(folder, m)
    with pytest.raises(BasisError, match=f"{names[2]}\\+{names[5]}"):
        bl.blend(folder, manifold, x=[manifold.latent[2], manifold.latent[5]])


# -------------------------------------------------------------------- path

def test_blend_path_and_contact_sheet(basis1, manifold, tmp_path):
    from PIL import Image
    folder, _, images = basis1
    a, b = manifold.names[1], manifold.names[4]
    seq, xs, info = bl.blend_path(folder, manifold, a, b, steps=5)
    assert seq.shape == (5, RES[1], RES[0], 3)
    assert np.allclose(xs[2], 0.5 * (manifold.latent[1] + manifold.latent[4]))
    assert np.array_equal(seq[0], images["base"] + images[a]) and np.array_equal(seq[-1], images["base"] + images[b])
    mid, _ = bl.blend(folder, manifold, x=xs[2])
    assert np.allclose(seq[2], mid, rtol=1e-6, atol=1e-6)
    sheet = str(tmp_path / "sheet.png")
    bl.write_contact_sheet(sheet, seq, labels=[f"{i}" for i in range(5)], columns=5, pad=2)
    assert Image.open(sheet).size == (5 * RES[0] + 6 * 2, RES[1] + 14 + 2 * 2)
    with pytest.raises(BasisError, match="steps"):
        bl.blend_path(folder, manifold, a, b, steps=1)


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


def test_cli_path_writes_sequence_and_sheet(basis1, manifold, tmp_path, cli, capsys):
    folder, _, _ = basis1
    out = str(tmp_path / "seq" / "seq.exr")
    cli.main(["--basis", folder, "--path", manifold.names[0], manifold.names[1], "--steps", "4", "--out", out])
    assert sorted(os.listdir(tmp_path / "seq")) == ["seq_0.exr", "seq_1.exr", "seq_2.exr", "seq_3.exr", "seq_sheet.png"]
    assert "4 images blended" in capsys.readouterr().out


def test_cli_bad_input_overwrites_nothing(basis1, manifold, tmp_path, cli, capsys):
    folder, _, _ = basis1
    out = str(tmp_path / "img.exr")
    for name in ("img.exr", "img_error.exr", "img_error.png"):
        open(str(tmp_path / name), "wb").write(b"precious")
    bad_ref = str(tmp_path / "ref.exr")
    open(bad_ref, "wb").write(b"v/1\x01" + b"\0" * 30)
    other_scene = _scene(str(tmp_path), "other")
    other_manifold = str(tmp_path / "other.npz")
    Manifold(manifold.names, manifold.latent * 1.01, manifold.database, manifold.hashes).save(other_manifold)
    x = ["--x", "0.1", "0.2"]
    cases = [(["--x", "0.1", "0.2", "0.3"], "needs 2 numbers"),
             (x + ["--reference", bad_ref], "ref.exr: truncated or corrupt"),
             (x + ["--reference", str(tmp_path / "none.exr")], "none.exr: image file does not exist"),
             (x + ["--scene", other_scene], "another scene"),
             (x + ["--manifold", other_manifold], "another manifold")]
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

def test_render_reference_is_the_interpolated_material(small_manifold, manifold, tmp_path):
    """On the convex sphere scene (no path scatters twice off the sphere) the full-GI
    reference of x equals, within noise, the affine blend of full renders of the training
    materials (sum w_i = 1, so each full render brings one copy of the base). x is a
    genuine mix of two materials whose interpolated table has no negative bins for the
    plugin to clamp (clamping is the one non-linearity)."""
    scene = os.path.join(ROOT, "scenes", "sphere.xml")
    res, spp = 24, 32
    renders = np.stack([bl.render_reference(scene, small_manifold, x, spp, seed=1 + i, resolution=(res, res))
                        for i, x in enumerate(manifold.latent)])
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
    ref = bl.render_reference(scene, small_manifold, x, spp, seed=100, resolution=(res, res))
    ref2 = bl.render_reference(scene, small_manifold, x, spp, seed=200, resolution=(res, res))
    noise = metrics.rel_mse(ref2, ref)
    err = metrics.rel_mse(blended, ref)
    assert err < 2.0 * noise
    assert np.allclose(blended.mean(axis=(0, 1)), ref.mean(axis=(0, 1)), rtol=0.02)
    # the material really is x: every training material's render is further off
    assert min(metrics.rel_mse(r, ref) for r in renders) > 2.0 * err
    with pytest.raises(BasisError, match="renders 256x256, not 24x12"):
        bl.render_reference(scene, small_manifold, x, spp, resolution=(24, 12))
    with pytest.raises(BasisError, match="manifold .* does not exist"):
        bl.render_reference(scene, str(tmp_path / "none.npz"), x, spp)

"""match: the latent point of a target image on a basis (inverse rendering), on small synthetic bases."""

import json
import os
import shutil

import numpy as np
import pytest
from helpers import write_basis

from mitsuba_manifold.apps.cli import match as cli
from mitsuba_manifold.basis import blend as bl
from mitsuba_manifold.basis.folder import BASE, Basis
from mitsuba_manifold.basis.inverse import match as mt
from mitsuba_manifold.basis.inverse import objectives as image_error
from mitsuba_manifold.basis.inverse import search as latent
from mitsuba_manifold.errors import InputError, MismatchError
from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.manifold.model import Manifold

RES = (20, 16)  # width, height


@pytest.fixture(scope="module")
def manifold(small_manifold_paper):
    """The paper's GP weights: the exact-recovery tests need weights that are not stationary at
    the training points (the default Shepard weights are flat there, so x is found to ~1e-6)."""
    return Manifold.load(small_manifold_paper)


def _smooth_images(rng, n):
    """``n`` positive images with smooth, material-specific structure (like renders)."""
    h, w = RES[1], RES[0]
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    out = []
    for _ in range(n):
        c = rng.uniform(0.2, 1.0, size=3)
        f = rng.uniform(1, 6, size=2)
        pattern = 0.5 + 0.5 * np.sin(f[0] * xx * 3 + rng.uniform(0, 6)) * np.cos(f[1] * yy * 3)
        out.append((pattern[..., None] * c + 0.05 * rng.uniform(size=(h, w, 3))).astype(np.float32))
    return out


def _make_basis(folder, manifold_path, names, seed=1, targets=("material",), keys=None):
    keys = [BASE] + list(names) if keys is None else keys
    images = dict(zip(keys, _smooth_images(np.random.default_rng(seed), len(keys))))
    write_basis(folder, manifold_path, images, targets)
    return folder, images


def _basis_without_manifold(tmp_path, small_manifold_paper, names):
    """A basis whose manifold file has since been deleted."""
    moved = str(tmp_path / "moved.npz")
    shutil.copy(small_manifold_paper, moved)
    folder, _ = _make_basis(str(tmp_path / "lost"), moved, names)
    os.remove(moved)
    return folder


@pytest.fixture
def basis(tmp_path, small_manifold_paper, manifold):
    folder, images = _make_basis(str(tmp_path / "basis"), small_manifold_paper, manifold.names)
    return Basis.load(folder, manifold=manifold), images


def _blend(basis, manifold, x):
    return bl.blend(basis, manifold, x=x, prune=0.0)[0].astype(np.float64)


def _interior_point(manifold, a=0, b=1, t=0.35):
    return (1 - t) * manifold.latent[a] + t * manifold.latent[b]


# ------------------------------------------------------------- gradients


@pytest.mark.parametrize(
    "loss,exposure_free,prior",
    [("rel_mse", False, 0.0), ("rel_mse", True, 0.05), ("log", False, 0.0), ("log", True, 0.05)],
)
def test_match_objective_gradient_matches_finite_differences(
    basis, manifold, loss, exposure_free, prior
):
    b, _ = basis
    target = 1.3 * _blend(b, manifold, _interior_point(manifold, 2, 5))
    mask = np.ones(target.shape[:2])
    mask[:5] = 0.0
    obj = image_error.objectives(b, manifold, target, mask, loss, exposure_free)[0]
    fun, _ = latent.evaluator(manifold, obj, prior)
    x0 = _interior_point(manifold, 0, 3, 0.6) + 0.05
    value, grad = fun(x0)
    assert value > 1e-4  # far from the optimum: a real gradient
    h = 1e-5
    fd = [(fun(x0 + h * e)[0] - fun(x0 - h * e)[0]) / (2 * h) for e in np.eye(manifold.q)]
    assert np.allclose(grad, fd, rtol=2e-3, atol=1e-4 * np.abs(grad).max())


def test_quadratic_form_equals_the_direct_relative_mse(basis, manifold):
    b, _ = basis
    target = _blend(b, manifold, _interior_point(manifold, 1, 4)) * 0.8
    mask = np.random.default_rng(3).uniform(size=target.shape[:2])
    mask[mask < 0.3] = 0.0
    for exposure_free in (False, True):
        obj = image_error.objectives(b, manifold, target, mask, "rel_mse", exposure_free)[0]
        x = _interior_point(manifold, 2, 6)
        err, _, s = obj(manifold.weights(x)[1])
        direct = image_error.masked_rel_mse(s * _blend(b, manifold, x), target, mask)
        assert err == pytest.approx(direct, rel=1e-6)
        assert (s == 1.0) != exposure_free


@pytest.mark.parametrize("exposure_free", [False, True])
def test_log_objectives_are_those_of_the_images_and_their_masked_box_averages(
    basis, manifold, exposure_free
):
    """The log loss's objectives hold the luminance of every image over the masked pixels, and
    the search's that of the mask-weighted ``f x f`` box averages of each image; every material
    alone scores as the batch of the identity, exactly."""
    b, _ = basis
    target = _blend(b, manifold, _interior_point(manifold, 1, 4)) * 0.8
    mask = np.random.default_rng(3).uniform(size=target.shape[:2])
    mask[mask < 0.3] = 0.0
    mask[:4, :4] = 0.0  # a box with no weight: left out of the search
    keys = [BASE] + b.material_keys(manifold.names)
    full, search = image_error.objectives(b, manifold, target, mask, "log", exposure_free, 2)
    wp = image_error.pool(mask[..., None], 2)[..., 0]
    for obj, f, on in ((full, 1, mask > 0), (search, 2, wp > 0)):
        images = [image_error.masked_pool(b.image(k), mask[..., None], f) for k in keys]
        lum = np.stack([img[on] @ image_error.LUMINANCE for img in images])
        np.testing.assert_allclose(obj.A, lum, rtol=1e-12, atol=1e-300)
        errs, scales = obj.singles()
        ref_errs, ref_scales = obj.batch(np.eye(manifold.n))
        assert np.array_equal(errs, ref_errs) and np.array_equal(scales, ref_scales)
    assert search.A.shape[1] == int((wp > 0).sum()) < wp.size
    W = np.random.default_rng(4).dirichlet(np.ones(manifold.n), size=4)
    for obj in (full, search):  # every point in one product, as one at a time
        errs, scales = obj.evaluate(W)
        one = np.array([obj(w)[::2] for w in W])
        np.testing.assert_allclose(np.stack([errs, scales], 1), one, rtol=1e-12)
    rel = image_error.objectives(b, manifold, target, mask, "rel_mse", exposure_free)[0]
    assert np.array_equal(rel.singles()[0], rel.batch(np.eye(manifold.n))[0])


# ---------------------------------------------------------------- matches


def test_training_material_is_recovered_exactly_from_its_own_blend(basis, manifold):
    b, images = basis
    for i, name in enumerate(manifold.names):
        target = images[BASE] + images[name]
        r = mt.match(b, target, starts=3)
        assert np.array_equal(r.x, manifold.latent[i]) and r.from_start is None
        assert r.single.name == name and r.error < 1e-12 and r.rel_mse < 1e-12
        assert np.array_equal(r.weights, np.eye(manifold.n)[i])
        assert r.variance < 2 * manifold.noise
    text = repr(r)  # a short summary, not the image's pixels
    assert len(text) < 400 and name in text and "MatchResult(x=[" in text


def test_interior_point_is_recovered(basis, manifold):
    b, _ = basis
    x_true = _interior_point(manifold, 0, 1)
    r = mt.match(b, _blend(b, manifold, x_true))
    assert r.error < 1e-9 and r.from_start is not None
    assert np.allclose(r.x, x_true, atol=1e-4)
    assert r.error < 1e-6 * r.single.error
    assert np.allclose(r.image, _blend(b, manifold, r.x), atol=1e-5)
    near = mt.match(
        b, _blend(b, manifold, x_true), scan=0, starts=3
    )  # the training points as starts
    best = manifold.latent[near.single.index]
    order = np.argsort(np.linalg.norm(manifold.latent - best, axis=1))[:3]
    assert np.allclose([s["x0"] for s in near.starts], manifold.latent[order], atol=1e-5)
    d = r.to_dict(manifold)
    assert json.loads(json.dumps(d))["x"] == pytest.approx(list(r.x))
    assert [n for n, _ in d["nearest"]][:1] == [
        manifold.names[int(np.argmin(np.linalg.norm(manifold.latent - r.x, axis=1)))]
    ]


def test_masked_match_ignores_what_is_outside_the_mask(basis, manifold):
    b, _ = basis
    x_true = _interior_point(manifold, 3, 6, 0.5)
    target = _blend(b, manifold, x_true)
    mask = np.zeros(target.shape[:2])
    mask[4:12, 5:15] = 1.0
    garbled = target.copy()
    garbled[mask == 0] = np.random.default_rng(7).uniform(0, 5, size=((mask == 0).sum(), 3))
    r = mt.match(b, garbled, mask=mask)
    assert r.n_pixels == int(mask.sum())
    assert r.error < 1e-8 and np.allclose(r.x, x_true, atol=1e-3)
    unmasked = mt.match(b, garbled)
    assert unmasked.error > 1e3 * max(r.error, 1e-12)


@pytest.mark.parametrize("loss", ["rel_mse", "log"])
def test_exposure_free_match_finds_point_and_exposure(basis, manifold, loss):
    b, _ = basis
    x_true = _interior_point(manifold, 4, 7, 0.4)
    target = 3.7 * _blend(b, manifold, x_true)
    r = mt.match(b, target, exposure_free=True, loss=loss, downsample=2)
    assert np.allclose(r.x, x_true, atol=1e-3)
    assert r.exposure == pytest.approx(3.7, rel=1e-3) and r.rel_mse < 1e-6
    fixed = mt.match(b, target, loss=loss)
    assert fixed.exposure == 1.0 and fixed.error > 1e3 * max(r.error, 1e-12)


def test_prior_pulls_towards_the_data(basis, manifold):
    b, _ = basis
    far = manifold.latent.mean(axis=0) + np.array([0.0, 1.5]) + manifold.latent.std(axis=0)
    target = _blend(b, manifold, far) * 1.0
    free = mt.match(b, target)
    held = mt.match(b, target, prior=1.0)
    assert held.variance < free.variance
    assert held.objective == pytest.approx(held.error + 1.0 * held.variance)


# -------------------------------------------------------------- bad input


def test_bad_inputs_are_clear_errors(basis, manifold, tmp_path, small_manifold_paper):
    b, images = basis
    target = _blend(b, manifold, manifold.latent[0])
    with pytest.raises(InputError, match=r"`image` is 20x15, the basis is 20x16"):
        mt.match(b, target[:-1])
    nan = target.copy()
    nan[3, 4, 1] = np.nan
    with pytest.raises(InputError, match=r"1 pixels with NaN or Inf"):
        mt.match(b, nan)
    with pytest.raises(InputError, match=r"mask selects no pixel \(all zero\)"):
        mt.match(b, target, mask=np.zeros(target.shape[:2]))
    with pytest.raises(InputError, match=r"mask is 3x3, the image to match is 20x16"):
        mt.match(b, target, mask=np.ones((3, 3)))
    for kwargs, msg in (
        ({"loss": "l1"}, "`loss` must be one of"),
        ({"prior": -1.0}, "`prior` must be"),
        ({"starts": 0}, "`starts` must be"),
        ({"scan": -1}, "`scan` must be"),
        ({"loss": "log", "downsample": 0}, "`downsample` must be"),
    ):
        with pytest.raises(InputError, match=msg):
            mt.match(b, target, **kwargs)
    # a basis missing materials, and one whose manifold is gone
    part, _ = _make_basis(str(tmp_path / "part"), small_manifold_paper, manifold.names[:3])
    with pytest.raises(InputError, match=r"lacks the images of 5 of the manifold's 8 materials"):
        mt.match(part, target)
    lost = _basis_without_manifold(tmp_path, small_manifold_paper, manifold.names)
    with pytest.raises(MismatchError, match=r"its manifold .*moved.npz no longer exists"):
        mt.match(lost, target)
    two, _ = _make_basis(
        str(tmp_path / "two"),
        small_manifold_paper,
        [],
        targets=("a", "b"),
        keys=[f"{p}+{q}" for p in manifold.names[:2] for q in manifold.names[:2]],
    )
    with pytest.raises(InputError, match=r"has 2 targets"):
        mt.match(two, target[:, :, :])


def test_the_image_to_match_by_its_former_name_target_still_works_and_warns(basis, manifold):
    b, _ = basis
    image = _blend(b, manifold, manifold.latent[0])
    new = mt.match(b, image=image, starts=1, scan=0)
    with pytest.warns(
        DeprecationWarning, match=r"match\(target=...\) is now spelled match\(image=...\)"
    ):
        old = mt.match(b, target=image, starts=1, scan=0)
    np.testing.assert_array_equal(old.x, new.x)
    with pytest.raises(TypeError, match="give `image` only"):
        mt.match(b, image, target=image)
    errors, _ = mt.single_material_errors(b, image)
    with pytest.warns(DeprecationWarning, match="single_material_errors"):
        np.testing.assert_array_equal(mt.single_material_errors(b, target=image)[0], errors)


def test_8bit_target_is_decoded_and_clipped_pixels_dropped(tmp_path):
    u8 = np.zeros((4, 5, 3), dtype=np.uint8)
    u8[..., 0] = 128
    u8[1, 2] = 255
    imageio.write_png(str(tmp_path / "t.png"), u8)
    img, clipped = mt.read_target(str(tmp_path / "t.png"))
    assert img[0, 0, 0] == pytest.approx(((128 / 255 + 0.055) / 1.055) ** 2.4, rel=1e-6)
    assert clipped.sum() == 1 and clipped[1, 2]
    assert np.allclose(
        imageio.srgb_encode(imageio.srgb_decode(np.linspace(0, 1, 11))), np.linspace(0, 1, 11)
    )
    with pytest.raises(InputError, match="not a readable image"):
        open(str(tmp_path / "bad.png"), "wb").write(b"nope")
        mt.read_target(str(tmp_path / "bad.png"))


# -------------------------------------------------------------------- CLI


def test_cli_writes_blend_sheet_and_json(basis, manifold, tmp_path, capsys):
    b, _ = basis
    x_true = _interior_point(manifold, 0, 1)
    tpath = str(tmp_path / "target.exr")
    imageio.write_exr(tpath, 2.0 * _blend(b, manifold, x_true))
    mpath = str(tmp_path / "mask.png")
    m = np.zeros((RES[1], RES[0], 3), dtype=np.uint8)
    m[2:14, 3:17] = 255
    imageio.write_png(mpath, m)
    out, js = str(tmp_path / "o" / "best.exr"), str(tmp_path / "best.json")
    assert (
        cli.main(
            [
                "--basis",
                b.folder,
                "--target",
                tpath,
                "--mask",
                mpath,
                "--exposure-free",
                "--out",
                out,
                "--png",
                "--json",
                js,
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    text = captured.out
    # --target: the former spelling of --image, still read
    assert "note: --target is now spelled --image" in captured.err
    assert (
        "best latent point" in text
        and "fitted exposure x2" in text
        and "nearest training materials" in text
    )
    got = json.load(open(js))
    assert np.allclose(got["x"], x_true, atol=1e-3) and got["exposure"] == pytest.approx(
        2.0, rel=1e-3
    )
    assert got["mask"] == os.path.abspath(mpath) and len(got["weights"]) == manifold.n
    assert np.allclose(imageio.read_exr(out), _blend(b, manifold, got["x"]), atol=1e-4)
    assert os.path.isfile(str(tmp_path / "o" / "best_sheet.png"))


def test_cli_bad_input_writes_nothing(basis, manifold, tmp_path, capsys, small_manifold_paper):
    b, _ = basis
    good = str(tmp_path / "good.exr")
    imageio.write_exr(good, _blend(b, manifold, manifold.latent[2]))
    small = str(tmp_path / "small.exr")
    imageio.write_exr(small, np.ones((8, 8, 3)))
    nan = str(tmp_path / "nan.exr")
    import OpenEXR  # write_exr refuses NaN: write one through OpenEXR directly

    img = np.ones((RES[1], RES[0], 3), dtype=np.float32)
    img[0, 0, 0] = np.nan
    OpenEXR.File(
        {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"RGB": img}
    ).write(nan)
    black = str(tmp_path / "black.png")
    imageio.write_png(black, np.zeros((RES[1], RES[0], 3), dtype=np.uint8))
    out, js = str(tmp_path / "best.exr"), str(tmp_path / "best.json")
    outs = ["--out", out, "--json", js]
    cases = [
        (["--image", small] + outs, "small.exr is 8x8, the basis is 20x16"),
        (["--image", nan] + outs, "NaN or Inf"),
        (["--image", good, "--mask", black] + outs, "selects no pixel (all zero)"),
        (["--image", str(tmp_path / "none.exr")] + outs, "none.exr: image file does not exist"),
        (["--image", good, "--out", good], "would overwrite an input"),
        (["--image", good, "--out", str(tmp_path / "best.png")], "--out must name an .exr file"),
        (["--image", good, "--png", "--json", js], "give --out"),
    ]
    for extra, message in cases:
        with pytest.raises(SystemExit) as e:
            cli.main(["--basis", b.folder] + extra)
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and err.count("\n") == 1
        assert not os.path.exists(out) and not os.path.exists(js)
    # a basis without its manifold
    lost = _basis_without_manifold(tmp_path, small_manifold_paper, manifold.names)
    with pytest.raises(SystemExit) as e:
        cli.main(["--basis", lost, "--image", good, "--out", out])
    assert e.value.code == 2 and "no longer exists" in capsys.readouterr().err
    assert not os.path.exists(out)


@pytest.mark.parametrize("exposure_free", [False, True])
def test_log_loss_batch_scores_as_one_vector_at_a_time(exposure_free):
    """The float32 batch (the scan) gives each weight vector's error and exposure of the float64
    one-vector objective (the descents), weights below float32's normal range included.
    """
    rng = np.random.default_rng(3)
    n, p = 12, 700
    rows = rng.uniform(0.0, 2.0, size=(n + 1, p)) ** 3
    target = rng.uniform(0.0, 1.5, size=(p, 3))
    weight = rng.uniform(0.0, 1.0, size=p)
    obj = image_error.LogLuminanceMSE(rows, target, weight, exposure_free)
    W = rng.dirichlet(np.ones(n), size=300)
    W[:, 0] = np.where(rng.random(300) < 0.5, 1e-40, W[:, 0])
    errs, scales = obj.batch(W, chunk=64)
    for w, e, s in zip(W, errs, scales):
        e1, _, s1 = obj(w)
        assert e == pytest.approx(e1, rel=1e-4, abs=1e-7) and s == pytest.approx(s1, rel=1e-5)

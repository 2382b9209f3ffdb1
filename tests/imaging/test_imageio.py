"""Image files (EXR, PNG, contact sheets) and image metrics: exact round trips, clear errors, atomic writes."""

import dataclasses
import json
import os

import numpy as np
import pytest

from mitsuba_manifold.errors import FormatError
from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.imaging import metrics


def test_exr_round_trip_is_exact_and_keeps_metadata(tmp_path):
    rng = np.random.default_rng(0)
    img = (rng.normal(size=(7, 11, 3)) * 10.0 ** rng.integers(-6, 6, size=(7, 11, 3))).astype(
        np.float32
    )
    img[0, 0] = [0.0, -0.0, np.finfo(np.float32).max]
    path = str(tmp_path / "a.exr")
    imageio.write_exr(path, img, metadata={"scene": "x.xml", "spp": 64})
    back = imageio.read_exr(path)
    assert back.dtype == np.float32 and back.shape == (7, 11, 3)
    assert np.array_equal(back.view(np.uint32), img.view(np.uint32))  # bit exact, signed zero too
    header = imageio.read_exr_header(path)
    assert (header.width, header.height, header.channels) == (11, 7, ["B", "G", "R"])
    assert header.attributes["scene"] == "x.xml" and json.loads(header.attributes["spp"]) == 64


def test_exr_read_errors_name_the_file(tmp_path):
    img = np.random.default_rng(0).uniform(size=(64, 80, 3)).astype(np.float32)
    good = str(tmp_path / "good.exr")
    imageio.write_exr(good, img)
    data = open(good, "rb").read()
    cases = {
        "missing.exr": (None, "does not exist"),
        "empty.exr": (b"", "not an OpenEXR"),
        "text.exr": (b"hello, not an image" * 10, "not an OpenEXR"),
        "trunc.exr": (data[: len(data) * 2 // 3], "truncated or corrupt"),
        "header.exr": (data[:40], "truncated or corrupt"),
    }
    for name, (content, message) in cases.items():
        path = str(tmp_path / name)
        if content is not None:
            open(path, "wb").write(content)
        with pytest.raises(FormatError, match=message) as e:
            imageio.read_exr(path)
        assert path in str(e.value)
    import OpenEXR

    grey = str(tmp_path / "grey.exr")
    OpenEXR.File(
        {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
        {"Y": img[..., 0].copy()},
    ).write(grey)
    with pytest.raises(FormatError, match=r"grey.exr: EXR has channels \['Y'\], missing RGB"):
        imageio.read_exr(grey)
    with pytest.raises(FormatError, match="missing RGB"):
        imageio.check_exr_header(grey)
    with pytest.raises(FormatError, match="is 80x64, expected 80x65"):
        imageio.check_exr_header(good, (80, 65))


def test_writers_never_leave_a_half_written_file(tmp_path):
    path = str(tmp_path / "keep.exr")
    img = np.ones((4, 5, 3), np.float32)
    imageio.write_exr(path, img)
    before = open(path, "rb").read()
    bad = img.copy()
    bad[1, 1, 1] = np.nan
    with pytest.raises(FormatError, match="NaN"):
        imageio.write_exr(path, bad)
    with pytest.raises(FormatError, match="shape"):
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
    assert metrics.psnr(a, ref) == pytest.approx(
        10 * np.log10(16.0 / (4.26 / 6))
    )  # peak = max(ref) = 4
    assert metrics.psnr(a, ref, peak=1.0) == pytest.approx(10 * np.log10(6 / 4.26))
    assert metrics.max_abs(a, ref) == pytest.approx(2.0)
    assert np.allclose(metrics.error_image(a, ref), np.abs(a - ref))
    s = metrics.compare(a, ref)
    assert s.rel_mse == pytest.approx(rel) and s.max_abs == pytest.approx(2.0)
    assert s.mean_abs == pytest.approx(2.6 / 6) and s.peak == 4.0
    assert metrics.compare(ref, ref).psnr == float("inf")
    # the JSON object keeps the dict's keys, and the result still reads as that dict did
    keys = ["rel_mse", "mse", "psnr", "peak", "max_abs", "mean_abs", "eps"]
    assert list(s.as_dict()) == keys and json.loads(json.dumps(s.as_dict()))["mse"] == s.mse
    assert s["rel_mse"] == s.rel_mse and {**s} == s.as_dict()
    assert "psnr" in s and s.get("psnr") == s.psnr and list(s) == keys and len(s) == 7
    assert dict(s.items()) == s.as_dict() and "nope" not in s and s.get("nope") is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.psnr = 0.0
    with pytest.raises(ValueError, match="shape"):
        metrics.compare(a, ref[:, :1])
    with pytest.raises(ValueError, match="reference contains NaN"):
        metrics.compare(a, np.where(ref == 0, np.nan, ref))


def test_false_colour_error_png(tmp_path):
    from PIL import Image

    rng = np.random.default_rng(0)
    ref = np.zeros((40, 60, 3))
    a = ref + rng.uniform(0.0, 0.2, ref.shape)
    a[1, 2] = 1000.0  # one firefly must not set the scale
    path = str(tmp_path / "err.png")
    vmax = metrics.write_error_png(path, a, ref)
    err = np.abs(a - ref).mean(axis=-1)
    assert vmax == pytest.approx(np.percentile(err, 99)) and vmax < 0.2
    png = Image.open(path)
    assert f"0 .. {vmax:.6g}" in png.text["error-scale"]
    px = np.asarray(png.convert("RGB")).astype(int)
    rgb, _ = metrics.false_colour(err, vmax=vmax)
    assert np.array_equal(px[:40, :60], rgb)  # the image at the top, on the robust scale
    assert np.median(px[:40, :60].sum(axis=-1)) > 200  # not almost black
    assert (
        png.size[0] >= 200 and png.size[1] > 40 + 30
    )  # a legend under it, readable on small images
    bar = px[40 + 6 + 5, 6 : png.size[0] - 6]  # the colour bar's middle row, left to right
    lo, hi = metrics.false_colour(np.array([[0.0, 1.0]]), vmax=1.0)[0][0]
    assert np.array_equal(bar[0], lo) and np.array_equal(bar[-1], hi)
    assert (px[40 + 6 + 10 :] > 150).any()  # tick labels and caption drawn
    assert (
        metrics.write_error_png(path, a, ref, vmax=2.5) == 2.5
    )  # a given scale is kept (denoised beside raw)


# ------------------------------------------------------------------- basis


def test_contact_sheet_labels_stay_under_their_own_tile(tmp_path):
    """Long material names on small tiles wrap (or end in ...) instead of running into the next."""
    from PIL import Image

    images = np.zeros((3, 64, 64, 3), np.float32)
    path = tmp_path / "sheet.png"
    imageio.write_contact_sheet(
        path, images, labels=["specular-yellow-phenolic-and-more"] * 3, columns=3, pad=4
    )
    sheet = np.asarray(Image.open(path).convert("RGB"))
    labels = sheet[4 + 64 : -4]  # the label band under the tiles
    assert (labels > 100).any()  # the labels are drawn
    for c in range(1, 3):  # the gutters between tiles stay background
        gutter = labels[:, c * 68 : c * 68 + 4]
        assert (gutter == 32).all()


def test_contact_sheet_labels_keep_their_fields_on_lines_of_their_own(tmp_path):
    """Main-job labels on 64 px tiles: one field per line, never cut inside a field; the title
    (the two end materials) above the grid."""
    from PIL import Image, ImageDraw

    from mitsuba_manifold.apps import gi_comparison
    from mitsuba_manifold.basis.blend import path_labels

    length = ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength
    rows = [{"t": 2.73, "albedo": [0.31, 0.188, 0.167], "negative_fraction": 0.125}]
    (label,) = gi_comparison.extrapolation_labels(rows)
    assert imageio._label_lines(label, 62, length) == ["t = 2.73", "albedo 0.22", "neg. 12.5%"]
    labels = path_labels(("alum-bronze", "white-paint"), 5)
    assert imageio._label_lines(labels[0], 62, length) == ["t = 0.00", "alum-bronze"]
    assert labels[-1].endswith("white-paint") and labels[2] == "t = 0.50"
    assert imageio._label_lines("a\nb\nc\nd\ne", 62, length, max_lines=3) == [
        "a",
        "b",
        "c d e",
    ]  # the rest joined
    assert imageio._label_lines("a\nb\n" + "c" * 30 + "\nd", 62, length, max_lines=3)[-1].endswith(
        "..."
    )
    plain, titled = tmp_path / "plain.png", tmp_path / "titled.png"
    images = np.zeros((5, 64, 64, 3), np.float32)
    imageio.write_contact_sheet(plain, images, labels=labels, columns=5)
    imageio.write_contact_sheet(
        titled, images, labels=labels, columns=5, title="alum-bronze to white-paint"
    )
    a, b = (np.asarray(Image.open(p).convert("RGB")) for p in (plain, titled))
    assert (
        b.shape[0] > a.shape[0] and (b[: b.shape[0] - a.shape[0]] > 150).any()
    )  # the title, drawn
    assert np.array_equal(a[4:], b[b.shape[0] - a.shape[0] + 4 :])  # above the same grid


def test_control_characters_in_names_are_drawn_escaped_on_one_line(tmp_path):
    """A material name holding a newline, a tab or a NUL (issue 20): the sheet is drawn (no PIL
    error on a multi-line title), the name stays one field of its label, escaped."""
    from PIL import Image, ImageDraw

    from mitsuba_manifold.basis.blend import path_labels

    length = ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength
    labels = path_labels(("evil\nname", "tab\there\x00"), 3)
    assert imageio._label_lines(labels[0], 200, length) == ["t = 0.00", "evil\\nname"]
    assert imageio._label_lines(labels[-1], 200, length) == ["t = 1.00", "tab\\there\\x00"]
    assert imageio.printable("a\u202eb ü") == "a\\u202eb ü"
    path = tmp_path / "sheet.png"
    imageio.write_contact_sheet(
        path,
        np.zeros((3, 16, 16, 3), np.float32),
        labels=labels,
        title="evil\nname (t = 0) to tab\there\x00 (t = 1)",
    )
    assert Image.open(path).size[0] > 0


def test_pass_standard_error_predicts_the_spread_of_independent_means():
    """z-test: the estimated standard error of a mean of unequal passes is the true one."""
    rng = np.random.default_rng(7)
    sigma, n = 0.3, (8, 8, 8, 5)  # a sample's standard deviation; spp of each pass
    truth = rng.uniform(0.5, 2.0, (32, 32, 3))

    def mean_and_se():
        total = total2 = 0.0
        for k in n:  # a pass of k samples: its image's variance is sigma^2 / k
            img = truth + rng.normal(0.0, sigma / np.sqrt(k), truth.shape)
            total, total2 = total + k * img, total2 + k * img * img
        return total / sum(n), metrics.pass_standard_error(total, total2, sum(n), len(n))

    a, se_a = mean_and_se()
    b, _ = mean_and_se()
    exact = sigma / np.sqrt(sum(n))
    # mean of se^2 over 3072 values, each with 3 degrees of freedom: relative sd sqrt(2/3/3072)
    assert abs(np.mean(se_a**2) / exact**2 - 1) < 5 * np.sqrt(2 / 3 / se_a.size)
    # two independent means differ by sqrt(2) standard errors
    z = (a - b) / np.sqrt(2 * exact**2)
    assert abs(np.mean(z**2) - 1) < 5 * np.sqrt(2 / z.size)
    assert np.isnan(metrics.pass_standard_error(truth, truth**2, 4, 1)).all()


def test_noise_agreement_tells_an_exact_image_from_a_biased_one():
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.2, 1.0, (24, 24, 3))
    se = np.full_like(truth, 0.05)
    noisy_ref = truth + rng.normal(0.0, 0.05, truth.shape)
    exact = metrics.noise_agreement(truth, noisy_ref, se)
    assert exact.agrees is True and exact.noise_rel_mse > 0
    assert exact.excess_rel_mse < 0.2 * exact.noise_rel_mse
    biased = metrics.noise_agreement(truth * 1.2, noisy_ref, se)
    assert biased.agrees is False and biased.excess_rel_mse > exact.noise_rel_mse
    one_pass = metrics.noise_agreement(truth, noisy_ref, np.full_like(truth, np.nan))
    assert one_pass.as_dict() == {
        "rel_mse": None,
        "noise_rel_mse": None,
        "excess_rel_mse": None,
        "agrees": None,
    }

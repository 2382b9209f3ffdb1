"""The explorer's drag frames: the lone bright (or dark) pixels of a summed blend's part beyond
L1- are clamped, and nothing else changes."""

import numpy as np
import pytest

from mitsuba_manifold.apps.explore import encode, fireflies


def _smooth(rng, h=48, w=40):
    yy, xx = np.mgrid[0:h, 0:w] / 10.0
    base = 0.3 + 0.1 * np.sin(yy)[..., None] * np.cos(xx)[..., None] * np.array([1.0, 0.8, 0.6])
    return (base * (1 + 0.05 * rng.standard_normal((h, w, 3)))).astype(np.float32)


def test_a_lone_bright_pixel_is_clamped_and_nothing_else_changes():
    rng = np.random.default_rng(3)
    img = _smooth(rng)
    img[:, 30:] *= 6.0  # a sharp edge: each pixel on it has a neighbour as bright
    img[10:12, 5:7] = [4.0, 3.0, 1.0]  # a 2x2 highlight: each of its pixels has a bright neighbour
    img[30, 12] = [40.0, 20.0, 2.0]  # a firefly
    out, n = fireflies.clamp(img)
    assert n == 1
    changed = np.any(out != img, axis=2)
    assert changed.sum() == 1 and changed[30, 12]
    lum = out @ fireflies.LUMA
    ring = np.delete(lum[29:32, 11:14].ravel(), 4)  # its eight neighbours
    limit = fireflies.FACTOR * max(ring.max(), (img @ fireflies.LUMA).mean())
    assert lum[30, 12] == np.float32(limit) or abs(lum[30, 12] - limit) <= 1e-5 * limit
    np.testing.assert_allclose(
        out[30, 12] / out[30, 12].sum(), img[30, 12] / img[30, 12].sum(), rtol=1e-5
    )  # its colour kept
    _, none = fireflies.clamp(_smooth(rng))
    assert none == 0


def test_drag_image_clamps_the_part_beyond_l1_only_both_signs():
    """The L1- part keeps its own one-pixel highlight (the rest image shows it too); the
    L2+ part loses a lone bright and a lone dark pixel; the other pixels are bit for bit the
    summed blend."""
    rng = np.random.default_rng(4)
    l1 = _smooth(rng)
    l1[5, 5] = [30.0, 30.0, 30.0]  # a one-pixel highlight of the L1- part
    extra = 0.2 * _smooth(rng)
    extra[20, 20] = [25.0, 10.0, 1.0]  # bright firefly
    extra[35, 8] = [-3.0, -2.0, -2.5]  # dark firefly (a negative cross term)
    image = l1 + extra
    out, n = fireflies.drag_image(image, l1)
    assert n == 2
    changed = np.any(out != image, axis=2)
    assert set(zip(*np.nonzero(changed))) == {(20, 20), (35, 8)}
    assert out[5, 5].tolist() == image[5, 5].tolist()
    assert out[20, 20].sum() < 0.1 * image[20, 20].sum()
    assert (out[35, 8] > 0).all() and out[35, 8].sum() > l1[35, 8].sum() - 0.2  # not dark any more
    _, none = fireflies.drag_image(l1 + 0.2 * _smooth(rng), l1)
    assert none == 0


def _drag_image_by_filter(image, l1, factor=fireflies.FACTOR):
    """The clamp computed independently: one maximum filter over each whole part's luminance
    (a matrix product), each part clamped as a whole image and the parts summed back onto l1."""
    from scipy.ndimage import maximum_filter

    ring = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], bool)
    extra = image - l1
    out = np.zeros_like(extra)
    for sign in (1.0, -1.0):
        part = np.maximum(sign * extra, 0.0)
        lum = part @ fireflies.LUMA
        near = maximum_filter(lum, footprint=ring, mode="nearest")
        limit = factor * np.maximum(near, float(lum.mean()))
        over = lum > limit
        part[over] *= (limit[over] / lum[over])[:, None]
        out += sign * part
    return l1 + out


@pytest.mark.parametrize("share", [0.001, 0.2])  # few bright pixels, and many
def test_drag_image_is_the_clamp_of_each_whole_part(share):
    """The frame equals the clamp computed over the whole image (to float32 rounding: 1e-6 of the
    pixel's value; in 8-bit sRGB the same level), with fireflies of both signs at the border,
    in corners and side by side."""
    rng = np.random.default_rng(5)
    l1 = _smooth(rng, 64, 80)
    extra = 0.2 * _smooth(rng, 64, 80) - 0.1
    hot = rng.random(extra.shape[:2]) < share
    extra[hot] *= rng.choice([-30.0, 30.0], size=(hot.sum(), 1))
    for y, x in ((0, 0), (63, 79), (0, 40), (31, 0), (20, 20), (20, 21)):
        extra[y, x] = rng.choice([-1.0, 1.0]) * rng.uniform(5, 50, 3)
    for k, (dy, dx) in enumerate((a, b) for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b):
        y, x = 8 + 16 * (k // 4), 10 + 18 * (k % 4)  # a bright pair: neither is a firefly
        extra[y, x] = extra[y + dy, x + dx] = 20.0
    image = (l1 + extra).astype(np.float32)
    out, n = fireflies.drag_image(image, l1)
    expect = _drag_image_by_filter(image, l1)
    assert n > 0
    np.testing.assert_allclose(out, expect, rtol=1e-6, atol=1e-6 * np.abs(image).max())
    assert np.array_equal(encode.tonemap(out), encode.tonemap(expect))
    changed = np.any(expect != image, axis=2) & ~np.isclose(expect, image, rtol=1e-6).all(axis=2)
    assert np.array_equal(np.any(out != image, axis=2), changed)


def test_rest_change_finds_visible_noise_and_ignores_faint_or_smooth_light():
    """The estimate of what denoising the part beyond L1- would change: large for visible noise,
    zero for a smooth part (a blur keeps it), below the threshold for faint noise."""
    rng = np.random.default_rng(5)
    l1 = _smooth(rng)
    smooth_extra = 0.05 * np.ones_like(l1)
    assert fireflies.rest_change(l1 + smooth_extra, l1) == 0.0
    faint = 1e-4 * rng.standard_normal(l1.shape).astype(np.float32)
    assert fireflies.rest_change(l1 + faint, l1) <= fireflies.REST_FRACTION
    noisy = 0.05 * rng.standard_normal(l1.shape).astype(np.float32)
    assert fireflies.rest_change(l1 + noisy, l1) > 0.3
    # brighter exposure: the same faint noise may show; the estimate is on the 8-bit image shown
    assert fireflies.rest_change(l1 + faint, l1, exposure=8.0) >= fireflies.rest_change(
        l1 + faint, l1
    )

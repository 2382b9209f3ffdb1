"""The explorer's drag frames: the lone bright (or dark) pixels of a summed blend's part beyond
L1- are clamped, and nothing else changes."""

import numpy as np

from mitsuba_manifold.apps.explore import fireflies


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

"""Fireflies out of the explorer's drag frames, without denoising them.

A full-GI blend's part beyond L1- (the light that touches the material more than once: its
materials' L2+ images and their cross terms) holds the basis's Monte Carlo noise, and at rest
the explorer shows it denoised (:func:`~mitsuba_manifold.basis.denoise.denoised_l2`). A drag
shows it summed (denoising takes longer than a frame), where a rare path through a narrow
peak leaves a lone bright pixel (or, through a negative cross term, a lone dark one): a
firefly, the same one on every frame near that material.
:func:`clamp` takes such pixels down to what their neighbours allow, and :func:`drag_image`
applies it to the part beyond L1- of a summed blend only (the L1- part, which the rest image
shows as it is too, is never touched). A pixel is a firefly when its luminance exceeds
:data:`FACTOR` times the largest of its eight neighbours' (and the image's mean level): a
smooth image, an edge or a highlight wider than one pixel has a neighbour nearly as bright
and is left as it is.

Where a drag rests, the denoised frame costs the server a second or more of CPU at a few hundred
pixels a side, and often changes nothing the 8-bit image shows (a well-sampled basis, a material
whose light beyond L1- is faint). :func:`rest_change` estimates, in milliseconds, what denoising
would change: the part beyond L1- replaced by a box blur of it (:data:`REST_BLUR` pixels; a
denoiser takes the noise, which a blur takes too, and an edge, which it keeps: the estimate errs
towards denoising), both images tonemapped; the explorer skips the denoised frame where fewer
than :data:`REST_FRACTION` of the 8-bit values would change by :data:`REST_LEVELS` or more.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from typing import Any


#: A pixel brighter than this many times its brightest neighbour is a firefly.
FACTOR = 3.0
#: The denoised frame of a drag's rest is made only where the blur estimate (:func:`rest_change`)
#: changes more than this fraction of the 8-bit values by at least this many levels.
REST_FRACTION = 5e-3
REST_LEVELS = 2
#: Side (pixels) of the box blur standing for the denoiser in that estimate.
REST_BLUR = 5
#: Rec. 709 luminance of linear RGB.
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


def luminance(image) -> np.ndarray:
    """Rec. 709 luminance (H, W) of linear RGB ``image`` (H, W, 3), float32 (summed channel by
    channel: a matrix product would start BLAS threads for an image this small).
    """
    img = np.asarray(image, np.float32)
    lum = np.multiply(img[..., 0], LUMA[0])
    lum += np.multiply(img[..., 1], LUMA[1])
    lum += np.multiply(img[..., 2], LUMA[2])
    return lum


def brightest_neighbour(lum) -> np.ndarray:
    """The largest of the eight neighbours of each pixel of ``lum`` (H, W), the border repeated
    beyond the image: the larger of the three-pixel maxima of the rows above and below and of
    the pixels left and right.
    """
    p = np.pad(lum, 1, mode="edge")
    row3 = np.maximum(p[:, :-2], p[:, 1:-1])
    np.maximum(row3, p[:, 2:], out=row3)
    near = np.maximum(row3[:-2], row3[2:])
    np.maximum(near, p[1:-1, :-2], out=near)
    np.maximum(near, p[1:-1, 2:], out=near)
    return near


def _fireflies(lum, factor) -> tuple[np.ndarray, Any]:
    """Flat indices of the fireflies of luminance ``lum`` (H, W) and, per firefly, the luminance
    it is scaled down to: ``factor * max(its brightest neighbour, mean of lum)``.
    """
    limit = np.maximum(brightest_neighbour(lum), np.float32(lum.mean()))
    limit *= np.float32(factor)
    index = np.flatnonzero(lum > limit)
    return index, limit.ravel()[index]


def clamp(image, factor=FACTOR) -> tuple[np.ndarray, int]:
    """``image`` (H, W, 3, not negative) with every firefly scaled down to ``factor`` times its
    brightest neighbour's luminance (floored at the image's mean luminance); the other pixels
    exactly as they were. Returns ``(image, number of pixels changed)``.
    """
    img = np.asarray(image, np.float32)
    lum = luminance(img)
    index, limit = _fireflies(lum, factor)
    if not index.size:
        return img, 0
    out = img.copy()
    flat = out.reshape(-1, 3)
    flat[index] *= (limit / lum.ravel()[index])[:, None]
    return out, int(index.size)


def drag_image(image, l1, factor=FACTOR) -> tuple[Any, int]:
    """A summed full-GI blend ``image`` of one target with the fireflies of its part beyond L1-
    (``image - l1``; ``l1``: the same blend of the L1- images) clamped (:func:`clamp`). That part
    is signed (cross terms, negative weights), so its positive and negative parts are clamped
    apart (a negative firefly is a lone dark pixel): a firefly pixel becomes ``l1 + (positive
    part clamped - negative part clamped)``, every other pixel is ``image`` as it is. Returns
    ``(image, number of pixels changed)``.
    """
    image = np.asarray(image, np.float32)
    l1 = np.asarray(l1, np.float32)
    extra = np.subtract(image, l1)
    pos = np.maximum(extra, 0.0)
    neg = np.subtract(pos, extra, out=extra)  # max(-extra, 0), exactly
    found = []
    for part in (pos, neg):
        lum = luminance(part)
        index, limit = _fireflies(lum, factor)
        scale = np.ones(lum.size, np.float32)
        scale[index] = limit / lum.ravel()[index]
        found.append((index, scale))
    changed = found[0][0].size + found[1][0].size
    if not changed:
        return image, 0
    at = np.union1d(found[0][0], found[1][0])
    p, n = pos.reshape(-1, 3)[at], neg.reshape(-1, 3)[at]
    p *= found[0][1][at, None]
    n *= found[1][1][at, None]
    out = image.copy()
    out.reshape(-1, 3)[at] = l1.reshape(-1, 3)[at] + (p - n)
    return out, changed


def rest_change(image, l1, exposure=0.0, levels=REST_LEVELS, size=REST_BLUR) -> float:
    """The fraction of the 8-bit values of ``image`` (a summed full-GI blend of one target, H x
    W x 3, tonemapped at ``exposure``) that denoising its part beyond L1- (``image - l1``) would
    change by ``levels`` or more, estimated with that part blurred by a ``size``-pixel box
    instead of denoised (module doc).
    """
    from scipy.ndimage import uniform_filter

    from .encode import tonemap

    image = np.asarray(image, np.float32)
    l1 = np.asarray(l1, np.float32)
    smooth = uniform_filter(image - l1, size=(size, size, 1), mode="reflect")
    smooth += l1
    shown = tonemap(image, exposure).astype(np.int16)
    shown -= tonemap(smooth, exposure)
    return float(np.count_nonzero(np.abs(shown) >= levels)) / shown.size

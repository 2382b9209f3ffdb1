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
"""

import numpy as np
from scipy.ndimage import maximum_filter

#: A pixel brighter than this many times its brightest neighbour is a firefly.
FACTOR = 3.0
#: Rec. 709 luminance of linear RGB.
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
_RING = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], bool)  # the eight neighbours


def clamp(image, factor=FACTOR):
    """``image`` (H, W, 3, not negative) with every firefly scaled down to ``factor`` times its
    brightest neighbour's luminance (floored at the image's mean luminance); the other pixels
    exactly as they were. Returns ``(image, number of pixels changed)``.
    """
    img = np.asarray(image, np.float32)
    lum = img @ LUMA
    near = maximum_filter(lum, footprint=_RING, mode="nearest")
    limit = factor * np.maximum(near, float(lum.mean()))
    over = lum > limit
    n = int(over.sum())
    if not n:
        return img, 0
    out = img.copy()
    out[over] *= (limit[over] / lum[over])[:, None]
    return out, n


def drag_image(image, l1, factor=FACTOR):
    """A summed full-GI blend ``image`` of one target with the fireflies of its part beyond L1-
    (``image - l1``; ``l1``: the same blend of the L1- images) clamped (:func:`clamp`). That part
    is signed (cross terms, negative weights), so its positive and negative parts are clamped
    apart (a negative firefly is a lone dark pixel). Returns ``(image, number of pixels changed)``.
    """
    l1 = np.asarray(l1, np.float32)
    extra = np.asarray(image, np.float32) - l1
    out, changed = np.zeros_like(extra), 0
    for sign in (1.0, -1.0):
        part, n = clamp(np.maximum(sign * extra, 0.0), factor)
        out += sign * part
        changed += n
    return ((l1 + out).astype(np.float32), changed) if changed else (image, 0)

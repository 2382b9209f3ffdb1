"""The target of a match and its mask: read from image files and checked against a basis.

A target is linear RGB at the basis' resolution (an EXR as it is; an 8-bit PNG/JPEG
sRGB-decoded, its clipped pixels reported so that the match leaves them out); a mask gives
each pixel a weight in [0, 1] (0: ignored). :func:`mitsuba_manifold.basis.match.match` uses
:func:`check_target` and :func:`check_mask`; the ``match`` tool reads files with
:func:`read_target` and :func:`read_mask`.
"""

import numpy as np

from ..errors import InputError
from ..imaging import io as imageio


def check_target(target, resolution, what="target"):
    """``target`` as float64 (H, W, 3), checked against the basis ``resolution`` (width, height)."""
    arr = np.asarray(target)
    w, h = resolution
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(f"{what} must be an RGB image of shape (height, width, 3), got {arr.shape}")
    if arr.shape[:2] != (h, w):
        raise InputError(f"{what} is {arr.shape[1]}x{arr.shape[0]}, the basis is {w}x{h}: render or "
                         "resize the target to the basis resolution")
    bad = ~np.isfinite(arr).all(axis=-1)
    if bad.any():
        raise InputError(f"{what} has {int(bad.sum())} pixels with NaN or Inf values; fix them or "
                         "leave them out of the image")
    return arr.astype(np.float64)


def check_mask(mask, resolution, what="mask"):
    """Mask weights in [0, 1] as float64 (H, W): (H, W) or (H, W, C) (channels averaged)."""
    w, h = resolution
    arr = np.asarray(mask, dtype=np.float64)
    if arr.ndim == 3:
        arr = arr.mean(axis=-1)
    if arr.shape != (h, w):
        raise InputError(f"{what} is {arr.shape[1] if arr.ndim == 2 else arr.shape}"
                         f"{'x' + str(arr.shape[0]) if arr.ndim == 2 else ''}, the target is {w}x{h}: "
                         "they must have the same size")
    if not np.isfinite(arr).all():
        raise InputError(f"{what} has NaN or Inf values")
    arr = np.clip(arr, 0.0, 1.0)
    if not (arr > 0).any():
        raise InputError(f"{what} selects no pixel (all zero): nothing to match")
    return arr


def read_target(path):
    """A target image: linear EXR, or an 8-bit PNG/JPEG (sRGB-decoded to linear).

    Returns ``(image float32 (H, W, 3), saturated (H, W) bool)``: the pixels of an 8-bit
    image with a channel at 255 (clipped, their true value unknown), to leave out of the
    match; none for an EXR.
    """
    path = str(path)
    if path.lower().endswith(".exr"):
        img = imageio.read_exr(path)
        return img, np.zeros(img.shape[:2], dtype=bool)
    u8 = _read_8bit(path, "RGB", "target")
    return imageio.srgb_decode(u8 / 255.0).astype(np.float32), (u8 == 255).any(axis=-1)


def read_mask(path):
    """A mask image (PNG/JPEG grey or RGB: value / 255; EXR: mean of R, G, B) as (H, W)."""
    path = str(path)
    if path.lower().endswith(".exr"):
        return imageio.read_exr(path).mean(axis=-1)
    return _read_8bit(path, "L", "mask") / 255.0


def _read_8bit(path, mode, what):
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert(mode), dtype=np.float64)
    except FileNotFoundError:
        raise InputError(f"{what} {path}: file does not exist") from None
    except (UnidentifiedImageError, OSError) as e:
        raise InputError(f"{what} {path}: not a readable image ({e})") from None

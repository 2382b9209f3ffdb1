"""Frames for the page: linear radiance to 8-bit sRGB, then JPEG, PNG or raw RGBA bytes.

:func:`tonemap` gives :func:`mitsuba_manifold.imaging.io.tonemap` (scale by ``2**exposure``,
clip, sRGB encode, round) in float32 and a fraction of its time, without a power per
pixel: the 255 linear thresholds where the rounded level steps up are found once (exactly,
against ``imageio``'s own encoding, then rounded up to float32); a table over 16384
buckets of [0, 1] gives the level at each bucket's lower edge, and one comparison with the
next threshold settles the rest (no bucket holds two thresholds; checked at import). The
result is identical to ``imageio.tonemap`` for whole stops of exposure (the scaling is
then exact in float32) and within one level otherwise.
"""

from __future__ import annotations

import io

import numpy as np

from ...imaging.io import srgb_encode

#: Formats a frame can be encoded in (``rgba``: raw bytes, drawn with putImageData).
FORMATS = ("rgba", "jpeg", "png")
MIME = {"rgba": "application/octet-stream", "jpeg": "image/jpeg", "png": "image/png"}
JPEG_QUALITY = 92
PNG_LEVEL = 1
_BUCKETS = 1 << 14


def _level(v) -> np.ndarray:
    """Reference 8-bit level of linear values in [0, 1] (as imageio.tonemap)."""
    return np.round(srgb_encode(np.asarray(v, dtype=np.float64)) * 255.0)


def _tables() -> tuple[np.ndarray, np.ndarray]:
    """Thresholds (float32, the smallest float32 reaching each level; +inf appended) and the
    level at each bucket's lower edge.
    """
    levels = np.arange(1, 256)
    v = (levels - 0.5) / 255.0
    thr = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    for _ in range(64):  # nudge each to the smallest float64 reaching its level
        low = _level(thr) < levels
        below = _level(np.nextafter(thr, 0.0)) >= levels
        if not (low.any() or below.any()):
            break
        thr = np.where(low, np.nextafter(thr, 2.0), np.where(below, np.nextafter(thr, 0.0), thr))
    else:
        raise AssertionError("tonemap thresholds did not settle")
    if np.diff(thr).min() <= 1.0 / (_BUCKETS - 1):
        raise AssertionError("tonemap buckets too coarse for exact rounding")
    thr32 = thr.astype(np.float32)
    thr32 = np.where(thr32.astype(np.float64) < thr, np.nextafter(thr32, np.float32(2)), thr32)
    edges = (np.arange(_BUCKETS) / np.float32(_BUCKETS - 1)).astype(np.float32)
    lower = np.searchsorted(thr32, edges, side="right").astype(np.uint8)
    return np.append(thr32, np.float32(np.inf)), lower


_THRESHOLDS, _LOWER = _tables()


def tonemap(img, exposure=0.0) -> np.ndarray:
    """Linear RGB (..., 3) float to 8-bit sRGB, as :func:`imageio.tonemap` (NaN -> 0), in
    float32 and in place after the one copy of ``img``.
    """
    scale = np.float32(2.0 ** float(exposure))
    v = np.multiply(img, scale, dtype=np.float32) if scale != 1 else np.array(img, np.float32)
    np.fmax(v, np.float32(0.0), out=v)  # fmax/fmin: NaN -> 0, +-inf -> 1, 0
    np.fmin(v, np.float32(1.0), out=v)
    index = np.empty(v.shape, np.int32)
    np.multiply(v, np.float32(_BUCKETS - 1), out=index, casting="unsafe")  # truncated
    level = np.take(_LOWER, index)
    level += v >= np.take(_THRESHOLDS, level)
    return level


def encode(rgb8, fmt) -> bytes:
    """Bytes of an (H, W, 3) uint8 image in ``fmt`` (one of :data:`FORMATS`)."""
    if fmt == "rgba":
        h, w, _ = rgb8.shape
        out = np.full((h, w, 4), 255, dtype=np.uint8)
        out[..., :3] = rgb8
        return out.tobytes()
    from PIL import Image

    buf = io.BytesIO()
    if fmt == "jpeg":
        Image.fromarray(rgb8).save(buf, "JPEG", quality=JPEG_QUALITY)
    elif fmt == "png":
        Image.fromarray(rgb8).save(buf, "PNG", compress_level=PNG_LEVEL)
    else:
        raise ValueError(f"frame format must be one of {FORMATS}, got {fmt!r}")
    return buf.getvalue()


def png_bytes(rgb8) -> bytes:
    """PNG bytes of an 8-bit RGB(A) image (small images of the page: map, slice, error)."""
    return encode(np.ascontiguousarray(rgb8), "png") if rgb8.shape[-1] == 3 else _png_rgba(rgb8)


def _png_rgba(rgba8) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgba8), "RGBA").save(buf, "PNG", compress_level=PNG_LEVEL)
    return buf.getvalue()

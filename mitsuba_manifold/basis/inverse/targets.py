"""The image a match matches and its mask: read from image files and checked against a basis.

The image to match (the functions keep their names ``*_target``) is linear RGB at the basis'
resolution (an EXR as it is; a PNG/JPEG sRGB-decoded at
its depth, 8 bits or a 16-bit greyscale PNG, its clipped pixels reported so that the match
leaves them out; the size checked before any pixel is decoded); a mask gives
each pixel a weight in [0, 1] (0: ignored). :func:`mitsuba_manifold.basis.inverse.match.match` uses
:func:`check_target` and :func:`check_mask`; the ``match`` tool reads files with
:func:`read_target` and :func:`read_mask`.
"""

import struct
import warnings

import numpy as np

from ...errors import InputError
from ...imaging import io as imageio


def check_target(target, resolution, what="image to match"):
    """``target`` as float64 (H, W, 3), checked against the basis ``resolution`` (width, height)."""
    arr = np.asarray(target)
    w, h = resolution
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(
            f"{what} must be an RGB image of shape (height, width, 3), got {arr.shape}"
        )
    if arr.shape[:2] != (h, w):
        raise InputError(
            f"{what} is {arr.shape[1]}x{arr.shape[0]}, the basis is {w}x{h}: render or "
            f"resize the {what} to the basis resolution"
        )
    bad = ~np.isfinite(arr).all(axis=-1)
    if bad.any():
        raise InputError(
            f"{what} has {int(bad.sum())} pixels with NaN or Inf values; fix them or "
            "leave them out of the image"
        )
    if (arr < 0).any() and not (arr > 0).any():
        raise InputError(
            f"{what} holds only negative values (the lowest {float(arr.min()):.3g}) "
            "and no light: a rendered or photographed image has positive linear RGB "
            "(a negated image?)"
        )
    return arr.astype(np.float64)


def check_mask(mask, resolution, what="mask"):
    """Mask weights in [0, 1] as float64 (H, W): (H, W) or (H, W, C) (channels averaged)."""
    w, h = resolution
    arr = np.asarray(mask, dtype=np.float64)
    if arr.ndim == 3:
        arr = arr.mean(axis=-1)
    if arr.shape != (h, w):
        raise InputError(
            f"{what} is {arr.shape[1] if arr.ndim == 2 else arr.shape}"
            f"{'x' + str(arr.shape[0]) if arr.ndim == 2 else ''}, the image to match is {w}x{h}: "
            "they must have the same size"
        )
    if not np.isfinite(arr).all():
        raise InputError(f"{what} has NaN or Inf values")
    arr = np.clip(arr, 0.0, 1.0)
    if not (arr > 0).any():
        raise InputError(f"{what} selects no pixel (all zero): nothing to match")
    return arr


def read_target(path, resolution=None):
    """The image to match: linear EXR, or a PNG/JPEG (sRGB-decoded to linear) read at its depth:
    8 bits, or 16 bits for a greyscale PNG (a 16-bit colour PNG is refused: Pillow would read
    it as 8 bits).

    With ``resolution`` (the basis's ``(width, height)``) the size is checked from the file's
    header before any pixel is decoded; a size beyond memory is refused in any case.

    Returns ``(image float32 (H, W, 3), saturated (H, W) bool)``: the pixels of a PNG/JPEG
    with a channel at its largest code (255, or 65535: clipped, their true value unknown),
    to leave out of the match; none for an EXR.
    """
    path = str(path)
    if path.lower().endswith(".exr"):
        _exr_size(path, resolution, "image to match")
        img = imageio.read_exr(path)
        return img, np.zeros(img.shape[:2], dtype=bool)
    codes, top = _read_coded(path, "image to match", resolution)
    if codes.shape[-1] == 1:
        codes = np.repeat(codes, 3, axis=-1)
    return imageio.srgb_decode(codes / top).astype(np.float32), (codes == top).any(axis=-1)


def read_mask(path, resolution=None):
    """A mask image (PNG/JPEG grey or RGB: value / largest code, 255 or 65535; EXR: mean of
    R, G, B) as (H, W); ``resolution`` as for :func:`read_target`.
    """
    path = str(path)
    if path.lower().endswith(".exr"):
        _exr_size(path, resolution, "mask")
        return imageio.read_exr(path).mean(axis=-1)
    codes, top = _read_coded(path, "mask", resolution)
    return codes.mean(axis=-1) / top


def read_target_and_weight(target_path, mask_path, resolution):
    """The target of a match read from ``target_path`` and its pixel weights: the mask of
    ``mask_path`` (None: every pixel 1), without the target's clipped pixels
    (:func:`read_target`), all checked against ``resolution``.

    Returns ``(target float32 (H, W, 3), weight (H, W), clipped)``: ``clipped`` the number of
    pixels left out because a channel is at its largest code.
    """
    target, clipped = read_target(target_path, resolution)
    target = check_target(target, resolution, what=f"image {target_path}")
    weight = np.ones(target.shape[:2])
    if mask_path:
        weight = check_mask(read_mask(mask_path, resolution), resolution, what=f"mask {mask_path}")
    if clipped.any():
        weight = check_mask(
            weight * ~clipped,
            resolution,
            what=f"mask {mask_path or '(all pixels)'} without the target's clipped pixels",
        )
    return target, weight, int(clipped.sum())


#: The 8 bytes every PNG file starts with.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_header(path):
    """``(width, height, bit depth, colour type, interlace)`` from a PNG's IHDR chunk, or None
    (not a PNG).
    """
    with open(path, "rb") as f:
        head = f.read(29)
    if len(head) < 29 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", head[16:24])
    return width, height, head[24], head[25], head[28]


#: Samples per pixel of each PNG colour type (grey, RGB, palette, grey + alpha, RGBA).
PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
#: The seven passes of Adam7 interlacing: (x0, y0, dx, dy).
ADAM7 = (
    (0, 0, 8, 8),
    (4, 0, 8, 8),
    (0, 4, 4, 8),
    (2, 0, 4, 4),
    (0, 2, 2, 4),
    (1, 0, 2, 2),
    (0, 1, 1, 2),
)


def _png_data_size(width, height, depth, colour, interlace):
    """Bytes of a PNG's decompressed image data: one filter byte and the packed samples per row
    (of each Adam7 pass, when interlaced).
    """
    bits = depth * PNG_CHANNELS.get(colour, 0)
    passes = ADAM7 if interlace else ((0, 0, 1, 1),)
    total = 0
    for x0, y0, dx, dy in passes:
        w, h = -(-(width - x0) // dx), -(-(height - y0) // dy)
        if w > 0 and h > 0:
            total += h * (1 + -(-(w * bits) // 8))
    return total


def _check_png_data(what, path, header):
    """Refuse a PNG whose image data holds fewer rows than its header says (Pillow would decode
    the missing rows as black): the IDAT chunks' zlib stream is decompressed and counted.
    """
    import zlib

    expected, got = _png_data_size(*header), 0
    inflate = zlib.decompressobj()
    with open(path, "rb") as f:
        f.seek(8)
        while True:
            head = f.read(8)
            if len(head) < 8:
                break
            length, kind = struct.unpack(">I", head[:4])[0], head[4:]
            if kind == b"IEND":
                break
            if kind != b"IDAT":
                f.seek(length + 4, 1)
                continue
            try:
                got += len(inflate.decompress(f.read(length)))
            except zlib.error:
                break  # Pillow reports corrupt data itself
            f.seek(4, 1)
    if got < expected:
        raise InputError(
            f"{what} {path}: truncated PNG (its image data holds {got} of the "
            f"{expected} bytes its header announces, the rest would read as black); "
            "save the image again"
        )


def _check_size(what, path, size, resolution):
    """Refuse an image of ``size`` (width, height) other than ``resolution``, or beyond memory."""
    from ..._util import checks as validate

    w, h = (int(v) for v in size)
    if resolution is not None and (w, h) != tuple(resolution):
        raise InputError(
            f"{what} {path} is {w}x{h}, the basis is {resolution[0]}x{resolution[1]}: render "
            f"or resize the {what} to the basis resolution"
        )
    validate.fits_in_memory(what, 4 * w * h * 3 * 8, f"the {w}x{h} image {path}")


def _exr_size(path, resolution, what):
    info = imageio.read_exr_header(path)
    _check_size(what, path, (info.width, info.height), resolution)


def _read_coded(path, what, resolution=None):
    """The integer codes of a PNG/JPEG as float64 (H, W, C) (C: 1 grey, 3 colour) and the
    largest code (255, or 65535 for a 16-bit greyscale PNG); the size checked before decoding.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        png = _png_header(path)
        if png is not None:
            _check_size(what, path, png[:2], resolution)
            if png[2] == 16 and png[3] != 0:
                raise InputError(
                    f"{what} {path} is a 16-bit PNG with colour or alpha (colour type {png[3]}), "
                    "which cannot be read at its depth here (it would be cut to 8 bits): save it "
                    "as a linear EXR, an 8-bit PNG or a 16-bit greyscale PNG without alpha"
                )
            _check_png_data(what, path, png)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                _check_size(what, path, im.size, resolution)
                if im.mode.startswith("I;16") or (
                    im.mode == "I" and png is not None and png[2] == 16
                ):
                    return np.asarray(im, dtype=np.float64)[..., None], 65535
                if im.mode in ("1", "L", "LA", "I", "F"):
                    return np.asarray(im.convert("L"), dtype=np.float64)[..., None], 255
                return np.asarray(im.convert("RGB"), dtype=np.float64), 255
    except FileNotFoundError:
        raise InputError(f"{what} {path}: file does not exist") from None
    except Image.DecompressionBombError as e:
        raise InputError(f"{what} {path} is too large to decode ({e})") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise InputError(f"{what} {path}: not a readable image ({e})") from None

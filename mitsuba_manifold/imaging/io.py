"""Image files: float32 RGB OpenEXR read/write, tonemapped sRGB PNG and contact sheets, all written atomically.

Every writer goes through a temporary file beside the target and a rename, so an existing
image is replaced only by a complete one. Every reader raises :class:`FormatError` naming
the file and the problem (missing, not an EXR, truncated or corrupt, wrong channels,
non-finite values).
"""

import functools
import json
import os
from dataclasses import dataclass

import numpy as np

from .._util.atomic import atomic_write
from ..errors import FormatError


def _check_rgb(img, path, what="image"):
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise FormatError(f"{path}: {what} must have shape (height, width, 3), got {img.shape}")
    return img


def write_exr(path, img, metadata=None):
    """Write an (H, W, 3) image as a float32 RGB OpenEXR file (ZIP compressed), atomically.

    Parameters
    ----------
    path : str
    img : array_like (H, W, 3)
        Converted to float32; must be finite.
    metadata : dict, optional
        Extra header attributes: strings are stored as they are, other values as JSON text.
    """
    import OpenEXR

    path = os.fspath(path)
    img = np.ascontiguousarray(_check_rgb(img, path), dtype=np.float32)
    if not np.isfinite(img).all():
        raise FormatError(f"{path}: refusing to write an image with NaN or Inf values")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (metadata or {}).items():
        if key in header or key in ("channels", "dataWindow", "displayWindow"):
            raise FormatError(f"{path}: metadata key {key!r} is reserved by OpenEXR")
        header[str(key)] = value if isinstance(value, str) else json.dumps(value)
    exr = OpenEXR.File(header, {"RGB": img})
    atomic_write(path, exr.write)


def _open(path, header_only):
    import OpenEXR

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FormatError(f"{path}: image file does not exist")
    if not os.path.isfile(path):
        raise FormatError(f"{path}: not a file")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"\x76\x2f\x31\x01":
        raise FormatError(
            f"{path}: not an OpenEXR file (no EXR magic number"
            f"{', file is empty' if not magic else ''})"
        )
    try:
        exr = OpenEXR.File(path, separate_channels=True, header_only=header_only)
        header = exr.header()
        channels = None if header_only else exr.channels()
    except Exception as e:  # the library reports truncation and corruption in several ways
        raise FormatError(
            f"{path}: truncated or corrupt OpenEXR file ({type(e).__name__}: {e})"
        ) from None
    return header, channels


def _size(header, path):
    try:
        lo, hi = header["dataWindow"]
        return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
    except (KeyError, TypeError, ValueError, IndexError):
        raise FormatError(f"{path}: OpenEXR header has no valid data window") from None


@dataclass(frozen=True)
class ExrHeader:
    """What an EXR file's header says (:func:`read_exr_header`).

    Attributes
    ----------
    width, height : int
        The image size (of the data window).
    channels : list of str
        The channel names, sorted.
    attributes : dict
        The other header entries (JSON metadata written by :func:`write_exr` stays a string).
    """

    width: int
    height: int
    channels: list
    attributes: dict


def read_exr_header(path):
    """Header of an EXR file without reading its pixels.

    Returns
    -------
    ExrHeader
    """
    path = os.fspath(path)
    header, _ = _open(path, header_only=True)
    width, height = _size(header, path)
    names = sorted(c.name for c in header.get("channels", []))
    skip = {"channels", "dataWindow", "displayWindow"}
    return ExrHeader(
        width=width,
        height=height,
        channels=names,
        attributes={k: v for k, v in header.items() if k not in skip},
    )


def check_exr_header(path, resolution=None):
    """Check that ``path`` is an RGB EXR (of ``resolution`` = (width, height) if given).

    Reads the header only: a file truncated after its header passes here and fails in
    :func:`read_exr`. Returns its :class:`ExrHeader`.
    """
    info = read_exr_header(path)
    missing = [c for c in "RGB" if c not in info.channels]
    if missing:
        raise FormatError(
            f"{path}: EXR has channels {info.channels}, missing {''.join(missing)} "
            "(an RGB image is needed)"
        )
    if resolution is not None and (info.width, info.height) != tuple(resolution):
        raise FormatError(
            f"{path}: image is {info.width}x{info.height}, expected {resolution[0]}x{resolution[1]}"
        )
    return info


def read_exr(path):
    """Read the R, G, B channels of an OpenEXR file as float32 (H, W, 3).

    Other channels (alpha, AOVs) are ignored; half-float channels are converted.

    Raises
    ------
    FormatError
        Missing, empty, non-EXR, truncated or corrupt files, missing R/G/B channels,
        subsampled channels, NaN or Inf values.
    """
    path = os.fspath(path)
    header, channels = _open(path, header_only=False)
    width, height = _size(header, path)
    missing = [c for c in "RGB" if c not in channels]
    if missing:
        raise FormatError(
            f"{path}: EXR has channels {sorted(channels)}, missing {''.join(missing)} "
            "(an RGB image is needed)"
        )
    planes = []
    for c in "RGB":
        px = channels[c].pixels
        if px is None or np.shape(px) != (height, width):
            raise FormatError(
                f"{path}: channel {c} has shape {np.shape(px)}, expected ({height}, {width}) "
                "(subsampled or unreadable channel)"
            )
        if not np.issubdtype(px.dtype, np.floating):
            raise FormatError(f"{path}: channel {c} holds {px.dtype} values, expected float")
        planes.append(px)
    img = np.stack(planes, axis=-1).astype(np.float32, copy=False)
    if not np.isfinite(img).all():
        bad = int((~np.isfinite(img)).any(axis=-1).sum())
        raise FormatError(f"{path}: {bad} pixels hold NaN or Inf values")
    return img


# ------------------------------------------------------------------ PNG


def srgb_encode(linear):
    """Linear values in [0, 1] to sRGB-encoded values in [0, 1] (IEC 61966-2-1)."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def srgb_decode(encoded):
    """sRGB-encoded values in [0, 1] to linear values (the inverse of :func:`srgb_encode`)."""
    c = np.clip(np.asarray(encoded, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, np.power((c + 0.055) / 1.055, 2.4))


def tonemap(img, exposure=0.0):
    """Linear RGB (H, W, 3) to 8-bit sRGB: scale by ``2**exposure``, clip to [0, 1], encode."""
    img = np.asarray(img, dtype=np.float64) * 2.0 ** float(exposure)
    img = np.nan_to_num(img, nan=0.0, posinf=1.0, neginf=0.0)
    return np.round(srgb_encode(img) * 255.0).astype(np.uint8)


def write_png(path, img, exposure=0.0, text=None):
    """Write a PNG atomically.

    Parameters
    ----------
    path : str
    img : array_like (H, W, 3)
        Linear radiance (float), tonemapped by :func:`tonemap` with ``exposure`` stops;
        a ``uint8`` array is taken as display-ready and written as it is.
    text : dict, optional
        PNG text chunks (e.g. the scale of a false-colour image).
    """
    from PIL import Image, PngImagePlugin

    path = os.fspath(path)
    img = _check_rgb(img, path)
    u8 = img if img.dtype == np.uint8 else tonemap(img, exposure)
    info = PngImagePlugin.PngInfo()
    for key, value in (text or {}).items():
        info.add_text(str(key), str(value))
    pil = Image.fromarray(np.ascontiguousarray(u8))
    atomic_write(path, lambda f: pil.save(f, format="PNG", pnginfo=info))


def printable(text):
    r"""``text`` with every character that is not printable (newlines, tabs, other control
    and format characters) written as its Python escape (``\n``, ``\x07``, ``\u202e``): a
    material name drawn in a label or a title reads as it is, on one line.
    """
    text = str(text)
    return "".join(
        c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text
    )


def _wrap(text, width, length, max_lines=3):
    """``text`` as at most ``max_lines`` lines no wider than ``width`` (``length(s)``: pixels);
    cut at ``-``, ``_`` or spaces where possible, the last line ending in ``...`` if it is cut.
    """
    out = []
    while text and len(out) < max_lines:
        k = len(text)
        while k > 1 and length(text[:k]) > width:
            k -= 1
        cut = max(text.rfind(ch, 0, k) for ch in "-_ ") + 1 if k < len(text) else k
        k = cut if cut > 1 else k
        out.append(text[:k].rstrip())
        text = text[k:].lstrip()
    if text:
        last = out[-1]
        while len(last) > 1 and length(last + "...") > width:
            last = last[:-1]
        out[-1] = last + "..."
    return out or [""]


def _label_lines(text, width, length, max_lines=4):
    r"""A label as lines no wider than ``width``: each ``\n``-separated field on lines of its
    own (:func:`_wrap`), at most ``max_lines`` in all, the last ending in ``...`` if cut.
    """
    out, fields = [], [printable(f) for f in str(text).split("\n")]
    for k, field in enumerate(fields):
        room = max_lines - len(out)
        out += _wrap(field, width, length, room)
        if len(out) >= max_lines and k + 1 < len(fields):
            if not out[-1].endswith("..."):
                out[-1] = _wrap(out[-1] + " " + " ".join(fields[k + 1 :]), width, length, 1)[0]
            break
    return out


@functools.cache
def label_font(size=10):
    """The font of labels, titles and captions: DejaVu Sans (shipped with matplotlib), whose
    spaces read as spaces at small sizes; Pillow's default font when it cannot be found.
    """
    from PIL import ImageFont

    try:
        from matplotlib import font_manager

        return ImageFont.truetype(
            font_manager.findfont("DejaVu Sans", fallback_to_default=False), size
        )
    except Exception:  # matplotlib missing or no DejaVu: Pillow's own
        return ImageFont.load_default()


def tiles(images, min_width=0) -> np.ndarray:
    """Images of different sizes as one (n, H, W, 3) float32 stack for a contact sheet: each
    enlarged by whole pixels (nearest) to at least ``min_width`` wide, so that small ones can
    be seen, then padded with black to the largest.
    """
    big = []
    for im in images:
        im = np.asarray(im, dtype=np.float32)
        k = max(1, -(-int(min_width) // im.shape[1]))
        big.append(im.repeat(k, axis=0).repeat(k, axis=1))
    out = np.zeros(
        (len(big), max(i.shape[0] for i in big), max(i.shape[1] for i in big), 3), np.float32
    )
    for t, im in zip(out, big):
        t[: im.shape[0], : im.shape[1]] = im
    return out


def write_contact_sheet(path, images, labels=None, columns=None, exposure=0.0, pad=4, title=None):
    r"""PNG grid of tonemapped images (one exposure for all), with optional labels; atomic.

    Parameters
    ----------
    images : array_like (n, H, W, 3)
        Linear radiance.
    labels : list of str, optional
        Drawn under each image, wrapped to its width; ``\n`` starts a new line (one field
        per line reads best on small tiles); other control characters are drawn escaped
        (:func:`printable`).
    columns : int, optional
        Default: ``ceil(sqrt(n))``.
    title : str, optional
        Drawn above the grid, wrapped to the sheet's width (what the sheet shows, e.g. its
        two end materials); one paragraph, control characters escaped (:func:`printable`).
    """
    from PIL import Image, ImageDraw

    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3 or len(images) == 0:
        raise FormatError(f"contact sheet needs images of shape (n, H, W, 3), got {images.shape}")
    n, h, w, _ = images.shape
    if labels is not None and len(labels) != n:
        raise FormatError(f"{len(labels)} labels for {n} images")
    cols = int(columns or np.ceil(np.sqrt(n)))
    rows = -(-n // cols)
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    draw.font = label_font()
    lines = [_label_lines(t, w - 2, draw.textlength) for t in labels] if labels else []
    label_h = 12 * max(map(len, lines)) + 2 if labels else 0
    width = cols * (w + pad) + pad
    heading = _wrap(printable(title), width - 2 * pad, draw.textlength) if title else []
    top = 12 * len(heading) + (pad if heading else 0)
    sheet = np.full((top + rows * (h + label_h + pad) + pad, width, 3), 32, dtype=np.uint8)
    tiles = tonemap(images, exposure)
    for i in range(n):
        r, c = divmod(i, cols)
        y, x0 = top + pad + r * (h + label_h + pad), pad + c * (w + pad)
        sheet[y : y + h, x0 : x0 + w] = tiles[i]
    if labels or heading:
        pil = Image.fromarray(sheet)
        draw = ImageDraw.Draw(pil)
        draw.font = label_font()
        if heading:
            draw.text((pad, pad // 2), "\n".join(heading), fill=(240, 240, 240), spacing=2)
        for i, text in enumerate(lines):
            r, c = divmod(i, cols)
            draw.text(
                (pad + c * (w + pad) + 2, top + pad + r * (h + label_h + pad) + h + 1),
                "\n".join(text),
                fill=(230, 230, 230),
                spacing=2,
            )
        sheet = np.asarray(pil)
    write_png(path, sheet)


def with_colour_bar(image, ramp, ticks, caption, min_width=240, pad=6, background=32):
    """``image`` (uint8 (H, W, 3)) above a colour bar and its legend, as one uint8 image.

    Parameters
    ----------
    ramp : uint8 (n, 3)
        The colours of the scale, bottom to top, drawn left to right.
    ticks : list of (fraction, str)
        Labels under the bar at ``fraction`` of its width (0: left end, 1: right end).
    caption : str
        What the scale measures; wrapped under the ticks (at most three lines).
    min_width : int
        The legend is at least this wide (small images get a margin on their right).
    """
    from PIL import Image, ImageDraw

    image = _check_rgb(image, "colour bar", "image")
    h, w, _ = image.shape
    width = max(w, min_width)
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    draw.font = label_font()
    lines = _wrap(caption, width - 2 * pad, draw.textlength)
    bar_h, line_h = 10, 12
    out = np.full(
        (h + 3 * pad + bar_h + line_h * (1 + len(lines)), width, 3), background, dtype=np.uint8
    )
    out[:h, :w] = image
    x0, x1, y = pad, width - pad, h + pad
    cols = np.linspace(0, len(ramp) - 1, x1 - x0).round().astype(int)
    out[y : y + bar_h, x0:x1] = np.asarray(ramp, dtype=np.uint8)[cols][None]
    pil = Image.fromarray(out)
    draw = ImageDraw.Draw(pil)
    draw.font = label_font()
    for frac, text in ticks:
        tw = draw.textlength(text)
        tx = min(
            max(x0 + frac * (x1 - x0) - tw / 2, x0), x1 - tw
        )  # centred on its place, inside the bar
        draw.line(
            [(x0 + frac * (x1 - x0 - 1), y + bar_h), (x0 + frac * (x1 - x0 - 1), y + bar_h + 2)],
            fill=(230, 230, 230),
        )
        draw.text((tx, y + bar_h + 2), text, fill=(230, 230, 230))
    draw.text(
        (x0, y + bar_h + 2 + line_h + pad // 2), "\n".join(lines), fill=(230, 230, 230), spacing=2
    )
    return np.asarray(pil)

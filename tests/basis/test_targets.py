"""Targets and masks decoded at their depth or refused (issue 20): 16-bit greyscale PNGs keep
their 16 bits, 16-bit colour PNGs (which Pillow would cut to 8) are refused, and the size is
checked from the header before any pixel is decoded."""

import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from mitsuba_manifold.basis.inverse import targets
from mitsuba_manifold.errors import InputError
from mitsuba_manifold.imaging import io as imageio


def _png_header_only(path, width, height, depth=8, colour=2):
    """A PNG whose header claims ``width`` x ``height`` pixels, with one empty data chunk: what
    a decompression bomb looks like before decoding."""

    def chunk(kind, data):
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    path.write_bytes(
        targets.PNG_SIGNATURE
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b""))
        + chunk(b"IEND", b"")
    )


def test_16bit_greyscale_png_target_is_read_at_its_depth(tmp_path):
    codes = (np.arange(64).reshape(8, 8) * 1000 + 300).astype(
        np.uint16
    )  # 300 .. 63300, none at 65535
    Image.fromarray(codes).save(tmp_path / "t.png")
    img, clipped = targets.read_target(tmp_path / "t.png", (8, 8))
    want = imageio.srgb_decode(codes / 65535.0)
    assert img.shape == (8, 8, 3) and not clipped.any()
    assert np.allclose(img, want[..., None], rtol=1e-6, atol=1e-9)
    assert len(np.unique(img[..., 0])) == 64  # not 8-bit (nor all clipped at 255)
    codes[0, 0] = 65535
    Image.fromarray(codes).save(tmp_path / "t.png")
    assert targets.read_target(tmp_path / "t.png")[1].sum() == 1
    mask = targets.read_mask(tmp_path / "t.png", (8, 8))
    assert np.allclose(mask, codes / 65535.0)


def test_8bit_greyscale_target_and_mask_are_grey_rgb(tmp_path):
    codes = np.arange(64, dtype=np.uint8).reshape(8, 8) * 3
    Image.fromarray(codes).save(tmp_path / "g.png")
    img, clipped = targets.read_target(tmp_path / "g.png")
    assert img.shape == (8, 8, 3) and np.allclose(img[..., 0], img[..., 2]) and not clipped.any()
    assert np.allclose(img[..., 1], imageio.srgb_decode(codes / 255.0))


def test_16bit_colour_png_is_refused_not_cut_to_8_bits(tmp_path):
    _png_header_only(tmp_path / "rgb16.png", 8, 8, depth=16, colour=2)
    with pytest.raises(InputError, match="16-bit PNG with colour"):
        targets.read_target(tmp_path / "rgb16.png")


def test_size_is_checked_before_decoding(tmp_path):
    bomb = tmp_path / "huge.png"
    _png_header_only(bomb, 20000, 20000)
    with pytest.raises(InputError, match="20000x20000, the basis is 8x8"):
        targets.read_target(bomb, (8, 8))
    with pytest.raises(InputError, match="20000x20000"):
        targets.read_mask(bomb, (8, 8))
    Image.fromarray(np.zeros((6, 4, 3), np.uint8)).save(tmp_path / "small.jpg")
    with pytest.raises(InputError, match="4x6, the basis is 8x8"):
        targets.read_target(tmp_path / "small.jpg", (8, 8))
    imageio.write_exr(tmp_path / "small.exr", np.zeros((6, 4, 3)))
    with pytest.raises(InputError, match="4x6, the basis is 8x8"):
        targets.read_target(tmp_path / "small.exr", (8, 8))

"""Inputs a user gets wrong, refused in one line before any work: a path depth that shows no
material, a path of blends beyond the limit, weights that overflow, and targets that are no image
of light (a PNG whose rows end early, an EXR of negative values), a fit by direct search with the
default's stress term."""

import struct
import zlib

import numpy as np
import pytest

from mitsuba_manifold.basis.inverse import targets
from mitsuba_manifold.errors import InputError


def _error(capsys, main, argv):
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and "\n" not in err and "Traceback" not in err
    return err


@pytest.mark.parametrize("depth", [0, 1, -2])
def test_a_path_depth_that_shows_no_material_is_refused(capsys, tmp_path, depth):
    from mitsuba_manifold.apps.cli.render_basis import main

    err = _error(capsys, main, ["sphere", "--out", str(tmp_path / "b"), "--max-depth", str(depth)])
    assert f"--max-depth must be -1 (unbounded) or at least 2, got {depth}" in err
    assert not (tmp_path / "b").exists()


def test_a_fit_by_direct_search_asks_to_drop_the_default_stress_term(capsys, tmp_path):
    """Hooke-Jeeves cannot fit the default's stress term: refused before the fit, naming the
    fix; with ``--stress 0`` it fits."""
    from mitsuba_manifold.apps.cli.fit_manifold import main
    from mitsuba_manifold.manifold.model import Manifold

    out = tmp_path / "m.npz"
    argv = ["nielsen@8x8x16", "--out", str(out), "--method", "hooke-jeeves"]
    err = _error(capsys, main, argv)
    assert "--method hooke-jeeves cannot fit the layout's stress term" in err
    assert "add --stress 0, or use --method newton (or lbfgs)" in err and not out.exists()
    assert main([*argv, "--stress", "0"]) in (0, None)
    m = Manifold.load(out)
    assert m.record.method == "hooke-jeeves" and "stress" not in m.info


def test_a_path_of_too_many_steps_is_refused_naming_the_limit(capsys, tmp_path):
    from mitsuba_manifold.apps.cli.blend import MAX_STEPS, main

    err = _error(
        capsys,
        main,
        [
            "--basis",
            str(tmp_path),
            "--path",
            "chrome",
            "steel",
            "--steps",
            "100000",
            "--out",
            str(tmp_path / "seq.exr"),
        ],
    )
    assert f"--steps must be from 2 to {MAX_STEPS}" in err and "100000" in err


@pytest.mark.parametrize("text", ["chrome:1e308, steel:1e308", "chrome:1e300"])
def test_weights_that_overflow_are_refused_in_one_line(text):
    from mitsuba_manifold.manifold.model import Manifold

    m = Manifold(["chrome", "steel"], [[0.0], [1.0]], "db", ["a", "b"])
    with pytest.raises(InputError, match="at most 1e\\+12 in magnitude"):
        m.parse_weights(text)


def _png(path, rows_written, width=16, height=16):
    """An RGB PNG whose IDAT holds a complete zlib stream of only ``rows_written`` rows."""
    rng = np.random.default_rng(0)
    raw = b"".join(
        b"\x00" + (rng.random(width * 3) * 200 + 20).astype(np.uint8).tobytes()
        for _ in range(rows_written)
    )

    def chunk(kind, data):
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )
    return str(path)


def test_a_png_whose_rows_end_early_is_refused_not_read_as_black(tmp_path):
    img, _ = targets.read_target(_png(tmp_path / "whole.png", 16), (16, 16))
    assert img.min() > 0
    with pytest.raises(InputError, match="truncated PNG"):
        targets.read_target(_png(tmp_path / "half.png", 8), (16, 16))


def test_a_target_of_no_light_is_refused():
    with pytest.raises(InputError, match="holds only negative values"):
        targets.check_target(-np.ones((4, 4, 3)), (4, 4))
    assert targets.check_target(np.full((4, 4, 3), 0.5), (4, 4)).shape == (4, 4, 3)


def test_refining_with_fewer_samples_than_the_default_passes_is_not_refused(capsys, tmp_path):
    """--refine 2 without --refine-passes: two passes (the default 4 would exceed the samples), so
    the parser goes on to the basis (missing here) instead of refusing an option never given."""
    from mitsuba_manifold.apps.cli.blend import main

    err = _error(
        capsys,
        main,
        [
            "--basis",
            str(tmp_path / "none"),
            "--x",
            "0,0",
            "--refine",
            "2",
            "--out",
            str(tmp_path / "o.exr"),
        ],
    )
    assert "--refine-passes" not in err and "does not exist" in err


@pytest.mark.render
def test_a_variant_that_cannot_render_is_refused_in_one_line(monkeypatch):
    pytest.importorskip("mitsuba")
    from mitsuba_manifold.errors import VariantError
    from mitsuba_manifold.render.scene import scenes

    monkeypatch.setenv("MM_VARIANT", "scalar_rgb")
    with pytest.raises(
        VariantError, match="MM_VARIANT=scalar_rgb: the tools render in llvm_ad_rgb"
    ):
        scenes.default_variant()
    monkeypatch.setenv("MM_VARIANT", "llvm_ad_rgb")
    assert scenes.default_variant() == "llvm_ad_rgb"

"""Property-based tests over the command lines of blend.py and fit_manifold.py (issue 10):
every argument list either succeeds (exit 0) with valid outputs, or exits 2 with exactly
one ``error:`` line and no file changed; argument lists made of valid values only succeed."""

import math
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from guarantees_helpers import TINY_NAMES as NAMES, make_tiny, refused_cleanly, run_tool, snapshot

from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.manifold.presets import PRESETS
pytestmark = pytest.mark.render   # the fixture renders a small basis
SETTINGS = dict(deadline=None, suppress_health_check=list(HealthCheck), derandomize=True, database=None)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("llvm_ad_rgb")
    tiny = make_tiny(tmp_path_factory.mktemp("props"))
    work = tiny["root"] / "work"
    work.mkdir()
    (work / "user.exr").write_bytes(b"not mine")
    (work / "afile").write_text("a file")
    return {**tiny, "work": str(work)}


odd = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([1e10, -1e10, 1e300, 0.0, -0.0]))
numbers = st.one_of(st.floats(-2, 2), st.integers(-5, 5).map(float), odd)


def _fmt(v):
    return repr(v) if isinstance(v, float) else str(v)


def _options(draw, valid, args, given, table):
    """Perhaps add ``option=value`` to ``args`` for each ``(option, good, bad)`` of ``table``:
    values from ``good`` only when ``valid``, else from ``good`` or ``bad``."""
    for option, good, bad in table:
        if draw(st.booleans()):
            v = draw(good if valid else st.one_of(good, bad))
            args.append(f"{option}={_fmt(v)}")
            given[option] = v


def _with_out(draw, valid, args, given, outs):
    """``(args, given, valid)`` with an ``--out`` from ``outs`` (valid ones, odd ones)."""
    given["--out"] = draw(st.sampled_from(outs[0] + ([] if valid else outs[1])))
    return args + [f"--out={given['--out']}"], given, valid


def _place(case, data):
    """``(args, given, valid)`` of a drawn case with its ``WORK/`` and ``BASIS/`` paths placed."""
    args, given, valid = case

    def place(a):
        for tag, folder in (("WORK/", data["work"]), ("BASIS/", data["basis"])):
            if isinstance(a, str) and tag in a:
                return a.replace(tag, folder + os.sep)
        return a
    return [place(a) for a in args], {k: place(v) for k, v in given.items()}, valid


def _run(tool, lead, args, valid, folders):
    """Run ``tool lead args``; valid arguments must succeed. Returns ``(refused, stderr)``
    after checking that a refusal is clean (:func:`refused_cleanly`)."""
    before = [snapshot(f) for f in folders]
    rc, _, err = run_tool(tool, *lead, *args)
    assert rc == 0 or not valid, err
    return refused_cleanly(rc, err, before, folders), err


BLEND_OUTS = (["WORK/img.exr", "WORK/sub/img.exr"],
              ["WORK/img.txt", "WORK/user.exr", "WORK/afile/img.exr", "BASIS/x.exr", "BASIS/base.exr"])


@st.composite
def blend_args(draw):
    """``(args, given, out, valid)``: half the cases use only valid values (they must succeed)."""
    valid = draw(st.booleans())
    args, given = [], {}
    if draw(st.booleans()):
        xs = draw(st.lists(st.floats(-3, 3), min_size=2, max_size=2) if valid else
                  st.one_of(st.lists(numbers, min_size=2, max_size=2), st.lists(numbers, max_size=3)))
        args += ["--x", ",".join(_fmt(v) for v in xs) if xs else "abc"]
        given["x"] = xs
    else:
        a = draw(st.sampled_from(NAMES + ([] if valid else ["adamantium", "0,0", "nan,1"])))
        b = draw(st.sampled_from([n for n in NAMES + ["1,1"] if n != a or not valid]))   # same ends: refused
        steps = draw(st.integers(2, 4) if valid else st.integers(-1, 4))
        args += ["--path", a, b, "--steps", str(steps)]
        given["path"] = (a, b, steps)
    _options(draw, valid, args, given, [("--exposure", st.floats(-8, 8), odd), ("--prune", st.floats(0, 0.5), odd)])
    if draw(st.booleans()):
        args.append("--png")
    return _with_out(draw, valid, args, given, BLEND_OUTS)


@settings(max_examples=60, **SETTINGS)
@given(case=blend_args())
def test_blend_cli_succeeds_or_refuses_cleanly(data, case):
    args, given, valid = _place(case, data)
    basis_before, out = snapshot(data["basis"]), given["--out"]
    refused, err = _run("blend", ["--basis", data["basis"]], args, valid, [data["work"], data["basis"]])
    if refused:
        return
    assert "Traceback" not in err
    assert all(math.isfinite(v) for v in given.get("x", [])) and len(given.get("x", [0, 0])) == 2
    assert math.isfinite(given.get("--exposure", 0.0)) and abs(given.get("--exposure", 0.0)) <= 64
    assert 0 <= given.get("--prune", 0.0) < 1
    assert snapshot(data["basis"]) == basis_before   # a blend never touches its basis
    stem = out[:-4]
    exrs = [out] if "x" in given else [f"{stem}_{s}.exr" for s in range(given["path"][2])]
    for path in exrs:
        img = imageio.read_exr(path)
        assert img.shape == (8, 8, 3) and np.isfinite(img).all()
        if "--png" in args:
            assert os.path.getsize(path[:-4] + ".png") > 0


FIT_OUTS = (["WORK/m.npz", "WORK/sub/m.npz"], ["WORK/user.exr", "WORK/afile/m.npz", "WORK/afile", "WORK/m.json",
                                            "WORK/m"])


@st.composite
def fit_args(draw):
    """``(args, given, out, valid)``: half the cases use only valid values (they must succeed)."""
    valid, args, given, one = draw(st.booleans()), [], {}, st.sampled_from
    _options(draw, valid, args, given, [
        ("--q", st.integers(1, 3), st.integers(-1, 9)),
        ("--length-scale", st.floats(0.5, 2), odd),
        ("--noise", st.floats(1e-5, 1e-2), odd),
        ("--materials", one(["steel,chrome", "chrome,gold-paint,pink-fabric"]),
         one(["steel", "steel,adamantium", "steel,steel", ","])),
        ("--method", one(["lbfgs", "hooke-jeeves"]), st.just("newton")),
        ("--features", one(["raw", "log"]), st.just("sqrt")),
        ("--plot", st.just("WORK/plots"), one(["WORK/afile", "WORK/afile/sub"]))])
    return _with_out(draw, valid, args, given, FIT_OUTS)


@settings(max_examples=30, **SETTINGS)
@given(case=fit_args())
def test_fit_manifold_cli_succeeds_or_refuses_cleanly(data, case):
    args, given, valid = _place(case, data)
    refused, err = _run("fit_manifold", [data["db"]], args, valid, [data["work"]])
    if refused:
        return
    assert "Traceback" not in err
    m = Manifold.load(given["--out"])
    assert m.q == given.get("--q", PRESETS["default"]["q"]) and 1 <= m.q <= 8
    assert np.isfinite(m.latent).all()
    for opt in ("--length-scale", "--noise"):
        if opt in given:
            assert math.isfinite(given[opt]) and given[opt] > 0
    if "--materials" in given:
        assert m.names == given["--materials"].split(",")

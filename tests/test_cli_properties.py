"""Property-based tests over the command lines of blend.py and fit_manifold.py (issue 10):
every argument list either succeeds (exit 0) with valid outputs, or exits 2 with exactly
one ``error:`` line and no file changed."""

import math
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from guarantees_helpers import TINY_NAMES as NAMES, make_tiny, refused_cleanly, run_tool, snapshot

from mitsuba_manifold import imageio
from mitsuba_manifold.manifold import Manifold
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


def mostly(valid):
    """Values from ``valid`` two times in three, odd ones otherwise (so both outcomes are tested)."""
    return st.one_of(valid, valid, odd)


def _fmt(v):
    return repr(v) if isinstance(v, float) else str(v)


def _maybe(draw, args, given, option, strategy):
    """Perhaps add ``option=value`` (value drawn from ``strategy``) to ``args``."""
    if draw(st.booleans()):
        v = draw(strategy)
        args.append(f"{option}={_fmt(v)}")
        given[option] = v


@st.composite
def blend_args(draw):
    args, given = [], {}
    if draw(st.booleans()):
        xs = draw(st.one_of(st.lists(numbers, min_size=2, max_size=2), st.lists(numbers, max_size=3)))
        args += ["--x", ",".join(_fmt(v) for v in xs) if xs else "abc"]
        given["x"] = xs
    else:
        a = draw(st.sampled_from(NAMES + ["adamantium", "0,0", "nan,1"]))
        b = draw(st.sampled_from(NAMES + ["1,1"]))
        steps = draw(st.integers(-1, 4))
        args += ["--path", a, b, "--steps", str(steps)]
        given["path"] = (a, b, steps)
    _maybe(draw, args, given, "--exposure", mostly(st.floats(-8, 8)))
    _maybe(draw, args, given, "--prune", mostly(st.floats(0, 0.5)))
    if draw(st.booleans()):
        args.append("--png")
    return args, given


@settings(max_examples=40, **SETTINGS)
@given(case=blend_args(), out=st.sampled_from(["img.exr", "img.exr", "sub/img.exr", "sub/img.exr", "img.txt",
                                               "user.exr", "afile/img.exr", "BASIS/x.exr", "BASIS/base.exr"]))
def test_blend_cli_succeeds_or_refuses_cleanly(data, case, out):
    (args, given), work = case, data["work"]
    out = os.path.join(data["basis"], out[6:]) if out.startswith("BASIS/") else os.path.join(work, out)
    before = [snapshot(work), snapshot(data["basis"])]
    rc, _, err = run_tool("blend", "--basis", data["basis"], "--out", out, *args)
    if refused_cleanly(rc, err, before, [work, data["basis"]]):
        return
    assert "Traceback" not in err
    assert all(math.isfinite(v) for v in given.get("x", [])) and len(given.get("x", [0, 0])) == 2
    assert math.isfinite(given.get("--exposure", 0.0)) and abs(given.get("--exposure", 0.0)) <= 64
    assert 0 <= given.get("--prune", 0.0) < 1
    assert snapshot(data["basis"]) == before[1]   # a blend never touches its basis
    stem = out[:-4]
    exrs = [out] if "x" in given else [f"{stem}_{s}.exr" for s in range(given["path"][2])]
    for path in exrs:
        img = imageio.read_exr(path)
        assert img.shape == (8, 8, 3) and np.isfinite(img).all()
        if "--png" in args:
            assert os.path.getsize(path[:-4] + ".png") > 0


@st.composite
def fit_args(draw):
    args, given = [], {}
    _maybe(draw, args, given, "--q", st.one_of(st.integers(1, 3), st.integers(-1, 9)))
    _maybe(draw, args, given, "--length-scale", mostly(st.floats(0.5, 2)))
    _maybe(draw, args, given, "--noise", mostly(st.floats(1e-5, 1e-2)))
    _maybe(draw, args, given, "--materials", st.sampled_from(
        ["steel", "steel,chrome", "steel,adamantium", "steel,steel", ",", "chrome,gold-paint,pink-fabric"]))
    _maybe(draw, args, given, "--method", st.sampled_from(["lbfgs", "hooke-jeeves", "newton"]))
    _maybe(draw, args, given, "--features", st.sampled_from(["raw", "log", "sqrt"]))
    _maybe(draw, args, given, "--plot", st.sampled_from(["plots", "afile", "afile/sub"]))
    return args, given


@settings(max_examples=14, **SETTINGS)
@given(case=fit_args(), out=st.sampled_from(["m.npz", "m.npz", "sub/m.npz", "user.exr", "afile/m.npz", "afile"]))
def test_fit_manifold_cli_succeeds_or_refuses_cleanly(data, case, out):
    (args, given), work = case, data["work"]
    args = [f"--plot={os.path.join(work, a[7:])}" if a.startswith("--plot=") else a for a in args]
    out = os.path.join(work, out)
    before = [snapshot(work)]
    rc, _, err = run_tool("fit_manifold", data["db"], "--out", out, *args)
    if refused_cleanly(rc, err, before, [work]):
        return
    assert "Traceback" not in err
    m = Manifold.load(out)
    assert m.q == given.get("--q", 2) and 1 <= m.q <= 8
    assert np.isfinite(m.latent).all()
    for opt in ("--length-scale", "--noise"):
        if opt in given:
            assert math.isfinite(given[opt]) and given[opt] > 0
    if "--materials" in given:
        assert m.names == given["--materials"].split(",")

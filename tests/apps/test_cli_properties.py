"""Property-based tests over the command lines of blend.py and fit_manifold.py (issue 10):
every argument list either succeeds (exit 0) with valid outputs, or exits 2 with exactly
one ``error:`` line and no file changed; argument lists made of valid values only succeed.
Issue 20 adds main.py, render_basis.py, match.py and bench.py: argument lists holding at
least one value refused before any work (so that they stay fast) are refused cleanly, and
no output replaces a link, a FIFO, a read-only file or a user's file."""

import math
import os
import stat
import struct
import zlib

import numpy as np
import pytest
from guarantees_helpers import TINY_NAMES as NAMES
from guarantees_helpers import make_tiny, refused_cleanly, run_tool, snapshot
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.manifold.presets import PRESETS

pytestmark = pytest.mark.render  # the fixture renders a small basis
SETTINGS = dict(
    deadline=None, suppress_health_check=list(HealthCheck), derandomize=True, database=None
)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("llvm_ad_rgb")
    tiny = make_tiny(tmp_path_factory.mktemp("props"))
    work = tiny["root"] / "work"
    work.mkdir()
    (work / "user.exr").write_bytes(b"not mine")
    (work / "afile").write_text("a file")
    _outputs_of_the_user(work)
    _targets(work, tiny["basis"])
    special = tiny["root"] / "special"  # not snapshotted: reading a FIFO would block
    special.mkdir()
    os.mkfifo(special / "fifo.json")
    return {**tiny, "work": str(work), "special": str(special)}


def _outputs_of_the_user(work):
    """Files no tool may replace: the user's, a read-only one, a link, a job folder of the user's."""
    (work / "user.json").write_text('{"mine": 1}')
    (work / "locked.json").write_text("{}")
    os.chmod(work / "locked.json", 0o444)
    os.symlink(work / "afile", work / "link.json")
    (work / "mainout").mkdir()
    (work / "mainout" / "manifold.npz").write_bytes(b"the user's manifold")


def _claim(path, width, height, depth=None):
    """Make the PNG ``path`` claim another size (and bit depth) in its header, data unchanged."""
    data = bytearray(path.read_bytes())
    data[16:24] = struct.pack(">II", width, height)
    data[24] = data[24] if depth is None else depth
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    path.write_bytes(bytes(data))


def _targets(work, basis):
    """Match targets: a 16-bit greyscale PNG of the basis's size, one too small, one claiming
    20000x20000 pixels, one claiming 16-bit colour."""
    from PIL import Image

    grey = imageio.read_exr(os.path.join(basis, "base.exr")).mean(axis=-1) + 0.2
    codes = np.round(imageio.srgb_encode(grey / grey.max() * 0.9) * 65535).astype(np.uint16)
    Image.fromarray(codes).save(work / "t16.png")
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(work / "small.png")
    for name, size, depth in (("bomb.png", (20000, 20000), None), ("rgb16.png", (8, 8), 16)):
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(work / name)
        _claim(work / name, *size, depth)


odd = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([1e10, -1e10, 1e300, 0.0, -0.0])
)
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
        for tag, folder in (
            ("WORK/", data["work"]),
            ("BASIS/", data["basis"]),
            ("SPECIAL/", data["special"]),
        ):
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
    assert "Traceback" not in err, err
    return refused_cleanly(rc, err, before, folders), err


def _refused(data, tool, lead, args):
    """Run an argument list holding a refused value: exit 2, one error line, no file changed
    (the FIFO still a FIFO)."""
    refused, err = _run(tool, lead, args, False, [data["work"], data["basis"]])
    assert refused, (args, err)
    assert stat.S_ISFIFO(os.stat(os.path.join(data["special"], "fifo.json")).st_mode)


@st.composite
def options(draw, good):
    """Options of ``good`` ({option: strategy of valid values}), each perhaps left out."""
    args = []
    for option, values in good.items():
        if draw(st.booleans()):
            args += [option, str(draw(values))]
    return args


@st.composite
def faulty(draw, good, bad):
    """:func:`options` of ``good``, then 1 to 3 faults of ``bad`` (strategies of argument lists,
    each refused before any work): the faults come last, so that they win."""
    args = draw(options(good))
    for fault in draw(st.lists(st.sampled_from(bad), min_size=1, max_size=3)):
        args += draw(fault)
    return args


def _opt(option, *values):
    return st.tuples(st.just(option), st.sampled_from([str(v) for v in values])).map(list)


JSON_FAULTS = [
    "WORK/user.json",
    "WORK/locked.json",
    "WORK/link.json",
    "SPECIAL/fifo.json",
    "WORK/afile/x.json",
]


BLEND_OUTS = (
    ["WORK/img.exr", "WORK/sub/img.exr"],
    ["WORK/img.txt", "WORK/user.exr", "WORK/afile/img.exr", "BASIS/x.exr", "BASIS/base.exr"],
)


@st.composite
def blend_args(draw):
    """``(args, given, out, valid)``: half the cases use only valid values (they must succeed)."""
    valid = draw(st.booleans())
    args, given = [], {}
    if draw(st.booleans()):
        xs = draw(
            st.lists(st.floats(-3, 3), min_size=2, max_size=2)
            if valid
            else st.one_of(st.lists(numbers, min_size=2, max_size=2), st.lists(numbers, max_size=3))
        )
        args += ["--x", ",".join(_fmt(v) for v in xs) if xs else "abc"]
        given["x"] = xs
    else:
        a = draw(st.sampled_from(NAMES + ([] if valid else ["adamantium", "0,0", "nan,1"])))
        b = draw(
            st.sampled_from([n for n in NAMES + ["1,1"] if n != a or not valid])
        )  # same ends: refused
        steps = draw(st.integers(2, 4) if valid else st.integers(-1, 4))
        args += ["--path", a, b, "--steps", str(steps)]
        given["path"] = (a, b, steps)
    _options(
        draw,
        valid,
        args,
        given,
        [("--exposure", st.floats(-8, 8), odd), ("--prune", st.floats(0, 0.5), odd)],
    )
    if draw(st.booleans()):
        args.append("--png")
    return _with_out(draw, valid, args, given, BLEND_OUTS)


@settings(max_examples=60, **SETTINGS)
@given(case=blend_args())
def test_blend_cli_succeeds_or_refuses_cleanly(data, case):
    args, given, valid = _place(case, data)
    basis_before, out = snapshot(data["basis"]), given["--out"]
    refused, err = _run(
        "blend", ["--basis", data["basis"]], args, valid, [data["work"], data["basis"]]
    )
    if refused:
        return
    assert "Traceback" not in err
    assert all(math.isfinite(v) for v in given.get("x", [])) and len(given.get("x", [0, 0])) == 2
    assert math.isfinite(given.get("--exposure", 0.0)) and abs(given.get("--exposure", 0.0)) <= 64
    assert 0 <= given.get("--prune", 0.0) < 1
    assert snapshot(data["basis"]) == basis_before  # a blend never touches its basis
    stem = out[:-4]
    exrs = [out] if "x" in given else [f"{stem}_{s}.exr" for s in range(given["path"][2])]
    for path in exrs:
        img = imageio.read_exr(path)
        assert img.shape == (8, 8, 3) and np.isfinite(img).all()
        if "--png" in args:
            assert os.path.getsize(path[:-4] + ".png") > 0


FIT_OUTS = (
    ["WORK/m.npz", "WORK/sub/m.npz"],
    ["WORK/user.exr", "WORK/afile/m.npz", "WORK/afile", "WORK/m.json", "WORK/m"],
)


@st.composite
def fit_args(draw):
    """``(args, given, out, valid)``: half the cases use only valid values (they must succeed)."""
    valid, args, given, one = draw(st.booleans()), [], {}, st.sampled_from
    _options(
        draw,
        valid,
        args,
        given,
        [
            ("--q", st.integers(1, 3), st.integers(-1, 9)),
            ("--length-scale", st.floats(0.5, 2), odd),
            ("--noise", st.floats(1e-5, 1e-2), odd),
            ("--stress", one([0.0, 5.0]), st.just(-1.0) | odd),
            (
                "--materials",
                one(["steel,chrome", "chrome,gold-paint,pink-fabric"]),
                one(["steel", "steel,adamantium", "steel,steel", ","]),
            ),
            ("--method", one(["lbfgs", "newton"]), one(["newtons", "hooke-jeeves"])),
            ("--features", one(["raw", "log"]), st.just("sqrt")),
            ("--plot", st.just("WORK/plots"), one(["WORK/afile", "WORK/afile/sub"])),
        ],
    )
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


MAIN_GOOD = {
    "--resolution": st.just("8,8,16"),
    "--res": st.sampled_from([8, 16]),
    "--spp": st.just(1),
    "--ref-spp": st.just(1),
    "--q": st.integers(1, 3),
    "--scene": st.sampled_from(["sphere", "table"]),
    "--mode": st.sampled_from(["onepass", "per-material"]),
}
MAIN_BAD = [
    _opt("--res", 0, -3, 10**6, "abc"),
    _opt("--spp", 0, -1),
    _opt("--ref-spp", 0),
    _opt("--q", 0, 9),
    _opt("--scene", "tabel", "missing.xml"),
    _opt("--resolution", "0,8,16", "8,8", "a,b,c"),
    _opt("--out", "WORK/afile", "WORK/afile/sub", "WORK/mainout"),
    _opt("--mode", "fast"),
    _opt("--features", "sqrt"),
]


@settings(max_examples=40, **SETTINGS)
@given(args=faulty(MAIN_GOOD, MAIN_BAD))
def test_main_job_cli_refuses_cleanly_before_any_work(data, args):
    args, _, _ = _place((["--out", "WORK/mj"] + args, {}, False), data)
    _refused(data, "main_job", [], args)
    assert not os.path.exists(os.path.join(data["work"], "mj", "database"))


RENDER_GOOD = {
    "--res": st.just(8),
    "--spp": st.integers(1, 2),
    "--mode": st.just("per-material"),
    "--seed": st.integers(0, 5),
    "--views": st.just("0"),
}
RENDER_BAD = [
    _opt("--seed", -1, 2**64, 2**32),
    _opt("--spp", 0, -2),
    _opt("--chunks", 0, -1),
    _opt("--views", "0,0", "-1", "x", "3"),
    _opt("--res", 0, 20000),
    _opt("--mode", "fast"),
    _opt("--executor", "dask"),
    _opt("--out", "WORK/."),
]


@settings(max_examples=40, **SETTINGS)
@given(
    scene=st.sampled_from(["sphere", "SCENE", "missing.xml", "WORK/afile"]),
    args=faulty(RENDER_GOOD, RENDER_BAD),
)
def test_render_basis_cli_refuses_cleanly_before_rendering(data, scene, args):
    from guarantees_helpers import SPHERE

    args, _, _ = _place(
        (
            [
                SPHERE if scene == "SCENE" else scene,
                "--manifold",
                data["manifold"],
                "--out",
                "WORK/rb",
            ]
            + args,
            {},
            False,
        ),
        data,
    )
    _refused(data, "render_basis", [], args)


MATCH_GOOD = {
    "--starts": st.just(1),
    "--max-iter": st.integers(1, 3),
    "--scan": st.sampled_from([0, 16]),
    "--json": st.just("WORK/m.json"),
    "--out": st.just("WORK/best.exr"),
    "--prior": st.just(0.0),
}
MATCH_BAD = [
    _opt("--starts", 0),
    _opt("--max-iter", 0),
    _opt("--scan", -1),
    _opt("--spp", 0),
    _opt("--seed", -1, 2**32),
    _opt("--out", "WORK/m.txt", "WORK/user.exr", "BASIS/x.exr"),
    _opt("--json", "WORK/m.txt", *JSON_FAULTS),
    _opt("--prior", "nan", -1),
    _opt(
        "--image",
        "WORK/bomb.png",
        "WORK/rgb16.png",
        "WORK/small.png",
        "WORK/none.png",
        "WORK/afile",
    ),
    _opt("--mask", "WORK/small.png", "WORK/bomb.png"),
]


@settings(max_examples=40, **SETTINGS)
@given(
    case=st.one_of(
        options(MATCH_GOOD).map(lambda a: (a, True)),
        faulty(MATCH_GOOD, MATCH_BAD).map(lambda a: (a, False)),
    ),
    extra=st.sampled_from([[], ["--log"], ["--exposure-free"]]),
)
def test_match_cli_succeeds_or_refuses_cleanly(data, case, extra):
    """Valid lists match the 16-bit greyscale target over all its 64 pixels (issue 20: it was
    cut to 8 bits, every pixel clipped)."""
    args, _, valid = _place((["--image", "WORK/t16.png"] + case[0] + extra, {}, case[1]), data)
    if not valid:
        return _refused(data, "match", ["--basis", data["basis"]], args)
    before = snapshot(data["basis"])
    rc, out, err = run_tool("match", "--basis", data["basis"], *args)
    assert rc == 0 and "over 64 pixels" in out and "clipped" not in out, (args, out, err)
    assert snapshot(data["basis"]) == before
    if "--json" in args:
        assert os.path.getsize(os.path.join(data["work"], "m.json")) > 0


#: Faults of bench.py: ``(benchmark or None, arguments)``; the benchmark replaces the drawn one.
BENCH_BAD = [
    st.tuples(st.none(), _opt("--json", *JSON_FAULTS, "WORK/.")),
    st.just((None, ["--materials", ","])),
    st.just(("nope", [])),
    st.just(("fit", ["--manifold", "MANIFOLD"])),
    st.just(("explore", [])),
    st.just(("space", ["--folds", "a"])),
]


@settings(max_examples=30, **SETTINGS)
@given(
    which=st.sampled_from(["fit", "interp", "stability", "pca"]),
    faults=st.lists(st.one_of(BENCH_BAD), min_size=1, max_size=2),
)
def test_bench_cli_refuses_cleanly_before_running(data, which, faults):
    args = ["--json", "WORK/b.json"]
    for bench, extra in faults:
        which = bench or which
        args += [data["manifold"] if a == "MANIFOLD" else a for a in extra]
    args, _, _ = _place(([which, "--database", data["db"]] + args, {}, False), data)
    _refused(data, "bench", [], args)

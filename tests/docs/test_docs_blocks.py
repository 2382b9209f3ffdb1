"""Every code block of the README and the documentation runs as written, at a small size.

The ``python``, ``sh`` and ``xml`` blocks of each page run in order in one folder (a later block
may use what an earlier one wrote, as a reader following the page would), each in a fresh
process that imports this checkout (the shipped data of :data:`SHIPPED_DATA` linked in, as a reader
running them from the checkout's root finds it):

- ``python``: the block, run with ``python3 -c``;
- ``sh``: each command, which must be ``python3 tools/NAME.py ...`` or
  ``python3 docs/tutorials/NAME.py ...``;
- ``xml``: loaded with ``mi.load_string`` (``version`` added to its root element); a block
  marked ``<!-- file: NAME -->`` is written to ``NAME`` instead, for a later block to use.

A basis render (``tools/render_basis.py``) that another page ran with the same arguments is
copied from that page's folder instead of rendered again (the same command on the same inputs).

Sizes are made small by rewriting sample counts, resolutions, step and iteration counts
(:data:`SMALLER`); nothing else of a block changes. A block preceded by
``<!-- not run: REASON -->`` is skipped, and :data:`MAX_NOT_RUN` bounds how many may be.
"""

import glob
import os
import re
import shlex
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
#: Generated pages (no examples of their own).
GENERATED = {"docs/reference/cli.md", "docs/reference/formats.md", "docs/benchmarks.md"}
#: Languages that run.
RUN = ("python", "sh", "xml")
#: How many blocks of all pages may be marked not run.
MAX_NOT_RUN = 10
#: Sizes -> the tests' (regular expression, replacement).
SMALLER = [
    (r"--spp \d+", "--spp 4"),
    (r"--res \d+", "--res 16"),
    (r"--steps \d+", "--steps 3"),
    (r"--chunks \d+", "--chunks 2"),
    (r"\bspp=\d+", "spp=4"),
    (r"\bres=\d+", "res=16"),
    (r'"width": \d+, "height": \d+', '"width": 16, "height": 16'),
    (r"\brange\(\d+\)", "range(2)"),
]
_FENCE = re.compile(r"^```(\w+)[^\n]*\n(.*?)^```", re.S | re.M)
_MARK = re.compile(r"<!--\s*(not run|file):\s*(.*?)\s*-->\s*$")


def pages():
    found = ["README.md"] + sorted(
        os.path.relpath(p, ROOT)
        for p in glob.glob(os.path.join(ROOT, "docs", "**", "*.md"), recursive=True)
        if "_build" not in p
    )
    return [p for p in found if p not in GENERATED]


def blocks(page):
    """``[(language, code, mark, argument, line)]`` of ``page``'s fenced blocks; ``mark``
    (``not run`` or ``file``) from an HTML comment on the line before the fence."""
    text = open(os.path.join(ROOT, page), encoding="utf-8").read()
    out = []
    for m in _FENCE.finditer(text):
        before = text[: m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        mark = _MARK.search(before)
        line = text[: m.start()].count("\n") + 1
        out.append((m.group(1), m.group(2), mark and mark.group(1), mark and mark.group(2), line))
    return out


def small(code):
    for big, little in SMALLER:
        code = re.sub(big, little, code)
    return code


def commands(code):
    """The commands of a shell block: continuation lines joined, comments dropped."""
    joined = re.sub(r"\\\n\s*", " ", code)
    return [ln.split(" #")[0].strip() for ln in joined.splitlines() if ln.split(" #")[0].strip()]


#: Basis renders already run: their arguments -> the folder they wrote.
_RENDERED = {}


def _run(argv, cwd, what):
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, check=False)
    assert r.returncode == 0, f"{what} failed:\n{r.stdout[-1500:]}\n{r.stderr[-3000:]}"
    return r


def run_block(lang, code, work, what):
    code = small(code)
    if lang == "python":
        _run([sys.executable, "-c", code], work, what)
    elif lang == "sh":
        for c in commands(code):
            words = shlex.split(c)
            assert words[0] == "python3" and re.match(
                r"(tools|docs/tutorials)/\w+\.py$", words[1]
            ), (
                f"{what}: only python3 tools/*.py and docs/tutorials/*.py commands run here, "
                f"got {c!r}: mark the block <!-- not run: REASON -->"
            )
            out = words[words.index("--out") + 1] if "--out" in words else None
            key = tuple(words) if words[1] == "tools/render_basis.py" and out else None
            if key in _RENDERED and os.path.isdir(_RENDERED[key]):
                shutil.copytree(_RENDERED[key], os.path.join(work, out))
                continue
            _run([sys.executable, os.path.join(ROOT, words[1])] + words[2:], work, f"{what}: {c}")
            if key:
                _RENDERED[key] = os.path.join(work, out)
    else:
        xml = re.sub(r"^(\s*<\w+)", r'\1 version="3.0.0"', code, count=1)
        script = (
            "import sys, mitsuba as mi, mitsuba_manifold.render\n"
            "mi.set_variant('llvm_ad_rgb')\n"
            "print(mi.load_string(sys.argv[1]))\n"
        )
        _run([sys.executable, "-c", script, xml], work, what)


def test_every_page_with_code_is_covered():
    counted = [b for p in pages() for b in blocks(p) if b[0] in RUN]
    assert len(counted) >= 20
    skipped = [b for b in counted if b[2] == "not run"]
    assert len(skipped) <= MAX_NOT_RUN, [(b[1][:60], b[3]) for b in skipped]
    assert all(b[3] for b in skipped)  # each says why


def _run_elsewhere():
    """Pages whose commands another test runs in their context: the tutorials' pages (each shows
    its script, docs/tutorials/NAME.py) show commands to run after the tutorial scripts, which
    tests/docs/test_docs_tutorials.py runs in that order."""
    return {
        p
        for p in pages()
        if p.startswith("docs/tutorials/")
        and re.search(r"literalinclude\W+\w+\.py", open(os.path.join(ROOT, p)).read())
    }


def _pages_with_code():
    elsewhere = _run_elsewhere()
    return [
        p
        for p in pages()
        if p not in elsewhere and any(b[0] in RUN and b[2] != "not run" for b in blocks(p))
    ]


def test_pages_run_elsewhere_hold_only_what_runs_there():
    """A tutorial page's runnable blocks are ``sh`` blocks of tool commands, each of which the
    tutorials' test runs (so leaving those pages out here skips nothing)."""
    from test_docs_tutorials import PAGES, sh_commands

    assert _run_elsewhere() == {f"docs/tutorials/{page}" for page, _ in PAGES.values()}
    for page in _run_elsewhere():
        code = [b for b in blocks(page) if b[0] in RUN and b[2] != "not run"]
        assert all(b[0] == "sh" for b in code), page
        run = sh_commands(os.path.join(ROOT, page))
        assert all(c in run for b in code for c in commands(b[1])), page


#: Data the pages name by their path in a checkout (read only): linked into the work folder.
SHIPPED_DATA = ("docs/tutorials/data",)


@pytest.mark.render
@pytest.mark.parametrize("page", _pages_with_code())
def test_the_pages_blocks_run(page, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    for data in SHIPPED_DATA:  # the commands run where a reader would: the checkout's root
        (work / data).parent.mkdir(parents=True, exist_ok=True)
        (work / data).symlink_to(os.path.join(ROOT, data), target_is_directory=True)
    for lang, code, mark, arg, line in blocks(page):
        if lang not in RUN or mark == "not run":
            continue
        what = f"{page}:{line} ({lang})"
        if mark == "file":
            path = work / arg
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(small(code), encoding="utf-8")
            continue
        run_block(lang, code, work, what)

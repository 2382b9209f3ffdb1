"""The tutorials and the gallery run (at a tiny size), their pages show what they make, and every
tool command written in the documentation is one the tool accepts."""

import glob
import os
import re
import shlex
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DOCS = os.path.join(ROOT, "docs")
sys.path[:0] = [DOCS, os.path.join(DOCS, "_ext")]
import clidoc  # noqa: E402
import gallery  # noqa: E402  (docs/gallery.py: the tutorials' order)
from test_docs_blocks import small  # noqa: E402
from test_docs_readme import parse  # noqa: E402

#: Each tutorial's page and the images it writes.
PAGES = {
    "manifold_tour": ("manifold-tour.md", ["manifold_tour.png"]),
    "own_scene": ("own-scene.md", ["own_scene.png"]),
    "basis_blend": ("basis-blend.md", ["basis_blend.png", "basis_parts.png"]),
    "inverse": ("inverse.md", ["inverse.png", "inverse_loss.png"]),
    "acquire": ("acquire.md", ["acquire.png"]),
}


def env():
    return dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))


def doc_pages():
    return [
        p
        for p in glob.glob(os.path.join(DOCS, "**", "*.md"), recursive=True)
        if "_build" not in p and not p.endswith(os.path.join("reference", "cli.md"))
    ]


def sh_commands(path):
    """``python3 tools/...`` lines of the ``sh`` blocks of a page (continuations joined)."""
    out = []
    for block in re.findall(r"```sh\n(.*?)```", open(path, encoding="utf-8").read(), re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split("#")[0].strip()
            if line.startswith("python3 tools/"):
                out.append(line)
    return out


def test_every_tutorial_has_a_page_showing_its_images():
    scripts = sorted(
        os.path.basename(p)[:-3] for p in glob.glob(os.path.join(DOCS, "tutorials", "*.py"))
    )
    assert scripts == sorted(gallery.TUTORIALS) == sorted(PAGES)
    for name, (page, images) in PAGES.items():
        text = open(os.path.join(DOCS, "tutorials", page), encoding="utf-8").read()
        assert f"literalinclude:: {name}.py" in text.replace(
            "{literalinclude} ", "literalinclude:: "
        )
        for image in images:
            assert f"_static/tutorials/{image}" in text
            assert os.path.getsize(os.path.join(DOCS, "_static", "tutorials", image)) > 0


@pytest.mark.render
def test_tutorials_run_in_order_and_their_commands_too(tmp_path):
    out = tmp_path / "out" / "tutorials"
    for name in gallery.TUTORIALS:
        r = subprocess.run(
            [
                sys.executable,
                os.path.join(DOCS, "tutorials", f"{name}.py"),
                "--out",
                str(out),
                "--small",
            ],
            env=env(),
            capture_output=True,
            text=True,
        )
        assert r.returncode == 0, f"{name}: {r.stderr[-2000:]}"
        for image in PAGES[name][1]:
            assert (out / image).stat().st_size > 0, image
    # The commands shown on the tutorial pages, at a small size, after the tutorials.
    commands = [
        c for page, _ in PAGES.values() for c in sh_commands(os.path.join(DOCS, "tutorials", page))
    ]
    assert commands
    data = tmp_path / "docs" / "tutorials" / "data"  # the shipped photo, where a reader finds it
    data.parent.mkdir(parents=True)
    data.symlink_to(os.path.join(DOCS, "tutorials", "data"), target_is_directory=True)
    for c in commands:
        words = shlex.split(small(c))
        r = subprocess.run(
            [sys.executable, os.path.join(ROOT, words[1])] + words[2:],
            cwd=tmp_path,
            env=env(),
            capture_output=True,
            text=True,
        )
        assert r.returncode == 0, f"{c}: {r.stderr[-2000:]}"


@pytest.mark.render
def test_a_tutorial_run_before_the_first_says_which_to_run_in_one_line(tmp_path):
    """Tutorials 2 to 4 on a folder without tutorial 1's manifold: one ``error:`` line naming
    the file and the tutorial to run first, no traceback, nothing written."""
    for name in gallery.TUTORIALS[1:]:
        r = subprocess.run(
            [sys.executable, os.path.join(DOCS, "tutorials", f"{name}.py"), "--out", str(tmp_path)]
            + ["--small"],
            env=env(),
            capture_output=True,
            text=True,
        )
        err = r.stderr.strip()
        assert r.returncode == 1 and "\n" not in err and "Traceback" not in err, f"{name}: {err}"
        assert "manifold.npz does not exist: run tutorial 1 first" in err, f"{name}: {err}"
    assert os.listdir(tmp_path) == []


@pytest.mark.render
def test_gallery_runs(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            os.path.join(DOCS, "gallery.py"),
            "--out",
            str(tmp_path),
            "--small",
            "--no-tutorials",
        ],
        env=env(),
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(os.listdir(tmp_path)) == ["latent_grid.png", "measured.png"]


@pytest.mark.render  # some tools' modules import Mitsuba (match.py --render)
def test_every_documented_tool_command_parses():
    commands = [c for p in doc_pages() for c in sh_commands(p)]
    assert len(commands) >= 15
    for c in commands:
        parse(c)  # SystemExit on an option the tool does not take


@pytest.mark.render  # some tools' modules import Mitsuba (match.py --render)
def test_cli_reference_lists_every_tool():
    text = clidoc.page(ROOT)
    for script in glob.glob(os.path.join(ROOT, "tools", "*.py")):
        assert f"tools/{os.path.basename(script)}`" in text
    assert "tools/match.py --render" in text
    # the console command of each tool as the dispatcher names it; bench.py has none
    assert "Installed as `mitsuba-manifold render-basis`" in text
    assert "Installed as `mitsuba-manifold fit`" in text and "mitsuba-manifold bench" not in text

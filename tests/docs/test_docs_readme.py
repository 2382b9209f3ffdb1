"""The README says what is true: its size and picture, its links, every command and snippet in it
(run at a small size, or checked against the tool's own parser where a run would take minutes)."""

import os
import re
import shlex
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
README = os.path.join(ROOT, "README.md")
sys.path.insert(0, os.path.join(ROOT, "docs", "_ext"))
import clidoc  # noqa: E402  (the command-line reference's parser capture)

#: Commands too long for the suite: how they were last run instead.
TOO_LONG = {
    "tools/main.py": "`tools/setup.sh && python3 tools/main.py` in a fresh clone: "
    "about 5 minutes on 2 CPU cores",
}
#: Sizes of the README's commands and snippets -> the tests' (the same code, smaller).
SMALLER = [
    ("--spp 64", "--spp 4"),
    ("--res 128", "--res 16"),
    ("--steps 8", "--steps 3"),
    ('"width": 128, "height": 128', '"width": 16, "height": 16'),
    ("spp=64", "spp=4"),
    ("res=64", "res=16"),
    ("spp=256", "spp=8"),
    ("spp=16", "spp=2"),
    ("range(60)", "range(2)"),
]


def text():
    return open(README, encoding="utf-8").read()


def blocks(lang):
    return re.findall(rf"```{lang}\n(.*?)```", text(), re.S)


def tool_commands():
    """Every ``python3 tools/NAME.py ...`` of the README: shell blocks and inline code."""
    found = []
    for block in blocks("sh"):
        for line in block.splitlines():
            for part in line.split("#")[0].split("&&"):
                if part.strip().startswith("python3 tools/"):
                    found.append(part.strip())
    found += [c for c in re.findall(r"`(python3 tools/[^`]+)`", text())]
    return found


def small(code):
    for big, little in SMALLER:
        code = code.replace(big, little)
    return code


def parse(command):
    """The tool's own parser's reading of ``command`` (SystemExit if it refuses it)."""
    words = shlex.split(command)
    script = os.path.join(ROOT, words[1])
    argv = words[2:]
    sub = [a for a in clidoc.SUB_MODES.get(os.path.basename(script)[:-3], [[]])[0] if a in argv]
    parser = clidoc.parser_of(clidoc.tool_module(script), sub)
    return parser.parse_args([a for a in argv if a not in sub])


def test_one_or_two_screens_with_a_picture_first():
    lines = text().splitlines()
    assert len(lines) <= 150
    first = "\n".join(lines[:30])
    assert re.search(r"<img src=|!\[", first)


def test_links_and_images_exist():
    targets = re.findall(r'\]\(([^)#]+)(?:#[^)]*)?\)|src="([^"]+)"', text())
    local = [a or b for a, b in targets if not (a or b).startswith("http")]
    assert local
    for t in local:
        assert os.path.exists(os.path.join(ROOT, t)), t


def test_no_run_logs():
    """No dates of runs, loads or commit hashes (measurements live on the benchmarks page)."""
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text())
    assert "load average" not in text()
    assert not re.search(r"\bcommit [0-9a-f]{7,}\b", text())


def test_the_two_commands_are_what_ci_runs():
    ci = open(os.path.join(ROOT, ".ci", "run"), encoding="utf-8").read()
    assert "tools/setup.sh" in ci and "python3 -m pytest -q" in ci
    assert "tools/setup.sh && python3 -m pytest -q" in text()
    docs = re.search(r"python3 -m sphinx -W[^\n`]*", ci).group(0).replace(" -q", "")
    assert " ".join(docs.split()) in " ".join(text().split())


@pytest.mark.render  # some tools' modules import Mitsuba (match.py --render)
def test_every_tool_command_parses():
    commands = tool_commands()
    assert len(commands) >= 5
    for c in commands:
        parse(c)  # raises SystemExit on an option the tool does not know


@pytest.mark.render  # some tools' modules import Mitsuba (match.py --render)
def test_explore_command_names_the_main_jobs_basis():
    d = clidoc.parser_of("mitsuba_manifold.apps.cli.main_job").parse_args([])
    folder = f"{d.out}/gi/basis_{d.scene}_{d.res}_{d.spp}_{d.mode}"
    explore = [c for c in tool_commands() if "tools/explore.py" in c]
    assert explore and all(parse(c).basis == [folder] for c in explore)
    helptext = clidoc.parser_of("mitsuba_manifold.apps.cli.explore").format_help()
    assert re.findall(r"out/gi/basis_\w+", helptext) == [folder]


def test_too_long_commands_are_listed():
    for c in tool_commands():
        script = shlex.split(c)[1]
        if script in TOO_LONG:
            assert TOO_LONG[script]


@pytest.fixture
def workdir(tmp_path, small_manifold):
    """A folder holding ``out/manifold.npz`` (a small manifold of the test database) and the
    environment that imports this checkout."""
    os.makedirs(tmp_path / "out")
    shutil.copy(small_manifold, tmp_path / "out" / "manifold.npz")
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return tmp_path, env


@pytest.mark.render
def test_basis_and_blend_commands_run(workdir):
    cwd, env = workdir
    commands = [c for c in tool_commands() if "render_basis.py" in c or "blend.py" in c]
    assert len(commands) == 3
    for c in commands:
        words = shlex.split(small(c))
        subprocess.run(
            [sys.executable, os.path.join(ROOT, words[1])] + words[2:],
            cwd=cwd,
            env=env,
            check=True,
            capture_output=True,
        )
    assert (cwd / "gold.png").stat().st_size > 0
    assert list(cwd.glob("walk*.exr"))


@pytest.mark.render
@pytest.mark.parametrize("index", [0, 1])
def test_python_snippets_run(workdir, index):
    cwd, env = workdir
    snippets = blocks("python")
    assert len(snippets) == 2
    r = subprocess.run(
        [sys.executable, "-c", small(snippets[index])],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    if index == 0:
        assert (cwd / "ball.png").stat().st_size > 0
    else:
        assert "found" in r.stdout

"""The README says what is true: its size and picture, its links, every command in it checked
against the tool's own parser (test_docs_blocks.py runs its blocks at a small size)."""

import os
import re
import shlex
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
    assert len(lines) <= 170
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

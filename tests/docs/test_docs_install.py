"""What the install instructions promise: the extras they name exist, the docs extra builds the
site, and the explorer without its extra says which one to install."""

import os
import re
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
tomllib = pytest.importorskip("tomllib")


def project():
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        return tomllib.load(f)["project"]


def test_extras_named_in_the_readme_exist():
    readme = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    named = set(re.findall(r"\[(explore|ray|test|docs)\]", readme))
    assert named == {"explore", "ray", "test", "docs"}
    assert named <= set(project()["optional-dependencies"])


def test_metadata_is_complete():
    p = project()
    assert p["license"] == "BSD-3-Clause" and p["authors"] and p["classifiers"]
    # no invented URL: every project URL, if any, is one the project has
    assert "urls" not in p or all(
        "mitsuba-manifold/mitsuba-manifold" not in u for u in p["urls"].values()
    )
    for f in p["license-files"]:
        assert os.path.isfile(os.path.join(ROOT, f)), f
    assert p["version"] in open(os.path.join(ROOT, "CITATION.cff"), encoding="utf-8").read()


def test_read_the_docs_builds_what_ci_builds():
    text = open(os.path.join(ROOT, ".readthedocs.yaml"), encoding="utf-8").read()
    assert "configuration: docs/conf.py" in text and "fail_on_warning: true" in text
    assert re.search(r"extra_requirements:\s*- docs", text)


def test_setup_installs_the_docs_extra_and_ci_builds_with_warnings_as_errors():
    setup = open(os.path.join(ROOT, "tools", "setup.sh"), encoding="utf-8").read()
    assert re.search(r'-e "\.\[[^\]]*docs[^\]]*\]"', setup)
    ci = open(os.path.join(ROOT, ".ci", "run"), encoding="utf-8").read()
    assert re.search(r"python3 -m sphinx -W .*docs docs/_build/html", ci)


def test_ci_runs_the_suite_in_a_clone_with_nothing_beside_it():
    """The suite runs from ``git clone`` of the checkout into a fresh temporary folder, so a file
    beside the checkout or left untracked in it cannot make it pass."""
    ci = open(os.path.join(ROOT, ".ci", "run"), encoding="utf-8").read()
    clone = ci.index('git clone -q "$PWD" "$tmp/mitsuba-manifold"')
    assert 'tmp="$(mktemp -d)"' in ci and ci.index('cd "$tmp/mitsuba-manifold"') > clone
    assert ci.rindex("python3 -m pytest -q") > clone


def test_explorer_without_its_extra_names_it(monkeypatch, capsys):
    from mitsuba_manifold.apps.cli import explore

    monkeypatch.setitem(sys.modules, "uvicorn", None)  # import uvicorn raises ImportError
    assert explore.main(["--basis", "somewhere", "--port", "0"]) == 2
    assert "pip install 'mitsuba-manifold[explore]'" in capsys.readouterr().err

"""The main job end to end on tiny settings: every output it promises, and its report."""

import json
import os
import re
import shlex
import subprocess
import sys

import pytest

from mitsuba_manifold.apps import pipeline
from mitsuba_manifold.apps.cli import main_job
from mitsuba_manifold.errors import InputError

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.mark.parametrize(
    "option, value, expect",
    [
        ("--res", "0", "--res 0"),
        ("--spp", "-1", "--spp -1"),
        ("--ref-spp", "0", "--ref-spp 0"),
        ("--q", "9", "--q 9"),
        ("--q", "0", "--q 0"),
        ("--scene", "tabel", "did you mean 'table'"),
        ("--scene", "missing.xml", "--scene 'missing.xml'"),
        ("--res", "1000000", "choose a smaller value"),
    ],
)
def test_main_job_refuses_bad_options_before_writing_anything(
    tmp_path, capsys, option, value, expect
):
    out = tmp_path / "mj"
    with pytest.raises(SystemExit) as e:
        main_job.main(["--out", str(out), "--resolution", "8,8,16", option, value])
    err = capsys.readouterr().err.strip()
    assert (
        e.value.code == 2 and len(err.splitlines()) == 1 and err.startswith(f"error: {option}")
    ), err
    assert expect in err and ("e.g." in err or "shipped scenes" in err or "smaller" in err), err
    assert not out.exists()  # checked before the database, the fit or any plot


def readme_outputs(points=("training", "midpoint", "extrapolated"), scene="table"):
    """The files the getting-started page's table of main-job outputs names (braces expanded,
    ``table_*`` as the three points), without the folders and per-material entries."""
    text = open(os.path.join(ROOT, "docs", "getting-started.md")).read()
    table = text[text.index("| output | what |") :]
    table = table[: table.index("\n\n")]
    names = []
    for cell in re.findall(r"^\| (.*?) \|", table, re.M):
        for pattern in re.findall(r"`([^`]+)`", cell):
            pattern = pattern.removeprefix("out/").replace(
                f"{scene}_*_", f"{scene}_{{{','.join(points)}}}_"
            )
            names += [
                n
                for n in expand_braces(pattern)
                if "<" not in n and "*" not in n and not n.endswith("/")
            ]
    return names


def expand_braces(pattern):
    m = re.search(r"\{([^{}]*)\}", pattern)
    if not m:
        return [pattern]
    return [
        n
        for alt in m.group(1).split(",")
        for n in expand_braces(pattern[: m.start()] + alt + pattern[m.end() :])
    ]


@pytest.mark.render
def test_main_job_writes_its_outputs_and_measures_its_targets(tmp_path):
    pytest.importorskip("mitsuba")
    lines = []
    report = pipeline.run_main_job(
        str(tmp_path),
        resolution=(8, 8, 16),
        res=16,
        spp=4,
        ref_spp=8,
        direct_spp=(1, 4),
        denoise=True,
        log=lines.append,
    )
    gi = tmp_path / "gi"
    for name in (
        "report.json",
        "gi_error_vs_time.png",
        "table_path_sheet.png",
        "table_extrapolation_sheet.png",
        "table_midpoint_blend.exr",
        "table_midpoint_reference.exr",
        "table_midpoint_error.png",
    ):
        assert (gi / name).is_file(), name
    promised = readme_outputs()  # the docs' table of outputs says what is written
    assert len(promised) > 20
    for name in promised:
        assert (tmp_path / name).exists(), name
    assert (tmp_path / "manifold.npz").is_file() and (
        tmp_path / "plots" / "latent_map.png"
    ).is_file()
    saved = json.loads((gi / "report.json").read_text())
    points = saved["scenes"]["table"]["points"]
    assert [p["point"] for p in points] == ["training", "midpoint", "extrapolated"]
    for p in points:  # the targets the job prints are in its report, computed from its own timings
        v = p["versus_direct"]
        d = next(r for r in p["direct"] if r["spp"] == 4)
        assert v["speedup"] == pytest.approx(d["time_s"] / p["blend"]["time_s"])
        assert v["meets_error_target"] == (p["blend"]["rel_mse"] < d["rel_mse"])
    assert set(saved["stages"]) >= {"tabulate_s", "fit_s", "basis_s", "references_s", "total_s"}
    peak = saved["peak_rss_after"]  # the process's peak memory, per stage, non-decreasing
    assert list(peak)[:4] == ["tabulate", "fit", "plots", "basis"] and list(peak)[-1] == "end"
    assert peak["end"] == saved["peak_rss_bytes"] == max(peak.values()) > 0
    assert list(peak.values()) == sorted(peak.values())
    assert any(line.startswith("peak memory: ") for line in lines)
    assert any("main job done" in line for line in lines) and os.path.isdir(
        report["scenes"]["table"]["basis_folder"]
    )


def test_explore_command_works_from_any_folder(tmp_path, monkeypatch):
    from mitsuba_manifold.apps.cli.explore import command

    monkeypatch.chdir(tmp_path)
    words = shlex.split(
        command(os.path.join("mj", "gi", "basis dir"), os.path.join("mj", "manifold.npz"))
    )
    checkout_tool = os.path.join(ROOT, "tools", "explore.py")
    if os.path.isfile(checkout_tool):  # run from a checkout: its own tool, by absolute path
        assert words[:2] == ["python3", checkout_tool]
    else:  # an installed package: the console script
        assert words[:2] == ["mitsuba-manifold", "explore"]
    assert words[words.index("--basis") + 1] == str(tmp_path / "mj" / "gi" / "basis dir")
    assert words[words.index("--manifold") + 1] == str(tmp_path / "mj" / "manifold.npz")


def test_the_pipeline_names_python_parameters_and_imports_no_tool():
    """Called from Python, the main job's checks name its parameters (the tool writes its
    options, test above); the pipeline shares the explore command line, not the CLI module."""
    with pytest.raises(InputError, match=r"^`res` 0 is not allowed: .*\(e\.g\. `res` 256\)"):
        pipeline.MainJob("out", res=0).check()
    with pytest.raises(InputError, match=r"^`ref_spp` -1 is not allowed"):
        pipeline.MainJob(
            "out", (8, 8, 16), q=None, scene="table", res=16, spp=4, ref_spp=-1
        ).check()
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, mitsuba_manifold.apps.pipeline\n"
            "print([m for m in sys.modules if m.startswith('mitsuba_manifold.apps.cli')])",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")),
    )
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stderr[-2000:]

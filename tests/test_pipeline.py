"""The main job end to end on tiny settings: every output it promises, and its report."""

import json
import os

import pytest

mi = pytest.importorskip("mitsuba")

from mitsuba_manifold import pipeline  # noqa: E402

pytestmark = pytest.mark.render


def test_main_job_writes_its_outputs_and_measures_its_targets(tmp_path):
    lines = []
    report = pipeline.run_main_job(str(tmp_path), resolution=(8, 8, 16), res=16, spp=4, ref_spp=8,
                                   direct_spp=(1, 4), denoise=False, log=lines.append)
    gi = tmp_path / "gi"
    for name in ("report.json", "gi_error_vs_time.png", "table_path_sheet.png", "table_extrapolation_sheet.png",
                 "table_midpoint_blend.exr", "table_midpoint_reference.exr", "table_midpoint_error.png"):
        assert (gi / name).is_file(), name
    assert (tmp_path / "manifold.npz").is_file() and (tmp_path / "plots" / "latent_map.png").is_file()
    saved = json.loads((gi / "report.json").read_text())
    points = saved["scenes"]["table"]["points"]
    assert [p["point"] for p in points] == ["training", "midpoint", "extrapolated"]
    for p in points:   # the targets the job prints are in its report, computed from its own timings
        v = p["versus_direct"]
        d = next(r for r in p["direct"] if r["spp"] == 4)
        assert v["speedup"] == pytest.approx(d["time_s"] / p["blend"]["time_s"])
        assert v["meets_error_target"] == (p["blend"]["rel_mse"] < d["rel_mse"])
    assert set(saved["stages"]) >= {"tabulate_s", "fit_s", "basis_s", "references_s", "total_s"}
    assert any("main job done" in line for line in lines) and os.path.isdir(report["scenes"]["table"]["basis_folder"])

"""tools/bench.py measured-space on tiny measured sets: the report's fields and what they promise."""

import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "manifold"))
from measured_helpers import weights_path, write_set

from benchmarks import measured_space

pytestmark = pytest.mark.skipif(not os.path.exists(weights_path()), reason="no NBRDF weights")


def test_by_device_reports_ratios_plausibility_and_added_materials(tmp_path):
    merl = [
        "alum-bronze",
        "blue-rubber",
        "chrome",
        "gold-metallic-paint",
        "red-fabric",
        "teflon",
        "white-paint",
        "yellow-matte-plastic",
        "black-phenolic",
        "green-plastic",
    ]
    root = tmp_path / "sets"
    write_set(str(root / "merl"), "merl", merl, dims=(8, 8, 16))
    write_set(str(root / "nielsen"), "nielsen", ["bindercover", "yellowpaper"], dims=(8, 8, 16))
    out = measured_space.run(str(root), n_add=2, progress=False)
    assert list(out["splits"]) == ["merl->nielsen"]  # no rgl folder: those splits are left out
    split = out["splits"]["merl->nielsen"]
    assert split["n_train"] == len(merl) and [r["name"] for r in split["rows"]] == [
        "bindercover",
        "yellowpaper",
    ]
    for r in split["rows"]:
        assert r["beyond_ratio"] <= r["convex_ratio"] + 1e-9 and r["convex_ratio"] <= 1.0 + 1e-9
        assert r["min_value"] >= 0 and r["max_albedo"] <= 1.0 + 1e-6
    s = split["summary"]
    assert s["median_beyond_ratio"] == pytest.approx(
        np.median([r["beyond_ratio"] for r in split["rows"]])
    )
    assert (
        all(a["exact"] and a["others_unchanged"] for a in split["add"]) and len(split["add"]) == 2
    )

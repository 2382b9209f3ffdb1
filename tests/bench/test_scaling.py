"""The scaling benchmark's machinery: exponents, one point measured in a subprocess."""

import numpy as np

from benchmarks import scaling


def test_exponent_of_power_laws():
    xs = [10, 30, 100, 300]
    assert abs(scaling.exponent(xs, [2.0 * x**1.5 for x in xs]) - 1.5) < 1e-9
    assert abs(scaling.exponent(xs, [0.5 + 3.0 * x for x in xs], floor=0.5) - 1.0) < 1e-9
    assert scaling.exponent([10], [1.0]) is None
    assert scaling.exponent([10, 20], [1.0, None]) is None


def test_one_point_in_a_subprocess(small_db, tmp_path):
    r = scaling.measure(
        "gram", {"db": small_db, "n": 4, "gram_out": str(tmp_path / "S.npy")}, timeout=120
    )
    assert "error" not in r, r
    assert r["time_s"] > 0 and 0.05 < r["peak_rss_gib"] < 8 and r["d"] == 3 * 32 * 32 * 64
    S = np.load(tmp_path / "S.npy")
    assert S.shape == (4, 4) and np.allclose(S, S.T)
    bad = scaling.measure(
        "gram", {"db": str(tmp_path / "missing"), "n": 4, "gram_out": str(tmp_path / "x.npy")}
    )
    assert "error" in bad and "missing" in bad["error"]

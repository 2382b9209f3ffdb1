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


def test_databases_of_the_measured_set(tmp_path):
    """The series' tables are the built-in measured set's, then noisy copies of them."""
    from mitsuba_manifold.data import merl
    from mitsuba_manifold.data.database import Database

    dims = (8, 8, 16)
    folder, _, count = scaling._noisy_database(str(tmp_path), 150, dims, progress=False)
    assert count == 200
    db = Database(folder)
    measured = Database(f"{scaling.SOURCE}@8x8x16")
    assert len(db.names) == 200 and set(measured.names) <= set(db.names)
    name = measured.names[0]
    assert np.allclose(db.reflectance(name), measured.reflectance(name), rtol=1e-3, atol=1e-6)
    raw = merl.read_binary(f"{folder}/{name}.binary")
    copy = merl.read_binary(f"{folder}/{name}~1.binary")
    ok = raw > 0
    log_ratio = np.log(copy[ok] / raw[ok])
    assert abs(log_ratio.std() - scaling.NOISE) < 0.01 and abs(log_ratio.mean()) < 0.01
    r = scaling.measure("tabulate", {"out": str(tmp_path / "tab"), "dims": list(dims), "n": 3})
    assert "error" not in r, r
    tab = Database(str(tmp_path / "tab"))
    assert tab.names == measured.names[:3]
    assert np.allclose(tab.reflectance(name), measured.reflectance(name), rtol=1e-3, atol=1e-6)

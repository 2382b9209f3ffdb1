"""Built-in surrogate database, Database folders and albedo quadrature."""

import json
import os
import warnings

import numpy as np
import pytest

from mitsuba_manifold.data import database, merl


def test_sgd_value_against_hand_computation():
    fits = database.load_sgd_fits()
    p = fits["gold-paint"]
    # Normal incidence and reflection: h = n, theta_h = 0, cos_d = 1, both elevations 0.
    n = np.array([[0.0, 0.0, 1.0]])
    f = database.sgd_reflectance(p, n, n)[0]
    alpha, pp, kap = p["alpha"], p["p"], p["kap"]
    D = kap * np.exp(-alpha) / (np.pi * alpha**pp)
    F = p["f0"] - p["f1"]
    G1 = np.clip(
        1 + p["lambda"] * (1 - np.exp(p["c"] * np.maximum(0 - p["theta0"], 0) ** p["k"])), 0, 1
    )
    assert np.allclose(f, (p["rho_d"] + p["rho_s"] * F * D * G1 * G1) / np.pi, rtol=1e-12)

    # An oblique pair in the plane of incidence: theta_i = 30 deg, theta_o = 50 deg.
    ti, to = np.radians(30), np.radians(50)
    wi = np.array([[np.sin(ti), 0, np.cos(ti)]])
    wo = np.array([[-np.sin(to), 0, np.cos(to)]])
    th = (to - ti) / 2  # half vector elevation, cos_d = cos((ti + to) / 2)
    cd = np.cos((ti + to) / 2)
    A = alpha + np.tan(th) ** 2 / alpha
    D = kap * np.exp(-A) / (np.pi * A**pp * np.cos(th) ** 4)
    F = p["f0"] - cd * p["f1"] + (1 - cd) ** 5 * (1 - p["f0"])

    def g1(t):
        return np.clip(
            1 + p["lambda"] * (1 - np.exp(p["c"] * np.maximum(t - p["theta0"], 0) ** p["k"])), 0, 1
        )

    expected = (
        p["rho_d"] + p["rho_s"] * F * D * g1(ti) * g1(to) / (np.cos(ti) * np.cos(to))
    ) / np.pi
    assert np.allclose(database.sgd_reflectance(p, wi, wo)[0], expected, rtol=1e-10)
    # Below the horizon: zero.
    assert np.all(database.sgd_reflectance(p, wi, wo * [1, 1, -1]) == 0)


def test_extreme_fits_are_finite_without_warnings():
    fits = database.load_sgd_fits()
    extreme = [n for n, p in fits.items() if p["c"].max() > 1e30 or p["k"].max() > 40]
    assert "black-obsidian" in extreme and len(extreme) > 3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in extreme:
            raw = database.tabulate_sgd(fits[name], (24, 24, 48))
            assert np.isfinite(raw).all(), name
            # grazing bins too
            wi, wo = merl.directions(np.full(50, 1.5706), np.linspace(0, 1.5707, 50), np.zeros(50))
            assert np.isfinite(database.sgd_reflectance(fits[name], wi, wo)).all()


def test_tabulation_flags_below_horizon_and_uses_bin_centres():
    dims = (16, 16, 32)
    raw = database.tabulate_sgd("pink-fabric", dims)
    mask = merl.above_horizon(dims)
    assert np.all(raw[:, ~mask] == merl.NOT_MEASURED) and np.all(raw[:, mask] >= 0)
    th, td, pd = merl.bin_centres(dims)
    i = (3, 7, 11)
    wi, wo = merl.directions(th[i], td[i], pd[i])
    expected = database.sgd_reflectance(
        database.load_sgd_fits()["pink-fabric"], wi[None], wo[None]
    )[0]
    assert np.allclose(raw[(slice(None),) + i] * merl.SCALE, expected, rtol=1e-12)
    with pytest.raises(KeyError, match="unknown material 'no-such'"):
        database.tabulate_sgd("no-such", dims)


def test_make_database_is_deterministic_and_keeps_valid_files(tmp_path):
    dims = (8, 8, 16)
    a, b = tmp_path / "a", tmp_path / "b"
    pa = database.make_database(a, dims, ["steel", "teflon"], noise=0.1, seed=7)
    database.make_database(b, dims, ["teflon"], noise=0.1, seed=7)
    assert (a / "teflon.binary").read_bytes() == (b / "teflon.binary").read_bytes()
    clean = database.tabulate_sgd("teflon", dims)
    noisy = merl.read_binary(a / "teflon.binary")
    assert not np.array_equal(clean, noisy) and np.array_equal(clean < 0, noisy < 0)
    ratio = noisy[clean > 0] / clean[clean > 0]
    assert 0.07 < np.std(np.log(ratio)) < 0.13
    mtimes = [os.stat(p).st_mtime_ns for p in pa]
    database.make_database(a, dims, ["steel", "teflon"], noise=0.1, seed=7)
    assert [os.stat(p).st_mtime_ns for p in pa] == mtimes
    with pytest.raises(ValueError, match="made with"):
        database.make_database(a, dims, ["steel"], noise=0.2, seed=7)
    with pytest.raises(ValueError, match="unknown material"):
        database.make_database(tmp_path / "c", dims, ["steel", "unobtainium"])
    with pytest.raises(
        ValueError, match=r"\['stel'\] \(did you mean 'steel'"
    ):  # a typo gets a suggestion
        database.make_database(tmp_path / "c", dims, ["stel"])
    assert json.loads((a / "database.json").read_text())["seed"] == 7


def test_repeated_materials_make_one_table_each_and_are_counted_once(tmp_path):
    from guarantees_helpers import run_tool

    rc, out, err = run_tool(
        "make_database",
        "--out",
        tmp_path / "db",
        "--resolution",
        "4,4,8",
        "--materials",
        "chrome,chrome,steel,chrome",
    )
    assert rc == 0, err
    assert "chrome repeated" in out and "2 .binary files in" in out
    assert sorted(f for f in os.listdir(tmp_path / "db") if f.endswith(".binary")) == [
        "chrome.binary",
        "steel.binary",
    ]
    paths = database.make_database(tmp_path / "db2", (4, 4, 8), ["steel", "steel"])
    assert paths == [os.path.join(tmp_path / "db2", "steel.binary")]


def test_database_folder_errors(tmp_path, small_db):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        database.Database(tmp_path / "nope")
    with pytest.raises(ValueError, match="holds no tables"):
        database.Database(tmp_path)
    with pytest.raises(KeyError, match="no table for"):
        database.Database(small_db, ["chrome", "vantablack"])
    db = database.Database(small_db)
    with pytest.raises(KeyError, match="unknown material 'vantablack'"):
        db.reflectance("vantablack")
    # mixed resolutions are refused
    folder = tmp_path / "mixed"
    database.make_database(folder, (8, 8, 16), ["steel"])
    merl.write_binary(folder / "other.binary", np.ones((3, 4, 4, 8)))
    with pytest.raises(
        ValueError, match="different resolutions: "
    ) as e:  # a tie: every group named
        database.Database(folder)
    assert "8x8x16: steel.binary" in str(e.value) and "4x4x8: other.binary" in str(e.value)
    database.make_database(folder, (8, 8, 16), ["steel", "chrome"])
    with pytest.raises(ValueError, match="2 are 8x8x16, but other.binary is 4x4x8; remove") as e:
        database.Database(folder)
    assert "chrome.binary" not in str(e.value) and "steel.binary" not in str(e.value)


def test_reflectance_cache_and_hash_follow_file_content(tmp_path):
    folder = tmp_path / "db"
    database.make_database(folder, (8, 8, 16), ["steel", "teflon"])
    db = database.Database(folder)
    h1 = db.hash("steel")
    t1 = np.array(db.reflectance("steel"))
    assert np.array_equal(t1, merl.filled_reflectance(merl.read_binary(db.path("steel"))))
    raw = merl.read_binary(db.path("steel"))
    raw[raw > 0] *= 2
    merl.write_binary(db.path("steel"), raw)
    db2 = database.Database(folder)
    assert db2.hash("steel") != h1
    assert np.allclose(np.array(db2.reflectance("steel")), 2 * t1)


def test_albedo_quadrature_lambertian(small_db):
    for dims, tol in [((16, 16, 32), 3e-3), ((90, 90, 180), 1e-3)]:
        q = database.albedo_weights(dims)
        assert (q / np.pi).sum() == pytest.approx(1.0, abs=tol)
    db = database.Database(small_db)
    alb = db.albedo()
    assert alb.shape == (len(db.names), 3) and np.all(alb > 0)
    i = db.names.index("white-diffuse-bball")
    assert np.all(alb[i] > 0.2)


def test_cache_follows_the_content_even_with_the_mtime_restored(tmp_path):
    """Issue 10: a table edited in place with its modification time restored is read again
    (the cache is keyed on the bytes; size and mtime are not trusted)."""
    folder = tmp_path / "db"
    database.make_database(folder, (8, 8, 16), ["steel", "teflon"])
    path = str(folder / "steel.binary")
    before = database.Database(folder)
    old_hash, old_table = before.hash("steel"), np.array(before.reflectance("steel"))
    st = os.stat(path)
    raw = merl.read_binary(path)
    raw[:, raw[0] > 0] *= 2.0  # same size, different bytes
    with open(path, "r+b") as f:  # in place (same inode)
        f.seek(0)
        f.write(open(path, "rb").read()[:12])
        f.write(np.asarray(raw, "<f8").tobytes())
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(path).st_size == st.st_size and os.stat(path).st_mtime_ns == st.st_mtime_ns
    after = database.Database(folder)
    assert after.hash("steel") != old_hash
    np.testing.assert_allclose(
        np.array(after.reflectance("steel")),
        np.where(old_table > 0, 2 * old_table, old_table),
        rtol=1e-6,
    )


def test_a_database_skips_the_temporary_files_of_writers(tmp_path, small_db):
    """A killed writer's temporary (old and new naming) is not read as a material (issue 20)."""
    import shutil

    from mitsuba_manifold.data.database import Database

    folder = tmp_path / "db"
    shutil.copytree(small_db, folder)
    first = sorted(Database(str(folder)).names)
    (folder / ".ipswich-pine-221.binary.1234.tmp.binary").write_bytes(b"\0" * 12)
    (folder / ".chrome.binary.99-abcd-x1y2.tmp.binary").write_bytes(b"\0" * 12)
    assert sorted(Database(str(folder)).names) == first


def test_a_table_written_without_its_cache_is_made_again(tmp_path, monkeypatch):
    """A run stopped between a table and its reflectance cache (SIGTERM reaching a worker there):
    the next run makes that table again, and the folder is the one an uninterrupted run makes."""
    import sys

    sys.path.insert(0, os.path.dirname(os.path.dirname(__file__)))
    from guarantees_helpers import snapshot

    names, dims = ["steel", "chrome", "gold-paint"], (8, 8, 16)
    database.make_database(tmp_path / "clean", dims, names)
    real, calls = database.npy_cache, []

    def stopped(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt  # the second table is on disk, its cache is not
        return real(*args, **kwargs)

    monkeypatch.setattr(database, "npy_cache", stopped)
    with pytest.raises(KeyboardInterrupt):
        database.make_database(tmp_path / "db", dims, names)
    monkeypatch.setattr(database, "npy_cache", real)
    database.make_database(tmp_path / "db", dims, names)
    assert snapshot(tmp_path / "db") == snapshot(tmp_path / "clean")

"""Mitsuba ``measured`` files imported as MERL tables: against Mitsuba's own plugin at random
directions, in a database beside other kinds, and rendered as the plugin renders them."""

import os

import numpy as np
import pytest
from measured_files import FILES  # the files are made by the ``measured_files`` fixture

from mitsuba_manifold.data import merl
from mitsuba_manifold.data.database import Database

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MITSUBA_MANIFOLD_CACHE", str(tmp_path / "cache"))


def _random_pairs(n, seed):
    """Uniform direction pairs on the upper hemisphere, away from grazing (cos > 0.1)."""
    rng = np.random.default_rng(seed)

    def hemi():
        z = rng.uniform(0.1, 1.0, n)
        phi = rng.uniform(0, 2 * np.pi, n)
        r = np.sqrt(1 - z * z)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)

    return hemi(), hemi()


def test_the_table_is_the_plugins_brdf_at_random_directions(measured_files):
    """At bin-centre directions (random bins, random phi_h) a one-sample table holds exactly the
    plugin's eval / cos(theta_o); at random directions the table looked up by MERL's indexing
    follows the plugin (a wrong phi_d, swapped directions or a cosine left in would not)."""
    from mitsuba_manifold.render.plugin import measured

    path = measured_files["vch_golden_yellow"]
    dims = (90, 90, 180)
    table = measured.resample(path, dims, samples=1)
    bsdf = measured.load_measured(path)
    rng = np.random.default_rng(1)
    above = np.argwhere(merl.above_horizon(dims))
    picked = above[rng.choice(len(above), 2000, replace=False)]
    th, td, pd = (c[tuple(picked.T)] for c in merl.bin_centres(dims))
    wi, wo = merl.directions(th, td, pd, phi_h=rng.uniform(0, 2 * np.pi, len(th)))
    plugin = measured.evaluate(bsdf, wi, wo)
    ok = (wi[:, 2] > 0.05) & (wo[:, 2] > 0.05)
    np.testing.assert_allclose(
        table[(slice(None),) + tuple(picked[ok].T)].T, plugin[ok], rtol=2e-3, atol=1e-5
    )

    wi, wo = _random_pairs(20000, 2)
    plugin = measured.evaluate(bsdf, wi, wo) * wo[:, 2:3]  # what a renderer integrates

    def error(a, b, extra=1.0):  # relative L1 of the table's value looked up at (a, b)
        looked_up = table.reshape(3, -1)[:, merl.flat_index(a, b, dims)].T * wo[:, 2:3] * extra
        return np.abs(looked_up - plugin).sum() / plugin.sum()

    ok = error(wi, wo)
    assert ok < 0.15  # nearest-bin lookup of a glossy film
    assert error(wi * [1, -1, 1], wo) > 5 * ok  # phi_d mirrored
    assert error(wi, wo, extra=wo[:, 2:3]) > 2 * ok  # the cosine left in the table


def test_measured_files_join_a_database_with_other_kinds(tmp_path, measured_files):
    import mitsuba_manifold.render  # noqa: F401  (registers the reader)
    from mitsuba_manifold.data import nbrdf

    folder = tmp_path / "db"
    folder.mkdir()
    os.symlink(measured_files["paper_blue"], folder / FILES["paper_blue"])
    nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "nielsen").subset(["notebook"]).save(
        folder / "notebook.npz"
    )
    db = Database(f"{folder}@16x16x32")
    assert db.names == ["notebook", "paper_blue"] and db.dims == (16, 16, 32)
    table = db.reflectance("paper_blue")
    assert table.shape == (3, 16, 16, 32) and np.isfinite(table).all() and table.max() > 0
    rho = db.albedo(["paper_blue"])[0]
    assert rho[2] > rho[0] and 0.05 < rho.mean() < 0.8  # a blue paper, reflecting less than all
    assert os.listdir(tmp_path / "db" / ".manifold-cache") == [
        db.hash("paper_blue") + ".refl16.npy"
    ]


def test_an_imported_file_renders_as_mitsubas_measured_plugin(tmp_path, measured_files):
    """Image mean within 1% and relative MSE within 3x the noise of two measured renders
    (median over the three files; 32x32 here, the benchmark runs larger)."""
    from mitsuba_manifold import Manifold
    from mitsuba_manifold.render.plugin import measured

    folder = tmp_path / "db"
    folder.mkdir()
    for name, f in FILES.items():
        os.symlink(measured_files[name], folder / f)
    m = Manifold.fit(str(folder), q=1)
    m.save(tmp_path / "m.npz")
    rows = [
        measured.fidelity(path, tmp_path / "m.npz", res=32, spp=128)
        for path in measured_files.values()
    ]
    for r in rows:
        assert abs(r["mean_ratio"] - 1) < 0.01, r
    assert np.median([r["ratio_to_noise"] for r in rows]) <= 3.0, rows


def test_every_tool_reads_a_database_folder_holding_measured_files(tmp_path, measured_files):
    """``make_database.py --from FOLDER`` then ``fit_manifold.py`` and ``project.py`` on a folder
    holding a ``.bsdf`` file, each in a fresh process: the tools read Mitsuba measured files
    without the user importing anything."""
    import shutil
    import subprocess
    import sys

    tools = os.path.join(os.path.dirname(__file__), "..", "..", "tools")
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(measured_files["paper_blue"], src / FILES["paper_blue"])
    db, m = str(tmp_path / "db"), str(tmp_path / "m.npz")
    steps = [
        ("make_database.py", "--from", "nielsen", "--from", str(src), "--resolution", "8,8,16")
        + ("--out", db),
        ("fit_manifold.py", db, "--q", "2", "--out", m, "--materials")
        + ("paper_blue,notebook,bluebook,yellowpaper",),
        ("project.py", str(src / FILES["paper_blue"]), "--manifold", m),
    ]
    env = dict(os.environ, MITSUBA_MANIFOLD_CACHE=str(tmp_path / "cache"))
    for tool, *argv in steps:
        r = subprocess.run(
            [sys.executable, os.path.join(tools, tool), *argv],
            capture_output=True,
            text=True,
            cwd=str(tmp_path),
            env=env,
            check=False,
        )
        assert r.returncode == 0, f"{tool}: {r.stderr}"
    assert (
        "nearest training material paper_blue" in r.stdout and "weights: paper_blue:1," in r.stdout
    )

"""Nothing lost (issue 10): odd material names, locks, content-keyed caches, files of the
user's, content identity of manifolds and old bases, moved and interrupted databases --
reproduced through the tools' command lines.

Tools run in-process through their ``main(argv)`` (:mod:`guarantees_helpers`); a few run
as subprocesses where the operating system is part of the test (locks). Fixtures:
``tests/apps/conftest.py``.
"""

import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
from guarantees_helpers import (
    DIMS,
    ROOT,
    SPHERE,
    assert_one_error,
    render_basis_command,
    run_render_basis,
    run_tool,
    snapshot,
)
from guarantees_helpers import (
    write_table as _table,
)

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("plugins")]
mi = pytest.importorskip("mitsuba")
from mitsuba_manifold._util.cache import file_hash  # noqa: E402
from mitsuba_manifold._util.locking import FolderLock  # noqa: E402
from mitsuba_manifold.basis.folder.manifest import Manifest  # noqa: E402
from mitsuba_manifold.data import database, merl  # noqa: E402
from mitsuba_manifold.imaging import io as imageio  # noqa: E402
from mitsuba_manifold.manifold.file.identity import manifold_identity  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402

# ------------------------------------------------------ 1. reserved and odd names


def test_material_named_base_or_with_separator_gets_its_own_image(tmp_path):
    db = tmp_path / "db"
    database.make_database(db, DIMS, ["steel", "chrome"])
    shutil.copy(db / "chrome.binary", db / "base.binary")
    raw = merl.read_binary(db / "steel.binary")
    merl.write_binary(db / "a+b.binary", np.where(raw > 0, raw * 0.5, raw))
    m = tmp_path / "m.npz"
    rc, _, err = run_tool("fit_manifold", db, "--out", m, "--features", "log")
    assert rc == 0, err
    out = tmp_path / "basis"
    rc, _, err = run_render_basis(m, out, "--mode", "per-material", spp=2)
    assert rc == 0, err
    manifest = json.loads((out / "manifest.json").read_text())
    files = [e["file"] for e in manifest["images"].values()]
    assert len(manifest["images"]) == 5 and len(set(files)) == 5
    man = Manifold.load(m)
    base = imageio.read_exr(out / manifest["images"]["base"]["file"])
    for name in ("base", "a+b"):
        x = ",".join(repr(float(v)) for v in man.latent[man.index(name)])
        rc, _, err = run_tool("blend", "--basis", out, "--x", x, "--out", tmp_path / f"{name}.exr")
        assert rc == 0, err
        img = imageio.read_exr(tmp_path / f"{name}.exr")
        assert not np.allclose(img, 2 * base)  # the old collision: material 'base' read as base
        touch = img - base
        assert touch.max() > 0
    # every file the run made is listed: no orphan image
    listed = set(files) | {"manifest.json"}
    assert {f for f in os.listdir(out) if not f.startswith(".")} == listed
    # match finds its way through escaped image keys
    rc, _, err = run_tool(
        "match",
        "--basis",
        out,
        "--image",
        tmp_path / "a+b.exr",
        "--json",
        tmp_path / "m.json",
        "--scan",
        64,
        "--starts",
        2,
    )
    assert rc == 0, err
    assert json.loads((tmp_path / "m.json").read_text())["rel_mse"] < 1e-6


def test_escaped_names_are_injective_and_safe():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from mitsuba_manifold._util import names

    @settings(max_examples=300, deadline=None)
    @given(st.text(min_size=1, max_size=30), st.text(min_size=1, max_size=30))
    def check(a, b):
        try:
            ea, eb = names.escape(a), names.escape(b)
        except names.InputError:
            return
        assert names.unescape(ea) == a
        assert (ea == eb) == (a == b)
        assert set(ea) <= names.SAFE | {"%"} and not ea.startswith(".")
        assert ea.lower() not in names.RESERVED and "+" not in ea and "/" not in ea

    check()
    for n in ("base", "BASE", "manifest", "a+b", "../x", ".hidden", "a%2Bb"):
        e = names.escape(n)
        assert e not in ("base", "manifest") and "/" not in e and not e.startswith(".")
    assert names.escape("gold-paint") == "gold-paint"
    with pytest.raises(names.InputError, match="differ only in case"):
        names.check_unique(["Steel", "steel"])


# ------------------------------------------------------------ 2. locks


def make_steel(out):
    """The command that makes a one-material database (steel, 8x8x16) in ``out``."""
    tool = os.path.join(ROOT, "tools", "make_database.py")
    options = "--from sgd --resolution 8,8,16 --materials steel".split()
    return [sys.executable, tool, "--out", str(out), *options]


def test_second_writer_of_a_folder_gets_a_clear_error(tmp_path, tiny):
    out = tmp_path / "db"
    with FolderLock(out, "database folder"):
        before = snapshot(out)
        r = subprocess.run(make_steel(out), capture_output=True, text=True)
        assert_one_error(r.returncode, r.stderr, str(out), "another process")
        assert snapshot(out) == before
        rc, _, err = run_render_basis(tiny["manifold"], out)
        assert_one_error(rc, err, "another process")
    r = subprocess.run(make_steel(out), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr  # the lock went with the process that held it


def test_two_render_basis_runs_into_one_folder_cannot_mix(tmp_path, tiny):
    """The reported race: two runs with different spp at once. The second is refused while the
    first holds the folder; the basis left is the first run's, whole."""
    out = tmp_path / "basis"
    tool = render_basis_command(tiny["manifold"], out, "--mode", "per-material", res=16, spp=None)
    first = subprocess.Popen(
        tool + ["--spp", "12000"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    deadline = time.time() + 120
    while time.time() < deadline and not (out / "manifest.json").exists():
        time.sleep(0.1)
    try:
        second = subprocess.run(tool + ["--spp", "4"], capture_output=True, text=True, timeout=300)
        _, err = first.communicate(timeout=300)
    finally:
        first.kill()  # no-op once it has ended
    assert first.returncode == 0, err
    line = assert_one_error(second.returncode, second.stderr)
    assert "another process" in line or "other settings" in line, (
        line
    )  # locked, or seen as another basis
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["spp"] == 12000 and len(manifest["images"]) == 1 + len(
        Manifold.load(tiny["manifold"]).names
    )


# ------------------------------------------------------- 3. content-keyed caches


def test_table_edited_in_place_with_its_mtime_restored_is_read_again(tmp_path):
    folder = tmp_path / "db"
    database.make_database(folder, DIMS, ["steel", "chrome"])
    db = database.Database(folder)
    h1, t1 = db.hash("steel"), np.array(db.reflectance("steel"))
    path = db.path("steel")
    st = os.stat(path)
    raw = merl.read_binary(path)
    with open(path, "r+b") as f:  # same size, same inode, mtime put back
        f.seek(12)
        f.write(np.where(raw > 0, raw * 3, raw).astype("<f8").tobytes())
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    db2 = database.Database(folder)
    assert db2.hash("steel") != h1
    assert np.allclose(np.array(db2.reflectance("steel")), 3 * t1)


# ------------------------------------------------------------ 5.-8. data lost


def test_blend_x_by_material_name_is_its_point_and_an_unwritable_out_is_refused_first(
    tiny, tmp_path
):
    m = Manifold.load(tiny["manifold"])
    name, point = m.names[1], ",".join(repr(float(v)) for v in m.latent[1])
    rc, out, err = run_tool(
        "blend", "--basis", tiny["basis"], "--x", name, "--out", tmp_path / "named.exr"
    )
    assert rc == 0, err
    rc, _, err = run_tool(
        "blend", "--basis", tiny["basis"], "--x", point, "--out", tmp_path / "numbers.exr"
    )
    assert rc == 0, err
    np.testing.assert_array_equal(
        imageio.read_exr(tmp_path / "named.exr"), imageio.read_exr(tmp_path / "numbers.exr")
    )
    rc, _, err = run_tool(
        "blend", "--basis", tiny["basis"], "--x", name[:-1] + "q", "--out", tmp_path / "typo.exr"
    )
    assert_one_error(rc, err, "unknown material")
    assert not (tmp_path / "typo.exr").exists()
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if (
            os.access(locked, os.W_OK) and os.geteuid() == 0
        ):  # root: a read-only file system stands in
            locked = "/proc/mitsuba-manifold-test"
        rc, out, err = run_tool(
            "blend", "--basis", tiny["basis"], "--x", name, "--out", os.path.join(locked, "a.exr")
        )
        assert_one_error(rc, err, "cannot write in")
        assert "blend time" not in out
    finally:
        (tmp_path / "locked").chmod(0o700)


def test_blend_never_writes_into_a_basis_folder(tiny):
    before = snapshot(tiny["basis"])
    for name in ("base.exr", "new.exr"):
        rc, _, err = run_tool(
            "blend",
            "--basis",
            tiny["basis"],
            "--x",
            "0,0",
            "--out",
            os.path.join(tiny["basis"], name),
            "--png",
        )
        assert_one_error(rc, err, "basis")
    assert snapshot(tiny["basis"]) == before


def test_blend_replaces_its_own_outputs_but_not_the_users(tmp_path, tiny):
    out = tmp_path / "img.exr"
    for _ in range(2):
        rc, _, err = run_tool(
            "blend", "--basis", tiny["basis"], "--x", "0,0", "--out", out, "--png"
        )
        assert rc == 0, err
    (tmp_path / "mine.png").write_bytes(b"my own picture")
    before = snapshot(tmp_path)
    rc, _, err = run_tool(
        "blend", "--basis", tiny["basis"], "--x", "0,0", "--out", tmp_path / "mine.exr", "--png"
    )
    assert_one_error(rc, err, "mine.png", "--force")
    assert snapshot(tmp_path) == before
    rc, _, err = run_tool(
        "blend",
        "--basis",
        tiny["basis"],
        "--x",
        "0,0",
        "--out",
        tmp_path / "mine.exr",
        "--png",
        "--force",
    )
    assert rc == 0, err
    os.chmod(out, 0o444)
    before = snapshot(tmp_path)
    rc, _, err = run_tool("blend", "--basis", tiny["basis"], "--x", "0,0", "--out", out, "--force")
    assert_one_error(rc, err, "read-only")
    assert snapshot(tmp_path) == before


def test_make_database_keeps_foreign_tables(tmp_path):
    out = tmp_path / "db"
    out.mkdir()
    _table(out / "steel.binary", dims=(4, 4, 8), value=7.0)  # the user's own table
    before = snapshot(out)
    rc, _, err = run_tool(
        "make_database", "--out", out, "--resolution", "8,8,16", "--materials", "steel,chrome"
    )
    assert_one_error(rc, err, "steel.binary")
    assert snapshot(out) == before
    # a folder the tool made: extra foreign tables are refused too
    rc, _, err = run_tool(
        "make_database",
        "--out",
        tmp_path / "db2",
        "--resolution",
        "8,8,16",
        "--materials",
        "chrome",
    )
    assert rc == 0, err
    _table(tmp_path / "db2" / "steel.binary", value=7.0)
    before = snapshot(tmp_path / "db2")
    rc, _, err = run_tool(
        "make_database",
        "--out",
        tmp_path / "db2",
        "--resolution",
        "8,8,16",
        "--materials",
        "chrome,steel",
    )
    assert_one_error(rc, err, "steel.binary")
    assert snapshot(tmp_path / "db2") == before
    # its own tables are resumed, and --force takes over foreign ones
    rc, _, err = run_tool(
        "make_database",
        "--out",
        out,
        "--resolution",
        "8,8,16",
        "--materials",
        "steel,chrome",
        "--force",
    )
    assert rc == 0, err
    assert merl.read_header(out / "steel.binary") == DIMS


def test_render_basis_keeps_same_named_user_files(tmp_path, tiny):
    out = tmp_path / "basis"
    out.mkdir()
    imageio.write_exr(out / "chrome.exr", np.ones((4, 4, 3)))
    (out / "notes.txt").write_text("mine")
    before = snapshot(out)
    rc, _, err = run_render_basis(tiny["manifold"], out)
    assert_one_error(rc, err, "chrome.exr")
    assert snapshot(out) == before


def test_render_basis_refuses_a_folder_of_the_users_unless_forced(tmp_path, tiny):
    """A database or a folder of blends is no basis folder: refused whole (no image added,
    however the files are named), also for chunks and as the parent of several bases."""
    db = tmp_path / "db"
    shutil.copytree(tiny["db"], db)
    blends = tmp_path / "blends"
    blends.mkdir()
    x = ",".join(f"{v:.6g}" for v in Manifold.load(tiny["manifold"]).latent[0])
    assert (
        run_tool("blend", "--basis", tiny["basis"], "--x", x, "--out", blends / "mine.exr")[0] == 0
    )
    base = ["--manifold", tiny["manifold"], "--res", 8, "--spp", 2]
    for folder in (db, blends):
        before = snapshot(folder)
        for args in (
            [SPHERE],
            [SPHERE, "--chunks", 2],
            [SPHERE, SPHERE.replace("sphere", "table")],
        ):
            rc, _, err = run_tool("render_basis", *args, *base, "--out", folder)
            assert_one_error(rc, err, f"{folder} is not a", "did not make", "--force")
            assert snapshot(folder) == before
    rc, _, err = run_tool("render_basis", SPHERE, *base, "--out", blends, "--force")
    assert rc == 0, err
    assert (blends / "mine.exr").exists() and (blends / "manifest.json").exists()


def test_render_basis_resumes_a_folder_holding_only_its_own_lock_and_temporary_files(
    tmp_path, tiny
):
    """Killed before its manifest was written: the lock file and a temporary file are its own."""
    from mitsuba_manifold._util.locking import LOCK_NAME

    out = tmp_path / "basis"
    out.mkdir()
    (out / LOCK_NAME).write_text("")
    (out / ".manifest.json.k3j2x9ab.tmp.json").write_text("{")
    rc, _, err = run_render_basis(tiny["manifold"], out)
    assert rc == 0, err
    assert len(json.loads((out / "manifest.json").read_text())["images"]) == 5


def test_fit_manifold_out_refuses_read_only_and_foreign_files(tmp_path, tiny):
    out = tmp_path / "m.npz"
    rc, _, err = run_tool("fit_manifold", tiny["db"], "--out", out)
    assert rc == 0, err
    rc, _, err = run_tool("fit_manifold", tiny["db"], "--out", out)  # its own output: replaced
    assert rc == 0, err
    os.chmod(out, 0o444)
    (tmp_path / "thesis.npz").write_bytes(b"PK not a manifold")
    before = snapshot(tmp_path)
    rc, _, err = run_tool("fit_manifold", tiny["db"], "--out", out, "--force")
    assert_one_error(rc, err, str(out), "read-only")
    rc, _, err = run_tool("fit_manifold", tiny["db"], "--out", tmp_path / "thesis.npz")
    assert_one_error(rc, err, "thesis.npz")
    assert snapshot(tmp_path) == before


# -------------------------------------------- 11. content identity, moved databases


def test_identical_refit_is_accepted_by_existing_bases(tmp_path, tiny):
    again = tmp_path / "again.npz"
    rc, _, err = run_tool("fit_manifold", tiny["db"], "--out", again, "--q", 2)  # as make_tiny
    assert rc == 0, err
    # the same model (latent points, hyperparameters, materials, tables), whatever its file's bytes
    # (they may differ: the file records when and how it was made): the identity the basis holds
    identity = manifold_identity(Manifold.load(again))
    assert identity == manifold_identity(Manifold.load(tiny["manifold"]))
    assert identity == Manifest.read(tiny["basis"]).manifold_hash
    rc, _, err = run_tool(
        "blend",
        "--basis",
        tiny["basis"],
        "--manifold",
        again,
        "--x",
        "0,0",
        "--out",
        tmp_path / "img.exr",
    )
    assert rc == 0, err
    other = tmp_path / "other.npz"
    rc, _, err = run_tool(
        "fit_manifold", tiny["db"], "--out", other, "--q", 2, "--length-scale", "2"
    )
    assert rc == 0, err
    rc, _, err = run_tool(
        "blend",
        "--basis",
        tiny["basis"],
        "--manifold",
        other,
        "--x",
        "0,0",
        "--out",
        tmp_path / "img2.exr",
    )
    assert_one_error(rc, err, "another manifold")


def test_tools_read_a_moved_database(tmp_path, tiny):
    moved = tmp_path / "moved"
    shutil.copytree(tiny["db"], moved)
    m = tmp_path / "m.npz"
    Manifold.load(tiny["manifold"]).save(m)
    man = Manifold.load(m)
    man.database = str(tmp_path / "gone")
    man.save(m)
    rc, _, err = run_render_basis(m, tmp_path / "b", "--materials", "steel")
    assert_one_error(rc, err, "--database")
    rc, _, err = run_render_basis(m, tmp_path / "b", "--materials", "steel", "--database", moved)
    assert rc == 0, err
    rc, _, err = run_tool(
        "blend",
        "--basis",
        tmp_path / "b",
        "--manifold",
        m,
        "--database",
        moved,
        "--x",
        ",".join(map(str, man.latent[man.index("steel")])),
        "--out",
        tmp_path / "i.exr",
        "--render-reference",
        "--spp",
        1,
        "--png",
    )
    assert rc == 0, err
    for name in ("i.png", "i_reference.exr", "i_reference.png", "i_error.png"):
        assert (tmp_path / name).is_file(), name


def test_names_cannot_leave_the_database_folder(tmp_path, tiny):
    (tmp_path / "x.binary").write_bytes(open(os.path.join(tiny["db"], "steel.binary"), "rb").read())
    inner = tmp_path / "inner"
    shutil.copytree(tiny["db"], inner)
    with pytest.raises(ValueError, match="not file names"):
        database.Database(inner, ["steel", "../x"])


def _version_1_copy(tiny, old):
    """A copy of the tiny basis with a version-1 manifest (raw names, manifold file hash)."""
    shutil.copytree(tiny["basis"], old)
    manifest = json.loads((old / "manifest.json").read_text())
    manifest.update(version=1, manifold_hash=file_hash(tiny["manifold"]))
    (old / "manifest.json").write_text(json.dumps(manifest))
    return manifest


def test_version_1_bases_are_still_read_and_checked_by_file_hash(tmp_path, tiny):
    old = tmp_path / "old"
    manifest = _version_1_copy(tiny, old)
    rc, _, err = run_tool("blend", "--basis", old, "--x", "0,0", "--out", tmp_path / "a.exr")
    assert rc == 0, err
    manifest["manifold_hash"] = "0" * 64
    (old / "manifest.json").write_text(json.dumps(manifest))
    rc, _, err = run_tool("blend", "--basis", old, "--x", "0,0", "--out", tmp_path / "b.exr")
    assert_one_error(rc, err, "is not the one it was rendered with", "version-1")


def test_render_basis_resumes_a_version_1_basis_of_the_same_manifold_file(tmp_path, tiny):
    old = tmp_path / "old"
    _version_1_copy(tiny, old)
    stamps = {f: os.stat(old / f).st_mtime_ns for f in os.listdir(old) if f.endswith(".exr")}
    rc, _, err = run_render_basis(tiny["manifold"], old, "--mode", "per-material")
    assert rc == 0, err
    assert json.loads((old / "manifest.json").read_text())["version"] == 2
    assert {f: os.stat(old / f).st_mtime_ns for f in stamps} == stamps  # nothing rendered again


def test_interrupted_make_database_lists_every_table_it_finished(tmp_path, monkeypatch):
    real, calls = database._write_sgd_table, []

    def write_then_interrupt(job):
        calls.append(real(job))  # the table is complete on disk ...
        if len(calls) == 2:
            raise KeyboardInterrupt  # ... when Ctrl-C arrives, before it is recorded
        return calls[-1]

    monkeypatch.setattr(database, "_write_sgd_table", write_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        database.make_database(tmp_path / "db", DIMS, ["steel", "chrome", "gold-paint"])
    listed = json.loads((tmp_path / "db" / "database.json").read_text())["tables"]
    assert sorted(listed) == ["chrome", "steel"]
    monkeypatch.setattr(database, "_write_sgd_table", real)
    rc, _, err = run_tool(
        "make_database",
        "--out",
        tmp_path / "db",
        "--from",
        "sgd",
        "--resolution",
        "8,8,16",
        "--materials",
        "steel,chrome,gold-paint",
    )
    assert rc == 0, err  # resumed, not refused as foreign tables

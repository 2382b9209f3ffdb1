"""One output discipline for every tool (issue 20), through the tools' command lines: the main
job, the benchmarks and the scene meshes replace only what they made; blend and fit_manifold
leave, after a failure or Ctrl-C, only files the same command replaces; full disks and names
too long for the file system name the file.

Tools run in-process through their ``main(argv)`` (:mod:`guarantees_helpers`); fixtures:
``tests/apps/conftest.py``.
"""

import errno
import json
import os

import pytest
from guarantees_helpers import assert_one_error, run_render_basis, run_tool, snapshot

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("plugins")]
mi = pytest.importorskip("mitsuba")
from mitsuba_manifold._util import atomic, ownership  # noqa: E402
from mitsuba_manifold.imaging import io as imageio  # noqa: E402
from mitsuba_manifold.imaging import plots


def _temporaries(folder):
    return [n for _, _, files in os.walk(folder) for n in files if atomic.is_temporary(n)]


# ------------------------------------------------- tools that did not check at all


def test_bench_json_never_replaces_links_fifos_read_only_or_users_files(tmp_path, tiny):
    files = tmp_path / "files"
    files.mkdir()
    precious = files / "precious.txt"
    precious.write_text("the user's")
    link = files / "link.json"
    link.symlink_to(precious)  # as /dev/null would be: not a regular file
    (tmp_path / "fifos").mkdir()  # (kept out of the snapshot, which would block on it)
    fifo = tmp_path / "fifos" / "fifo.json"
    os.mkfifo(fifo)
    locked = files / "locked.json"
    locked.write_text("{}")
    os.chmod(locked, 0o444)
    user = files / "user.json"
    user.write_text('{"mine": 1}')
    before = snapshot(tmp_path / "files")
    for target, words in (
        (link, "not a regular file"),
        (fifo, "not a regular file"),
        (locked, "read-only"),
        (user, "--force"),
    ):
        for force in ([], ["--force"]) if target != user else ([],):
            rc, _, err = run_tool(
                "bench", "stability", "--manifold", tiny["manifold"], "--json", target, *force
            )
            assert_one_error(rc, err, "--json", str(target), words)
    assert (
        snapshot(tmp_path / "files") == before and os.path.islink(link) and not os.path.isfile(fifo)
    )
    assert os.listdir(tmp_path / "fifos") == ["fifo.json"]


def test_main_job_refuses_the_users_files_in_out_before_computing_anything(tmp_path):
    out = tmp_path / "out"
    for rel in (
        "manifold.npz",
        os.path.join("gi", "report.json"),
        os.path.join("plots", "latent_map.png"),
    ):
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(b"the user's " + rel.encode())
    os.chmod(out / "manifold.npz", 0o444)
    before = snapshot(out)
    args = ["--out", out, "--resolution", "8,8,16", "--res", "8", "--spp", "1", "--ref-spp", "1"]
    rc, _, err = run_tool("main_job", *args, "--force")
    assert_one_error(rc, err, "manifold.npz", "read-only")
    os.chmod(out / "manifold.npz", 0o644)
    ownership.record([out / "manifold.npz"], "main.py")  # now its own output: replaceable
    before = snapshot(out)
    rc, _, err = run_tool("main_job", *args)
    line = assert_one_error(rc, err, "--force")
    assert "manifold.npz" not in line and ("latent_map.png" in line or "report.json" in line)
    assert (
        snapshot(out) == before and not (out / "database").exists()
    )  # refused before the database


def test_make_scene_meshes_replaces_its_own_files_keeps_identical_ones_and_refuses_others(tmp_path):
    out = tmp_path / "scenes"
    args = ["--out", out, "--segments", "8", "--profile", "8"]
    for _ in range(2):  # new, then its own
        rc, text, err = run_tool("make_scene_meshes", *args)
        assert rc == 0, err
    os.remove(out / ownership.RECORD)  # as shipped: made here, but not recorded
    os.chmod(out / "sky.exr", 0o640)
    rc, text, err = run_tool("make_scene_meshes", *args)
    assert rc == 0 and text.count("(unchanged)") == 2, (text, err)
    assert oct(os.stat(out / "sky.exr").st_mode & 0o777) == "0o640"
    rc, _, err = run_tool("make_scene_meshes", *args[:2], "--segments", "9", "--profile", "8")
    assert_one_error(rc, err, "bowl.ply", "--force")  # another mesh over a file it did not record
    os.chmod(out / "bowl.ply", 0o444)
    before = snapshot(out)
    rc, _, err = run_tool(
        "make_scene_meshes", *args[:2], "--segments", "9", "--profile", "8", "--force"
    )
    assert_one_error(rc, err, "bowl.ply", "read-only")
    assert snapshot(out) == before and not _temporaries(out)


# ------------------------------------------------- failures and interruptions


def test_a_full_disk_names_the_file_and_the_same_command_then_succeeds(tmp_path, tiny, monkeypatch):
    from PIL import Image

    out = tmp_path / "img.exr"
    cmd = ["blend", "--basis", tiny["basis"], "--x", "0,0", "--out", out, "--png"]

    def full(self, fp, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", full)
    rc, _, err = run_tool(*cmd)
    assert_one_error(rc, err, str(tmp_path / "img.png"), "no space left")
    monkeypatch.undo()
    assert not _temporaries(tmp_path)
    rc, _, err = run_tool(*cmd)  # the .exr it wrote is its own
    assert rc == 0, err
    assert (tmp_path / "img.png").is_file()


def test_names_too_long_for_the_file_system_are_refused_before_anything_is_written(tmp_path, tiny):
    ref = tmp_path / "ref.exr"
    imageio.write_exr(ref, imageio.read_exr(os.path.join(tiny["basis"], "base.exr")))
    before = snapshot(tmp_path)
    out = tmp_path / ("x" * 246 + ".exr")  # fits; "<stem>_error.png" does not
    rc, _, err = run_tool(
        "blend", "--basis", tiny["basis"], "--x", "0,0", "--out", out, "--reference", ref
    )
    assert_one_error(rc, err, "_error", "longer than the file system allows")
    assert snapshot(tmp_path) == before
    rc, _, err = run_tool("blend", "--basis", tiny["basis"], "--x", "0,0", "--out", out)
    assert rc == 0, err  # its temporary name is cut to fit
    assert out.is_file() and not _temporaries(tmp_path)


def test_an_interrupted_path_is_redone_by_the_same_command_and_a_shorter_one_removes_the_rest(
    tmp_path, tiny, monkeypatch
):
    out = tmp_path / "seq.exr"
    real, calls = imageio.write_exr, []

    def stopped(path, img, *a, **k):
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(path, img, *a, **k)

    cmd = ["blend", "--basis", tiny["basis"], "--path", "steel", "chrome", "--out", out, "--png"]
    monkeypatch.setattr(imageio, "write_exr", stopped)
    rc, _, err = run_tool(*cmd, "--steps", "5")
    assert rc == 130 and "interrupted" in err
    monkeypatch.undo()
    rc, _, err = run_tool(*cmd, "--steps", "5")  # its own frames: replaced
    assert rc == 0, err
    (tmp_path / "seq_9.exr").write_bytes(b"the user's")
    rc, text, err = run_tool(*cmd, "--steps", "2")
    assert rc == 0, err
    left = sorted(n for n in os.listdir(tmp_path) if not n.startswith("."))
    assert left == [
        "seq_0.exr",
        "seq_0.png",
        "seq_1.exr",
        "seq_1.png",
        "seq_9.exr",
        "seq_sheet.png",
    ], left
    assert "removed" in text and (tmp_path / "seq_9.exr").read_bytes() == b"the user's"


def test_an_interrupted_fit_leaves_only_files_the_same_command_replaces(
    tmp_path, tiny, monkeypatch
):
    def stopped(*a, **k):
        raise KeyboardInterrupt

    cmd = [
        "fit_manifold",
        tiny["db"],
        "--out",
        tmp_path / "m.npz",
        "--plot",
        tmp_path / "plots",
        "--q",
        "3",
    ]
    monkeypatch.setattr(plots, "convergence", stopped)  # after the manifold and the first plots
    rc, _, err = run_tool(*cmd)
    assert rc == 130 and (tmp_path / "m.npz").is_file(), err
    monkeypatch.undo()
    rc, _, err = run_tool(*cmd)
    assert rc == 0, err
    rc, text, err = run_tool(*cmd[:-1], "2")  # q = 2 has no second slice: its plot goes
    assert rc == 0 and "removed" in text, err
    assert sorted(os.listdir(tmp_path / "plots")) == sorted(
        [ownership.RECORD, "latent_map.png", "log_likelihood.png"]
    )


def test_a_newline_in_a_path_end_is_drawn_escaped(tmp_path, tiny):
    rc, _, err = run_tool(
        "blend",
        "--basis",
        tiny["basis"],
        "--path",
        "0.1,0.2\n",
        "steel",
        "--steps",
        "2",
        "--out",
        tmp_path / "seq.exr",
    )
    assert rc == 0, err
    assert (tmp_path / "seq_sheet.png").is_file()


# ------------------------------------------------- render_basis arguments


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--seed", "1234567890"], "--seed"),
        (["--seed", "-1"], "--seed"),
        (["--seed", str(2**64)], "--seed"),
        (
            ["--seed", str(2**31), "--chunks", "2", "--mode", "per-material", "--spp", "2"],
            "--chunks 2",
        ),
        (["--views", "0,0"], "more than once"),
        (["--spp", "0"], "--spp"),
        (["--chunks", "0"], "--chunks"),
    ],
)
def test_render_basis_checks_seeds_and_views_before_anything_is_written(
    tmp_path, tiny, extra, words
):
    out = tmp_path / "basis"
    rc, _, err = run_render_basis(tiny["manifold"], out, *extra, spp=None)
    assert_one_error(rc, err, words)
    assert not out.exists()


def test_new_manifests_record_their_sensor_and_old_ones_mean_sensor_0(tiny):
    from mitsuba_manifold.basis.folder import Basis
    from mitsuba_manifold.basis.folder import manifest as mf

    m = mf.Manifest.read(tiny["basis"]).to_json()
    assert m["sensor"] == 0 and Basis.load(tiny["basis"]).sensor_known
    old = {k: v for k, v in m.items() if k != "sensor"}
    assert mf.Manifest.from_json(old).differences(m) == []
    assert mf.Manifest.from_json(dict(m, sensor=1)).differences(m) == ["sensor"]
    assert Basis(tiny["basis"], old).sensor == 0 and not Basis(tiny["basis"], old).sensor_known


def test_references_render_the_sensor_of_the_basis_or_say_why_not(tmp_path, tiny):
    from mitsuba_manifold.basis.folder import Basis
    from mitsuba_manifold.render.scene.references import BasisView, reference_sensor

    scene = tmp_path / "two_views.xml"
    scene.write_text(
        '<scene version="3.0.0"><sensor type="perspective"/><sensor type="perspective"/></scene>'
    )
    m = json.loads(open(os.path.join(tiny["basis"], "manifest.json")).read())
    one = Basis(tiny["basis"], dict(m, sensor=1))
    assert reference_sensor(one, scene, warn=print) == 1
    assert BasisView.of(one, str(scene)).sensor == 1
    warnings = []
    old = Basis(tiny["basis"], {k: v for k, v in m.items() if k != "sensor"})
    assert reference_sensor(old, scene, warn=warnings.append) == 0
    assert len(warnings) == 1 and "2 sensors" in warnings[0]
    view = BasisView.of(old, str(scene), warn=warnings.append)
    assert BasisView.from_json(json.loads(json.dumps(view.to_json()))) == view


def test_the_main_job_removes_only_a_basis_of_its_own_to_render_it_again(tmp_path, tiny):
    import shutil

    from mitsuba_manifold.basis.folder.owned_files import remove_basis
    from mitsuba_manifold.errors import ForeignFileError

    own, theirs, user = tmp_path / "own", tmp_path / "theirs", tmp_path / "user"
    for folder in (own, theirs):
        shutil.copytree(tiny["basis"], folder)
    (own / atomic.temporary_name(own / "steel.exr", "1-abcd-0123abcd")).write_bytes(b"killed")
    (theirs / "notes.txt").write_text("the user's")
    user.mkdir()
    (user / "photo.exr").write_bytes(b"the user's")
    remove_basis(own)
    assert not own.exists()
    for folder in (theirs, user):
        before = snapshot(folder)
        with pytest.raises(ForeignFileError, match="not removing it"):
            remove_basis(folder)
        assert snapshot(folder) == before
    os.remove(theirs / "notes.txt")
    os.chmod(theirs / "base.exr", 0o444)
    with pytest.raises(ForeignFileError, match="read-only"):
        remove_basis(theirs)
    remove_basis(tmp_path / "missing")  # nothing to remove

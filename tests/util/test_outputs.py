"""The one output discipline (issue 20), module by module: :class:`ownership.Outputs` and the
atomic writes it watches (temporary names, sweeping, errors naming the user's file)."""

import errno
import json
import os
import subprocess
import sys

import pytest

from mitsuba_manifold._util import atomic, ownership
from mitsuba_manifold.errors import ForeignFileError


def _special_targets(tmp_path):
    """A FIFO, a symbolic link to a file and a folder, none of which a tool may replace."""
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    precious = tmp_path / "precious.txt"
    precious.write_text("the user's")
    link = tmp_path / "link.json"
    link.symlink_to(precious)
    folder = tmp_path / "folder.json"
    folder.mkdir()
    return {"FIFO": fifo, "symbolic link": link, "folder": folder}, precious


def test_non_regular_targets_are_refused_even_with_force(tmp_path):
    targets, precious = _special_targets(tmp_path)
    for path in targets.values():
        for force in (False, True):
            with pytest.raises(ForeignFileError, match="not a regular file|is a folder"):
                ownership.check_replaceable(path, force=force, what="--json")
            with ownership.Outputs("test", force=force) as guard:
                with pytest.raises(ForeignFileError, match="--json"):
                    guard.check(path, "--json")
            with ownership.Outputs(
                "test", force=force, folders=[tmp_path]
            ):  # refused at the write too
                with pytest.raises(ForeignFileError):
                    atomic.write_bytes(path, "report")
    assert os.path.islink(targets["symbolic link"]) and precious.read_text() == "the user's"
    assert not os.path.isfile(targets["FIFO"]) and os.path.exists(targets["FIFO"])
    assert sorted(os.listdir(tmp_path)) == sorted(
        ["fifo.json", "precious.txt", "link.json", "folder.json"]
    )


def test_outputs_replace_their_own_files_only_and_never_read_only_ones(tmp_path):
    out = tmp_path / "report.json"
    with ownership.Outputs("test") as guard:
        guard.check(out, "--json")
        atomic.write_bytes(out, "one")
    with ownership.Outputs("test") as guard:  # its own output: replaced
        guard.check(out, "--json")
        atomic.write_bytes(out, "two")
    assert out.read_text() == "two" and ownership.owned(out)
    os.chmod(out, 0o444)
    with pytest.raises(ForeignFileError, match="read-only"):
        ownership.Outputs("test", force=True).check(out, "--json")
    assert oct(os.stat(out).st_mode & 0o777) == "0o444"
    user = tmp_path / "user.json"
    user.write_text("mine")
    with ownership.Outputs("test", folders=[tmp_path]):  # unchecked, but in a watched folder
        with pytest.raises(ForeignFileError, match="not written by this tool"):
            atomic.write_bytes(user, "theirs")
    assert user.read_text() == "mine"


def test_a_run_stopped_between_recording_and_renaming_leaves_files_the_same_command_replaces(
    tmp_path, monkeypatch
):
    out = tmp_path / "img.exr"
    with ownership.Outputs("test") as guard:
        guard.check(out)
        atomic.write_bytes(out, "first")
    real = os.replace

    def killed(src, dst):
        if os.path.basename(dst) == ownership.RECORD:
            return real(src, dst)
        raise KeyboardInterrupt  # the moment after the record was written

    monkeypatch.setattr(atomic.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        with ownership.Outputs("test") as guard:
            guard.check(out)
            atomic.write_bytes(out, "second")
    monkeypatch.setattr(atomic.os, "replace", real)
    assert out.read_text() == "first" and ownership.owned(
        out
    )  # the old content is still the tool's
    new = tmp_path / "new.exr"  # a first write stopped the same way
    monkeypatch.setattr(atomic.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        with ownership.Outputs("test") as guard:
            atomic.write_bytes(guard.check(new), "x")
    monkeypatch.setattr(atomic.os, "replace", real)
    assert not new.exists() and [f for f in os.listdir(tmp_path) if atomic.is_temporary(f)] == []
    with ownership.Outputs("test") as guard:  # the same command replaces both
        for path in (out, new):
            atomic.write_bytes(guard.check(path), "third")
    assert out.read_text() == new.read_text() == "third"
    record = json.loads((tmp_path / ownership.RECORD).read_text())["files"]
    assert "was" not in record["img.exr"]  # settled once renamed


def test_identical_content_is_left_as_it_is_and_different_content_refused(tmp_path):
    shipped = tmp_path / "bowl.ply"
    shipped.write_text("generated mesh")
    os.chmod(shipped, 0o640)
    with ownership.Outputs("test") as guard:
        guard.check(shipped, identical=True)
        atomic.write_bytes(shipped, "generated mesh")
    assert guard.kept == [str(shipped)] and oct(os.stat(shipped).st_mode & 0o777) == "0o640"
    assert not ownership.owned(shipped)  # still the user's (or the package's)
    with ownership.Outputs("test") as guard:
        guard.check(shipped, identical=True)
        with pytest.raises(ForeignFileError, match="not written by this tool"):
            atomic.write_bytes(shipped, "another mesh")
    assert shipped.read_text() == "generated mesh"
    assert {n for n in os.listdir(tmp_path) if not n.startswith(ownership.RECORD)} == {"bowl.ply"}


def test_a_group_removes_what_its_earlier_run_wrote_and_this_one_did_not(tmp_path):
    def run(names, group="path:seq"):
        with ownership.Outputs("blend.py", group=group) as guard:
            for n in names:
                atomic.write_bytes(guard.check(tmp_path / n), n)
            return guard.remove_stale(tmp_path)

    assert run(["a", "b", "c", "d"]) == []
    (tmp_path / "mine").write_text("user")
    run(["x"], group="path:other")
    (tmp_path / "d").write_text("edited by the user")  # no longer the tool's: kept
    removed = run(["a", "b"])
    assert sorted(os.path.basename(p) for p in removed) == ["c"]
    assert sorted(n for n in os.listdir(tmp_path) if not n.startswith(".")) == [
        "a",
        "b",
        "d",
        "mine",
        "x",
    ]


def test_temporary_names_fit_the_file_system_and_say_what_they_are(tmp_path):
    long_name = "x" * 250 + ".exr"  # fits; its temporary name would not, uncut
    atomic.write_bytes(tmp_path / long_name, "data")
    assert os.listdir(tmp_path) == [long_name]
    name = atomic.temporary_name(tmp_path / long_name, "123-abcd-0123abcd")
    assert (
        len(name) <= 255
        and name.startswith(".x")
        and name.endswith(".tmp.exr")
        and atomic.is_temporary(name)
    )
    assert not atomic.is_temporary("gold-paint.exr") and not atomic.is_temporary("steel.binary")
    assert atomic.is_temporary(
        ".ipswich-pine-221.binary.0a1b2c3d.tmp.binary"
    )  # an earlier version's
    too_long = tmp_path / ("y" * 256 + ".json")
    with pytest.raises(ForeignFileError, match="longer than the file system allows"):
        ownership.check_replaceable(too_long, what="--json")


def test_a_full_disk_names_the_file_and_leaves_nothing(tmp_path):
    path = tmp_path / "img.png"

    def full(f):
        f.write(b"half")
        raise OSError(
            errno.ENOSPC, "No space left on device"
        )  # as a write() reports it: no file name

    with pytest.raises(OSError) as e:
        atomic.atomic_write(path, full)
    assert (
        str(path) in str(e.value)
        and "no space left" in str(e.value).lower()
        and ".tmp" not in str(e.value)
    )
    assert e.value.errno == errno.ENOSPC and os.listdir(tmp_path) == []


def test_temporary_files_of_killed_writers_are_swept_by_the_next_write(tmp_path):
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    pid = int(dead.stdout)
    host = atomic._host()
    killed = atomic.temporary_name(tmp_path / "m.npz", f"{pid}-{host}-0123abcd")
    running = atomic.temporary_name(tmp_path / "m.npz", f"{os.getpid()}-{host}-0123abcd")
    other_host = atomic.temporary_name(
        tmp_path / "m.npz", f"{pid}-{'0000' if host != '0000' else '1111'}-0123abcd"
    )
    old = ".m.npz.0a1b2c3d.tmp.npz"
    for name in (killed, running, other_host, old, ".hidden-by-the-user"):
        (tmp_path / name).write_text("partial")
    os.utime(tmp_path / old, (0, 0))  # an earlier version's, long ago
    atomic.write_bytes(tmp_path / "other.json", "{}")
    left = set(os.listdir(tmp_path))
    assert killed not in left and old not in left
    assert {running, other_host, ".hidden-by-the-user", "other.json"} <= left


def test_a_database_folder_never_counts_temporary_files_as_tables(tmp_path):
    (tmp_path / "steel.binary").write_bytes(b"table")
    (tmp_path / atomic.temporary_name(tmp_path / "chrome.binary", "123-abcd-0123abcd")).write_bytes(
        b"half"
    )
    (tmp_path / ownership.DATABASE_JSON).write_text(
        '{"resolution": [8, 8, 16]}'
    )  # no table list: older
    assert ownership.owned_tables(tmp_path, {"resolution": [8, 8, 16]}, ["steel"], False) == {
        "steel"
    }


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="zombies read from /proc")
def test_a_zombie_writers_temporary_file_is_swept(tmp_path):
    """A killed run's worker that ended but was not reaped (its parent died too) is a zombie: its
    temporary file is swept like a dead process's, and a running process's is kept."""
    import time

    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    running = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:  # not waited for: a zombie once it has ended
            with open(f"/proc/{ended.pid}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                    break
            time.sleep(0.02)
        host = atomic._host()
        for proc, name in ((ended, "a"), (running, "b")):
            (tmp_path / f".{name}.npy.{proc.pid}-{host}-0123abcd.tmp").write_bytes(b"x")
        removed = atomic.sweep(tmp_path, force=True)
        assert [n.startswith(".a.") for n in removed] == [True]
        assert (tmp_path / f".b.npy.{running.pid}-{host}-0123abcd.tmp").exists()
    finally:
        running.kill()
        running.wait()
        ended.wait()


def test_no_output_replaces_an_input_or_lands_in_an_input_folder(tmp_path):
    photo = tmp_path / "photo.exr"
    photo.write_bytes(b"the user's")
    basis = tmp_path / "basis"
    basis.mkdir()
    alias = tmp_path / "alias.exr"
    alias.symlink_to(photo)
    for out in (photo, alias, basis / "blend.exr"):
        with pytest.raises(ForeignFileError, match="would overwrite an input"):
            ownership.check_not_inputs([out], [photo], folders=[basis])
    ownership.check_not_inputs([tmp_path / "new.exr"], [photo], folders=[basis])
    with pytest.raises(ForeignFileError, match=r"^--json .* is an input of this run"):
        ownership.check_not_inputs(
            [photo], [photo], what="--json", reason="is an input of this run"
        )


def test_only_the_tools_own_unchanged_files_are_removed(tmp_path):
    mine, edited, users = (tmp_path / n for n in ("mine.png", "edited.png", "users.png"))
    for p in (mine, edited, users):
        atomic.write_bytes(p, b"made")
    ownership.record([mine, edited], "t.py")
    edited.write_bytes(b"the user's edit")
    kept = tmp_path / "kept.png"
    atomic.write_bytes(kept, b"made")
    ownership.record([kept], "t.py")
    removed = ownership.remove_owned(
        [mine, edited, users, kept, tmp_path / "gone.png"], keep=[kept]
    )
    assert removed == [mine] and not mine.exists()
    assert edited.exists() and users.exists() and kept.exists()


def test_a_result_never_lands_in_a_folder_a_manifest_owns(tmp_path):
    managed = tmp_path / "basis"
    managed.mkdir()
    with pytest.raises(ForeignFileError, match="lies in the basis folder"):
        ownership.check_outside_managed(managed / "o.exr", lambda f: f == str(managed))
    with pytest.raises(ForeignFileError, match="never writes into a basis"):
        ownership.check_outside_managed(tmp_path / "o.exr", lambda f: False, folder=tmp_path)
    ownership.check_outside_managed(tmp_path / "o.exr", lambda f: False, folder=managed)

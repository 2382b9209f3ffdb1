"""Content-hash caches and atomic writes (NumPy only)."""

import os

import numpy as np
import pytest

from mitsuba_manifold._util import atomic, cache


def test_file_hash_follows_the_bytes(tmp_path):
    path = tmp_path / "t.bin"
    path.write_bytes(b"a" * 1000)
    first = cache.file_hash(path)
    assert first == cache.file_hash(str(path))  # memoised, same answer
    st = os.stat(path)
    with open(path, "r+b") as f:  # same size, in place, mtime restored
        f.write(b"b")
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert cache.file_hash(path) != first
    assert cache.key_hash("a", np.arange(3)) != cache.key_hash("a", np.arange(4))
    assert len(cache.key_hash("x", length=16)) == 16


def test_npy_cache_loads_checks_rebuilds_and_evicts(tmp_path):
    calls = []

    def build(value):
        calls.append(value)
        return np.full((2, 3), value, dtype=np.float32)

    damaged = []
    path = str(tmp_path / "k1.thing-v1.npy")
    a = cache.npy_cache(path, lambda: build(1.0), shape=(2, 3), dtype=np.float32, finite=True)
    b = cache.npy_cache(path, lambda: build(2.0), shape=(2, 3), dtype=np.float32, finite=True)
    assert calls == [1.0] and np.array_equal(a, b)  # the second call loads
    cache.write_npy(
        path, np.full((2, 3), np.nan, dtype=np.float32)
    )  # bad values: rebuilt, reported
    c = cache.npy_cache(
        path,
        lambda: build(3.0),
        shape=(2, 3),
        dtype=np.float32,
        finite=True,
        on_rebuild=lambda p, why: damaged.append((p, why)),
    )
    assert calls == [1.0, 3.0] and damaged == [(path, "it holds NaN or Inf values")]
    assert c[0, 0] == 3.0
    with open(path, "wb") as f:  # not even an .npy file
        f.write(b"garbage")
    assert cache.npy_cache(path, lambda: build(4.0), shape=(2, 3))[0, 0] == 4.0
    os.utime(path, (1000, 1000))
    for k in range(2, 5):  # keep the two newest of the kind
        p = str(tmp_path / f"k{k}.thing-v1.npy")
        cache.npy_cache(p, lambda: build(5.0), eviction=cache.Eviction(2, ".thing-v1."))
        os.utime(p, (1000 + k, 1000 + k))
    cache.evict(str(tmp_path), ".thing-v1.", 2)
    assert sorted(os.listdir(tmp_path)) == ["k3.thing-v1.npy", "k4.thing-v1.npy"]

    def write(tmp):  # a writer of the .npy itself, memory-mapped back
        out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float32, shape=(4,))
        out[:] = 7.0
        out.flush()

    m = cache.npy_cache(
        str(tmp_path / "big.npy"), write=write, shape=(4,), dtype=np.float32, mmap=True
    )
    assert isinstance(m, np.memmap) and m[3] == 7.0


def test_atomic_write_leaves_the_old_file_when_the_writer_fails(tmp_path):
    path = tmp_path / "f.txt"
    atomic.write_bytes(path, "old")

    def fail(f):
        f.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic.atomic_write(path, fail)
    assert path.read_text() == "old" and os.listdir(tmp_path) == ["f.txt"]


def test_atomic_write_errors_name_the_users_path_not_the_temporary_file(tmp_path):
    target = tmp_path / "nodir" / "x.json"
    with pytest.raises(FileNotFoundError) as e:
        atomic.write_bytes(target, "data")
    assert str(target) in str(e.value) and "folder" in str(e.value) and ".tmp" not in str(e.value)

    def full(tmp):
        raise OSError(28, "No space left on device", tmp)

    with pytest.raises(OSError) as e:
        atomic.atomic_replace(tmp_path / "y.exr", full)
    assert str(tmp_path / "y.exr") in str(e.value) and ".tmp" not in str(e.value)
    assert os.listdir(tmp_path) == []


def test_read_npy_into_converts_in_place_and_refuses_other_arrays(tmp_path, monkeypatch):
    monkeypatch.setattr(cache, "READ_CHUNK", 7)  # several chunks and a short last one
    rng = np.random.default_rng(0)
    half = rng.uniform(0, 100, (3, 4, 5)).astype(np.float16)
    path = tmp_path / "t.npy"
    cache.write_npy(path, half)
    out = np.full(60, np.nan, dtype=np.float32)
    assert cache.read_npy_into(path, out, shape=(3, 4, 5), dtype=np.float16)
    assert np.array_equal(out, half.astype(np.float32).reshape(-1))
    assert not cache.read_npy_into(path, out, shape=(3, 20), dtype=np.float16)  # other shape
    assert not cache.read_npy_into(path, out, shape=(3, 4, 5), dtype=np.float32)  # other dtype
    cache.write_npy(path, np.asfortranarray(half))
    assert not cache.read_npy_into(path, out, shape=(3, 4, 5), dtype=np.float16)  # Fortran order
    cache.write_npy(path, half)
    path.write_bytes(path.read_bytes()[:-10])  # cut short
    assert not cache.read_npy_into(path, out, shape=(3, 4, 5), dtype=np.float16)
    assert not cache.read_npy_into(tmp_path / "missing.npy", out, shape=(3, 4, 5), dtype=np.float16)
    with pytest.raises(ValueError, match="C-contiguous"):
        cache.read_npy_into(
            path, np.zeros((60, 2), np.float32)[:, 0], shape=(60,), dtype=np.float16
        )


def _doubled_in_place(path):
    """Damage a cache file as a disk or an editor would: its values doubled, its header and
    trailer kept (a valid ``.npy`` of the right shape and dtype)."""
    data = bytearray(open(path, "rb").read())
    value = np.load(path)
    start = len(data) - cache.TRAILER_SIZE - value.nbytes
    data[start : start + value.nbytes] = (2 * value).astype(value.dtype).tobytes()
    open(path, "wb").write(bytes(data))


def test_a_cache_file_whose_content_changed_is_made_again_and_reported(tmp_path, caplog):
    path = str(tmp_path / "k.refl16.npy")
    table = np.linspace(0.1, 1.0, 24, dtype=np.float16).reshape(2, 3, 4)
    first = cache.npy_cache(path, lambda: table, shape=(2, 3, 4), dtype=np.float16)
    assert np.array_equal(first, table) and cache.verify(path) == cache.SEALED
    assert np.array_equal(np.load(path), table)  # still a plain .npy file for NumPy
    assert np.array_equal(np.load(path, mmap_mode="r"), table)
    _doubled_in_place(path)
    assert cache.verify(path) == cache.DAMAGED
    with caplog.at_level("WARNING", logger="mitsuba_manifold"):
        again = cache.npy_cache(path, lambda: table, shape=(2, 3, 4), dtype=np.float16)
    assert np.array_equal(again, table)  # made again, not the doubled values
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and path in lines[0] and "checksum" in lines[0]
    assert "\n" not in lines[0]
    assert cache.verify(path) == cache.SEALED

    out = np.zeros(24, dtype=np.float32)  # the fast reader checks the same checksum
    assert cache.read_npy_into(path, out, shape=(2, 3, 4), dtype=np.float16)
    _doubled_in_place(path)
    seen = []
    assert not cache.read_npy_into(
        path, out, shape=(2, 3, 4), dtype=np.float16, on_rebuild=lambda p, w: seen.append(p)
    )
    assert seen == [path]


def test_a_cache_file_without_a_checksum_is_made_again_silently(tmp_path, caplog):
    path = str(tmp_path / "k.refl16.npy")
    table = np.ones((2, 3), dtype=np.float16)
    np.save(path, 2 * table)  # another program's (or an earlier version's) file
    with caplog.at_level("WARNING", logger="mitsuba_manifold"):
        got = cache.npy_cache(path, lambda: table, shape=(2, 3), dtype=np.float16)
    assert np.array_equal(got, table) and not caplog.records
    assert cache.verify(path) == cache.SEALED
    out = np.zeros(6, dtype=np.float32)
    np.save(path, 2 * table)
    assert not cache.read_npy_into(path, out, shape=(2, 3), dtype=np.float16)


def test_a_full_disk_while_numpy_writes_says_no_space_left(tmp_path):
    def short(tmp):  # what np.save says on a full disk: no errno
        raise OSError("8388608 requested and 4096 written")

    with pytest.raises(OSError) as e:
        atomic.atomic_replace(tmp_path / "t.refl16.npy", short)
    assert "no space left on the device" in str(e.value) and "Errno None" not in str(e.value)
    assert str(tmp_path / "t.refl16.npy") in str(e.value) and os.listdir(tmp_path) == []


def test_a_cache_file_copied_over_another_is_not_taken_for_it(tmp_path, caplog):
    """Two cache files of one shape (two materials' tables): one copied over the other is a
    valid array with a valid checksum of its own bytes, and still not the file asked for."""
    a, b = str(tmp_path / "a.refl16.npy"), str(tmp_path / "b.refl16.npy")
    ta, tb = np.zeros((2, 3), np.float16), np.ones((2, 3), np.float16)
    cache.npy_cache(a, lambda: ta, shape=(2, 3), dtype=np.float16)
    cache.npy_cache(b, lambda: tb, shape=(2, 3), dtype=np.float16)
    with open(a, "rb") as f:
        data = f.read()
    with open(b, "wb") as f:
        f.write(data)
    assert cache.verify(a) == cache.SEALED and cache.verify(b) == cache.DAMAGED
    with caplog.at_level("WARNING", logger="mitsuba_manifold"):
        got = cache.npy_cache(b, lambda: tb, shape=(2, 3), dtype=np.float16)
    assert np.array_equal(got, tb) and len(caplog.records) == 1 and b in caplog.text
    with open(b, "wb") as f:
        f.write(data)
    out = np.zeros(6, np.float32)
    assert not cache.read_npy_into(b, out, shape=(2, 3), dtype=np.float16, on_rebuild=None)


def test_a_cache_hit_that_marks_a_use_is_not_verified_again(tmp_path, monkeypatch):
    """An evicting cache marks each hit as a use (new file times): the file verified on that hit
    is not read again for its checksum on the next (the interleaved rows are gigabytes); a
    change of its bytes still is found."""
    path = str(tmp_path / "k.rows-v1-2x16.npy")
    kind = cache.Eviction(2, ".rows-v1-")
    cache.npy_cache(path, lambda: np.ones(4, np.float32), shape=(4,), eviction=kind, mmap=True)
    cache.npy_cache(path, lambda: np.ones(4, np.float32), shape=(4,), eviction=kind, mmap=True)
    sums = []
    real = cache.zlib.crc32
    monkeypatch.setattr(cache.zlib, "crc32", lambda *a: sums.append(1) or real(*a))
    for _ in range(3):
        got = cache.npy_cache(path, lambda: np.zeros(4, np.float32), shape=(4,), eviction=kind)
        assert got[0] == 1.0
    assert not sums  # no checksum taken: verified once, kept verified
    data = bytearray(open(path, "rb").read())
    data[-cache.TRAILER_SIZE - 1] ^= 1  # one bit of the last value
    open(path, "wb").write(bytes(data))
    assert cache.npy_cache(path, lambda: np.zeros(4, np.float32), shape=(4,), eviction=kind)[0] == 0


def test_a_link_to_another_cache_file_is_not_taken_for_it_even_once_its_target_was_read(tmp_path):
    a, b = str(tmp_path / "a.refl.npy"), str(tmp_path / "b.refl.npy")
    cache.npy_cache(a, lambda: np.zeros(3, np.float32), shape=(3,), mmap=True)
    cache.npy_cache(a, lambda: np.zeros(3, np.float32), shape=(3,), mmap=True)  # verified
    os.symlink(a, b)
    assert cache.verify(a) == cache.SEALED and cache.verify(b) == cache.DAMAGED
    got = cache.npy_cache(b, lambda: np.ones(3, np.float32), shape=(3,), mmap=True)
    assert got[0] == 1.0 and not os.path.islink(b)
    assert np.load(a)[0] == 0.0  # the link's target untouched

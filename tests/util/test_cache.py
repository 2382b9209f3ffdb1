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
    np.save(path, np.full((2, 3), np.nan, dtype=np.float32))  # damaged: rebuilt, reported
    c = cache.npy_cache(
        path,
        lambda: build(3.0),
        shape=(2, 3),
        dtype=np.float32,
        finite=True,
        on_rebuild=damaged.append,
    )
    assert calls == [1.0, 3.0] and damaged == [path] and c[0, 0] == 3.0
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
    np.save(path, half)
    out = np.full(60, np.nan, dtype=np.float32)
    assert cache.read_npy_into(path, out, shape=(3, 4, 5), dtype=np.float16)
    assert np.array_equal(out, half.astype(np.float32).reshape(-1))
    assert not cache.read_npy_into(path, out, shape=(3, 20), dtype=np.float16)  # other shape
    assert not cache.read_npy_into(path, out, shape=(3, 4, 5), dtype=np.float32)  # other dtype
    np.save(path, np.asfortranarray(half))
    assert not cache.read_npy_into(path, out, shape=(3, 4, 5), dtype=np.float16)  # Fortran order
    np.save(path, half)
    path.write_bytes(path.read_bytes()[:-10])  # cut short
    assert not cache.read_npy_into(path, out, shape=(3, 4, 5), dtype=np.float16)
    assert not cache.read_npy_into(tmp_path / "missing.npy", out, shape=(3, 4, 5), dtype=np.float16)
    with pytest.raises(ValueError, match="C-contiguous"):
        cache.read_npy_into(
            path, np.zeros((60, 2), np.float32)[:, 0], shape=(60,), dtype=np.float16
        )

"""Content-hash caches.

:func:`file_hash` is the SHA-256 of a file's bytes. It is computed once per file and
process: the memo is keyed by the file's identity and status (device, inode, size,
modification *and* change time), so a file edited in place -- even with its
modification time restored, which still updates the change time -- is hashed again.
Nothing is trusted across processes: a cache file is found by the hash of the bytes
it was derived from, never by a file's size or date.

:func:`npy_cache` is the one load-check-rebuild-evict pattern for derived ``.npy``
arrays (reflectance tables, interleaved table rows, sampling densities, mixture
tables): load the file if it exists and has the expected shape, dtype and values,
otherwise build it, write it atomically, and keep only the newest few of its kind.
"""

import hashlib
import os
import threading
from dataclasses import dataclass

import numpy as np

from .atomic import atomic_replace, atomic_write

_HASHES = {}
_LOCK = threading.Lock()


def file_identity(path):
    """What the memo of :func:`file_hash` is keyed by: path, device, inode, size, times."""
    st = os.stat(path)
    return (
        os.path.realpath(path),
        st.st_dev,
        st.st_ino,
        st.st_size,
        st.st_mtime_ns,
        st.st_ctime_ns,
    )


def adopt_hash(path, identity, digest):
    """Take the hash a worker process of this run computed for ``path`` right after writing
    it, when the file is still exactly the one it hashed (same :func:`file_identity`).
    Returns whether it was adopted (otherwise the file will be hashed again on use).
    """
    if tuple(identity) != file_identity(path):
        return False
    with _LOCK:
        _HASHES[tuple(identity)] = str(digest)
    return True


def file_hash(path, block=1 << 22):
    """SHA-256 (hex) of a file's bytes, streamed; memoised per process (see the module notes)."""
    path = os.fspath(path)
    key = file_identity(path)
    with _LOCK:
        digest = _HASHES.get(key)
    if digest is None:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(block), b""):
                h.update(chunk)
        digest = h.hexdigest()
        with _LOCK:
            _HASHES[key] = digest
    return digest


def key_hash(*parts, length=None):
    """SHA-256 (hex) of ``parts`` (str, bytes or arrays), e.g. to name a cache file by its inputs."""
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, str):
            p = p.encode()
        elif isinstance(p, np.ndarray):
            p = p.tobytes()
        h.update(bytes(p))
        h.update(b"\0")
    return h.hexdigest()[:length]


def evict(folder, marker, keep):
    """Delete all but the ``keep`` (at least 1) most recently used ``.npy`` files of ``folder``
    whose name holds ``marker``.
    """
    try:
        names = [
            f
            for f in os.listdir(folder)
            if marker in f and f.endswith(".npy") and not f.startswith(".")
        ]
    except OSError:
        return

    def mtime(f):
        try:
            return os.path.getmtime(os.path.join(folder, f))
        except OSError:
            return 0.0

    for f in sorted(names, key=mtime, reverse=True)[max(1, keep) :]:
        try:
            os.remove(os.path.join(folder, f))
        except OSError:
            pass


def _load_valid(path, shape, dtype, finite, mmap):
    try:
        value = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError):
        return None
    if shape is not None and tuple(value.shape) != tuple(shape):
        return None
    if dtype is not None and value.dtype != np.dtype(dtype):
        return None
    if finite and not np.isfinite(value).all():
        return None
    return value


#: Values read and converted at a time by :func:`read_npy_into`.
READ_CHUNK = 1 << 18


def read_npy_into(path, out, *, shape, dtype):
    """Read the ``.npy`` file ``path`` into the array ``out`` (converting its values to
    ``out``'s dtype, a chunk at a time), if it holds a C-ordered array of ``shape`` (of
    ``out``'s size) and ``dtype``; returns whether it did (False: ``out`` is unchanged or
    partly written, and the file is to be made again, as :func:`npy_cache` would).

    No temporary of the whole array: what ``np.load(path).astype(out.dtype)`` gives, without
    its two allocations.
    """
    if not (out.flags.c_contiguous and out.flags.writeable and out.size == np.prod(shape)):
        raise ValueError(f"read_npy_into needs a writable C-contiguous `out` of {shape} values")
    flat = out.reshape(-1)
    dtype = np.dtype(dtype)
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                found_shape, fortran, found = np.lib.format.read_array_header_1_0(f)
            elif version == (2, 0):
                found_shape, fortran, found = np.lib.format.read_array_header_2_0(f)
            else:
                return False
            if fortran or found != dtype or tuple(found_shape) != tuple(shape):
                return False
            buf = np.empty(min(READ_CHUNK, flat.size), dtype=dtype)
            for start in range(0, flat.size, buf.size):
                part = buf[: min(buf.size, flat.size - start)]
                view = memoryview(part).cast("B")
                if f.readinto(view) != view.nbytes:
                    return False
                flat[start : start + part.size] = part
    except (OSError, ValueError):
        return False
    return True


@dataclass(frozen=True)
class Eviction:
    """Which files of a cache folder :func:`npy_cache` keeps: the ``keep`` most recently used
    of those whose name holds ``marker`` (a cache hit counts as a use).

    Parameters
    ----------
    keep : int
        Files of the kind kept after a write.
    marker : str
        What the names of the files of the kind hold (e.g. ``".rows-v1-"``).
    """

    keep: int
    marker: str


def npy_cache(
    path,
    build=None,
    write=None,
    *,
    shape=None,
    dtype=None,
    finite=False,
    mmap=False,
    eviction=None,
    on_rebuild=None,
):
    """Load the array cached at ``path``, or make it and cache it.

    Parameters
    ----------
    path : str
        Cache file, named after the content hash of what it is derived from.
    build : callable, optional
        ``build() -> ndarray``: makes the array (saved with ``np.save``).
    write : callable, optional
        ``write(tmp_path)``: writes the ``.npy`` file itself (for arrays larger than memory,
        e.g. with ``np.lib.format.open_memmap``); instead of ``build``.
    shape, dtype, finite :
        What a cached file must have to be used (``finite``: no NaN or Inf).
    mmap : bool
        Return the array memory-mapped read-only.
    eviction : Eviction, optional
        Mark a cache hit as recently used and, after writing, keep only the most recently used
        files of its kind in the folder (default: no eviction).
    on_rebuild : callable, optional
        ``on_rebuild(path)`` is called when a cached file exists but fails the checks.
    """
    if os.path.exists(path):
        value = _load_valid(path, shape, dtype, finite, mmap)
        if value is not None:
            if eviction is not None:
                os.utime(path)
            return value
        if on_rebuild is not None:
            on_rebuild(path)
    if write is not None:
        atomic_replace(path, write)
        value = None
    else:
        value = build()
        atomic_write(path, lambda f: np.save(f, value))
    if eviction is not None:
        evict(os.path.dirname(os.path.abspath(path)), eviction.marker, eviction.keep)
    if value is None or mmap:
        return np.load(path, mmap_mode="r" if mmap else None)
    return value

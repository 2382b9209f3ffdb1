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

Every cached ``.npy`` file ends with a checksum (:func:`seal`: a 16-byte trailer,
:data:`TRAILER_MAGIC` and the CRC-32 of the file's name and of all its bytes before the
trailer), written with the file and verified when it is read (:func:`verify`, once per file
and process for memory-mapped files; :func:`read_npy_into` as it reads): NumPy ignores the
bytes after an array, so the files stay plain ``.npy`` files. A file whose checksum does not
match (damaged on disk, edited, or another cache file copied over it: the name is part of
the checksum) is made again, and the rebuild is reported in one line naming the file
(:func:`report_rebuild`, on the ``mitsuba_manifold`` logger); a file without a checksum
(written by an earlier version, or by another program) is made again without a word.
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .atomic import atomic_replace

if TYPE_CHECKING:
    from typing import Any


_HASHES: dict = {}
_VERIFIED: dict = {}
_LOCK = threading.Lock()
#: Start of the checksum trailer of a cached ``.npy`` file (8 bytes), then the CRC-32 (8 bytes LE).
TRAILER_MAGIC = b"\x93MMSUM1\n"
TRAILER_SIZE = 16
#: Bytes read at a time when a checksum is computed.
_BLOCK = 1 << 22
LOG = logging.getLogger("mitsuba_manifold")


def file_identity(path) -> tuple[Any, int, int, int, int, int]:
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


def adopt_hash(path, identity, digest) -> bool:
    """Take the hash a worker process of this run computed for ``path`` right after writing
    it, when the file is still exactly the one it hashed (same :func:`file_identity`).
    Returns whether it was adopted (otherwise the file will be hashed again on use).
    """
    if tuple(identity) != file_identity(path):
        return False
    with _LOCK:
        _HASHES[tuple(identity)] = str(digest)
    return True


def file_hash(path, block=1 << 22) -> str:
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


def key_hash(*parts, length=None) -> str:
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


def _trailer(crc) -> bytes:
    return TRAILER_MAGIC + int(crc).to_bytes(8, "little")


def _start(path) -> int:
    """The CRC-32 of the file's name: where a file's checksum starts, so that it is bound to
    the name the cache finds it by (another cache file copied over it does not match).
    """
    return zlib.crc32(os.path.basename(os.fspath(path)).encode())


def seal(path, name=None) -> None:
    """Append the checksum trailer (see the module notes) to the ``.npy`` file ``path`` just
    written, for the name ``name`` (default ``path``: the file's name once in place).
    """
    crc = _start(path if name is None else name)
    with open(path, "r+b") as f:
        for chunk in iter(lambda: f.read(_BLOCK), b""):
            crc = zlib.crc32(chunk, crc)
        f.write(_trailer(crc))


def write_npy(path, value, name=None) -> None:
    """``np.save(path, value)`` and its checksum trailer (:func:`seal`, for ``name``), not
    atomically (a cache's writer inside :func:`atomic_replace`, or a test making a cache file).
    """
    with open(path, "wb") as f:
        np.save(f, np.asarray(value), allow_pickle=False)
    seal(path, name)


#: What :func:`verify` finds.
SEALED, UNSEALED, DAMAGED = "sealed", "unsealed", "damaged"


def _verified_key(path) -> tuple[Any, Any, int, int, int, int, int]:
    """What a sealed result is memoised by: the name the file is found by (part of its checksum)
    and the file's identity (:func:`file_identity`: a link and its target share one).
    """
    return (os.path.basename(path),) + file_identity(path)


def verify(path) -> str:
    """``SEALED`` when the file's checksum trailer matches its name and bytes, ``DAMAGED`` when
    it does not, ``UNSEALED`` when the file has no trailer; a sealed result is memoised per name,
    file identity and process (a file changed since is read again).
    """
    path = os.fspath(path)
    key = _verified_key(path)
    with _LOCK:
        if _VERIFIED.get(key):
            return SEALED
    size = key[4]
    if size < TRAILER_SIZE:
        return UNSEALED
    crc, left = _start(path), size - TRAILER_SIZE
    with open(path, "rb") as f:
        f.seek(left)
        trailer = f.read(TRAILER_SIZE)
        if trailer[:8] != TRAILER_MAGIC:
            return UNSEALED
        f.seek(0)
        while left > 0:
            chunk = f.read(min(_BLOCK, left))
            if not chunk:
                return DAMAGED
            crc = zlib.crc32(chunk, crc)
            left -= len(chunk)
    if trailer != _trailer(crc):
        return DAMAGED
    with _LOCK:
        _VERIFIED[key] = True
    return SEALED


def report_rebuild(path, why="its checksum does not match its content: damaged") -> None:
    """Say in one line (a warning of the ``mitsuba_manifold`` logger) that the cache file
    ``path`` is made again, and why.
    """
    LOG.warning("cache file %s: %s; making it again", os.fspath(path), why)


def evict(folder, marker, keep) -> None:
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

    def mtime(f) -> float:
        try:
            return os.path.getmtime(os.path.join(folder, f))
        except OSError:
            return 0.0

    for f in sorted(names, key=mtime, reverse=True)[max(1, keep) :]:
        try:
            os.remove(os.path.join(folder, f))
        except OSError:
            pass


def _load_valid(path, shape, dtype, finite, mmap) -> tuple[Any, str | None]:
    """``(array, None)`` of a valid cache file, else ``(None, why)`` (``why`` None: nothing to
    report, e.g. a file of an earlier version without a checksum).
    """
    try:
        state = verify(path)
        if state != SEALED:
            return None, (
                None if state == UNSEALED else "its checksum does not match its content: damaged"
            )
        value = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError):
        return None, "it cannot be read as an array"
    if shape is not None and tuple(value.shape) != tuple(shape):
        return None, f"it holds an array of shape {value.shape}, not {tuple(shape)}"
    if dtype is not None and value.dtype != np.dtype(dtype):
        return None, f"it holds {value.dtype} values, not {np.dtype(dtype)}"
    if finite and not np.isfinite(value).all():
        return None, "it holds NaN or Inf values"
    return value, None


#: Values read and converted at a time by :func:`read_npy_into`.
READ_CHUNK = 1 << 18


def read_npy_into(path, out, *, shape, dtype, finite=False, on_rebuild=report_rebuild) -> bool:
    """Read the cached ``.npy`` file ``path`` into the array ``out`` (converting its values to
    ``out``'s dtype, a chunk at a time), if it holds a C-ordered array of ``shape`` (of
    ``out``'s size) and ``dtype`` whose checksum trailer matches (and, with ``finite``, only
    finite values); returns whether it did (False: ``out`` is unchanged or partly written, and
    the file is to be made again, as :func:`npy_cache` would). ``on_rebuild(path, why)`` is
    called when the file exists and is damaged (checksum, values); a missing file, or one
    without a checksum, is not reported.

    No temporary of the whole array: what ``np.load(path).astype(out.dtype)`` gives, without
    its two allocations; the checksum is taken on the chunks as they are read.
    """
    if not (out.flags.c_contiguous and out.flags.writeable and out.size == np.prod(shape)):
        raise ValueError(f"read_npy_into needs a writable C-contiguous `out` of {shape} values")
    flat = out.reshape(-1)
    dtype = np.dtype(dtype)
    why = None
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
            start_of_data = f.tell()
            f.seek(0)
            crc = zlib.crc32(f.read(start_of_data), _start(path))
            buf = np.empty(min(READ_CHUNK, flat.size), dtype=dtype)
            for start in range(0, flat.size, buf.size):
                part = buf[: min(buf.size, flat.size - start)]
                view = memoryview(part).cast("B")
                if f.readinto(view) != view.nbytes:
                    return False
                crc = zlib.crc32(view, crc)
                dest = flat[start : start + part.size]
                dest[...] = part
                if finite and why is None and not np.isfinite(dest).all():
                    why = "it holds NaN or Inf values"
            trailer = f.read(TRAILER_SIZE + 1)
    except (OSError, ValueError):
        return False
    if trailer[:8] != TRAILER_MAGIC or len(trailer) != TRAILER_SIZE:
        return False  # no checksum (an earlier version's file), or bytes after it
    if trailer != _trailer(crc):
        why = "its checksum does not match its content: damaged"
    if why is not None:
        if on_rebuild is not None:
            on_rebuild(path, why)
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
    on_rebuild=report_rebuild,
) -> np.ndarray:
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
        ``on_rebuild(path, why)`` is called when a cached file exists but fails the checks
        (its checksum, shape, dtype or values; default :func:`report_rebuild`: one line); a
        file without a checksum (an earlier version's) is made again without a call.
    """
    if os.path.exists(path):
        value, why = _load_valid(path, shape, dtype, finite, mmap)
        if value is not None:
            if eviction is not None:
                os.utime(path)  # a use; the file just verified stays verified under its new times
                with _LOCK:
                    _VERIFIED[_verified_key(path)] = True
            return value
        if on_rebuild is not None and why is not None:
            on_rebuild(path, why)
    if write is not None:

        def sealed(tmp) -> None:
            write(tmp)
            seal(tmp, path)

        atomic_replace(path, sealed)
        value = None
    else:
        value = build()
        atomic_replace(path, lambda tmp: write_npy(tmp, value, path))
    if eviction is not None:
        evict(os.path.dirname(os.path.abspath(path)), eviction.marker, eviction.keep)
    if value is None or mmap:
        return np.load(path, mmap_mode="r" if mmap else None)
    return value

"""Atomic file writes: a temporary file beside the target, renamed over it on success.

A reader never sees a half-written file, and an existing file is replaced only when
the new one is complete (GUIDE: nothing existing destroyed or half-written).

Temporary files are hidden and say what they are: ``.<name>.<pid>-<host>-<random>.tmp<ext>``
(:func:`is_temporary`; the name cut short where the file system's limit needs it). Readers
of a folder skip names starting with ``.``, so no reader takes one for data. One killed
with its process (SIGKILL, a power cut) is removed by the next write into its folder
(:func:`sweep`): the process that made it, named in it, no longer runs on this host.

An active *watcher* (:func:`watching`, used by :class:`mitsuba_manifold._util.ownership.Outputs`)
sees every write: ``watcher.before(path)`` before the temporary file is made (it may
refuse the target), ``watcher.claim(path, tmp)`` when the new content is complete and
before the rename (it records the file as its own, or returns False to keep the existing
file, e.g. one of identical content).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import secrets
import socket
import threading
import time
from typing import TYPE_CHECKING

from ..errors import MitsubaManifoldError

if TYPE_CHECKING:
    from collections.abc import Iterator
    from typing import Any


#: Tries at a fresh temporary name before giving up (as :func:`tempfile.mkstemp`).
_TRIES = 100
#: Bytes per file name where the file system does not say (``NAME_MAX`` of Linux, macOS, Windows).
NAME_MAX = 255
#: ``.<name>.<pid>-<host>-<random>.tmp<ext>`` (this version) and ``.<name>.<random>.tmp<ext>`` (earlier ones).
_TEMPORARY = re.compile(
    r"^\..*\.(?:(?P<pid>\d+)-(?P<host>[0-9a-f]{4})-)?[0-9a-z]{8}\.tmp(?:\.[^.]*)?$"
)
#: A temporary file of an earlier version (no process named) this old (seconds) is stale.
STALE_AGE = 6 * 3600

_WATCHERS: list = []
_SWEPT: set = set()
_LOCK = threading.Lock()


def is_temporary(name) -> bool:
    """True when the file name ``name`` is a temporary file of :func:`atomic_replace` (of this
    or an earlier version): readers skip it (and every name starting with ``.``).
    """
    return bool(_TEMPORARY.match(os.path.basename(os.fspath(name))))


def _host() -> str:
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:4]


@contextlib.contextmanager
def watching(watcher) -> Iterator[None]:
    """Let ``watcher`` see every atomic write while the block runs (see the module notes)."""
    with _LOCK:
        _WATCHERS.append(watcher)
    try:
        yield watcher
    finally:
        with _LOCK:
            _WATCHERS.remove(watcher)


def atomic_replace(path, write) -> None:
    """Call ``write(tmp_path)`` on a temporary file beside ``path``, then rename it to ``path``.

    An existing ``path`` is replaced only when ``write`` succeeds; the new file gets the
    usual permissions (umask), not ``mkstemp``'s private ones. An ``OSError`` of the
    writer about the temporary file or about no file (a full disk: ``ENOSPC``) is raised
    as the same error naming ``path``.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    with _LOCK:
        watchers = list(_WATCHERS)
    for w in watchers:
        w.before(path)
    sweep(folder)
    try:
        tmp, mode = _temporary(path, folder)
    except OSError as e:
        raise _naming(e, path, folder) from None
    try:
        write(tmp)
        os.chmod(tmp, mode)  # a writer that re-created the file may have given it other permissions
        keep = [w.claim(path, tmp) for w in watchers]
        if all(k is not False for k in keep):
            os.replace(tmp, path)
    except BaseException as e:
        if (
            isinstance(e, OSError)
            and not isinstance(e, MitsubaManifoldError)
            and (tmp in (e.filename, e.filename2) or e.filename is None)
        ):
            _remove(tmp)
            raise _naming(e, path, folder) from None
        _remove(tmp)
        raise
    _remove(tmp)


def _remove(tmp) -> None:
    try:
        os.unlink(tmp)
    except FileNotFoundError:
        pass


def _name_max(folder) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return NAME_MAX


def name_max(path) -> int:
    """Longest file name (bytes) the file system of ``path``'s folder (or its nearest existing
    parent) allows.
    """
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    while not os.path.isdir(folder) and os.path.dirname(folder) != folder:
        folder = os.path.dirname(folder)
    return _name_max(folder)


def temporary_name(path, token, limit=NAME_MAX) -> str:
    """``.<name>.<token>.tmp<ext>`` for ``path``, its name shortened (never its token and
    extension) to at most ``limit`` bytes.
    """
    base = os.path.basename(os.fspath(path))
    suffix = f".{token}.tmp{os.path.splitext(base)[1]}"
    room = limit - 1 - len(os.fsencode(suffix))
    while base and len(os.fsencode(base)) > room:
        base = base[:-1]
    return "." + base + suffix


def _temporary(path, folder) -> tuple[Any, int]:
    """A new empty file beside ``path`` (:func:`temporary_name`) and its permissions.

    The file is created with mode 0666, so the kernel applies the process's umask (read
    here, when it is needed, without changing it: ``os.umask`` can only be read by
    setting it, which would race with other threads creating files).
    """
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    limit = _name_max(folder) if os.path.isdir(folder) else NAME_MAX
    for _ in range(_TRIES):
        token = f"{os.getpid()}-{_host()}-{secrets.token_hex(4)}"
        tmp = os.path.join(folder, temporary_name(path, token, limit))
        try:
            fd = os.open(tmp, flags, 0o666)
        except FileExistsError:
            continue
        try:
            return tmp, os.fstat(fd).st_mode & 0o777
        finally:
            os.close(fd)
    raise FileExistsError(f"no free temporary name beside {path} after {_TRIES} tries")


def _alive(pid) -> bool:
    """Whether process ``pid`` runs; a zombie (ended, not yet reaped: a killed run's worker whose
    parent died too) does not.
    """
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    if not os.path.isdir("/proc/self"):  # not Linux: as os.kill says
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:  # ended meanwhile
        return False
    except (OSError, IndexError):
        return True


def sweep(folder, force=False) -> list:
    """Remove the temporary files in ``folder`` left by writers that were killed: those naming
    a process of this host that no longer runs, and those of earlier versions (no process
    named) older than :data:`STALE_AGE`. Done once per folder and process unless ``force``;
    returns the names removed.
    """
    folder = os.path.abspath(os.fspath(folder))
    with _LOCK:
        if folder in _SWEPT and not force:
            return []
        _SWEPT.add(folder)
    try:
        names = [n for n in os.listdir(folder) if n.startswith(".") and ".tmp" in n]
    except OSError:
        return []
    removed, host, now = [], _host(), time.time()
    for name in names:
        m = _TEMPORARY.match(name)
        if m is None:
            continue
        path = os.path.join(folder, name)
        try:
            if m.group("pid") is None:
                stale = now - os.lstat(path).st_mtime > STALE_AGE
            else:
                stale = m.group("host") == host and not _alive(int(m.group("pid")))
            if stale and os.path.isfile(path) and not os.path.islink(path):
                os.unlink(path)
                removed.append(name)
        except OSError:
            continue
    return removed


#: What NumPy says when ``tofile`` (``np.save`` to a file) writes less than it should, without an errno.
_SHORT_WRITE = re.compile(r"\d+ requested and \d+ written")


def _full(error, folder) -> bool:
    """True when ``error`` is a full disk: ``ENOSPC``, or an error without an errno (NumPy's short
    write) while the file system of ``folder`` has no space left.
    """
    if error.errno == errno.ENOSPC:
        return True
    if error.errno is not None:
        return False
    try:
        st = os.statvfs(folder)
        empty = st.f_bavail == 0
    except (OSError, AttributeError):
        empty = False
    return empty or bool(_SHORT_WRITE.search(str(error)))


def _naming(error, path, folder):
    """``error`` (about the temporary file) as the same kind of OSError about ``path``, the
    user's name: the temporary file is an implementation detail that no longer exists. A
    full disk is said so, whoever noticed it (the OS, or NumPy writing less than it asked).
    """
    why = error.strerror or (str(error) or type(error).__name__)
    number = error.errno
    if not os.path.isdir(folder):
        why = f"its folder {folder} does not exist (create it, or choose another path)"
    elif error.errno == errno.ENAMETOOLONG:
        why = (
            f"its name is too long for the file system ({len(os.fsencode(os.path.basename(path)))} bytes, "
            f"at most {_name_max(folder)}): choose a shorter name"
        )
    elif _full(error, folder):
        why = "no space left on the device (free some space, or choose another folder)"
        number = errno.ENOSPC
    if number is None:
        return OSError(f"cannot write {path}: {why}")
    return OSError(number, f"cannot write {path}: {why}")


def atomic_write(path, write) -> None:
    """Call ``write(file_object)`` on a temporary file (binary mode) beside ``path``, then rename it."""

    def to_path(tmp) -> None:
        with open(tmp, "wb") as f:
            write(f)

    atomic_replace(path, to_path)


def write_bytes(path, data) -> None:
    """Write ``data`` (bytes or str, UTF-8) to ``path`` atomically."""
    if isinstance(data, str):
        data = data.encode()
    atomic_write(path, lambda f: f.write(data))

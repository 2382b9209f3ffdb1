"""Atomic file writes: a temporary file beside the target, renamed over it on success.

A reader never sees a half-written file, and an existing file is replaced only when
the new one is complete (GUIDE: nothing existing destroyed or half-written).
"""

import os
import secrets

#: Tries at a fresh temporary name before giving up (as :func:`tempfile.mkstemp`).
_TRIES = 100


def atomic_replace(path, write):
    """Call ``write(tmp_path)`` on a temporary file beside ``path``, then rename it to ``path``.

    An existing ``path`` is replaced only when ``write`` succeeds; the new file gets the
    usual permissions (umask), not ``mkstemp``'s private ones.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    try:
        tmp, mode = _temporary(path, folder)
    except OSError as e:
        raise _naming(e, path, folder) from None
    try:
        write(tmp)
        os.chmod(tmp, mode)   # a writer that re-created the file may have given it other permissions
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError) and tmp in (e.filename, e.filename2):
            raise _naming(e, path, folder) from None
        raise


def _temporary(path, folder):
    """A new empty file beside ``path`` (``.<name>.<random>.tmp<ext>``) and its permissions.

    The file is created with mode 0666, so the kernel applies the process's umask (read
    here, when it is needed, without changing it: ``os.umask`` can only be read by
    setting it, which would race with other threads creating files)."""
    prefix, suffix = "." + os.path.basename(path) + ".", ".tmp" + os.path.splitext(path)[1]
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    for _ in range(_TRIES):
        tmp = os.path.join(folder, prefix + secrets.token_hex(4) + suffix)
        try:
            fd = os.open(tmp, flags, 0o666)
        except FileExistsError:
            continue
        try:
            return tmp, os.fstat(fd).st_mode & 0o777
        finally:
            os.close(fd)
    raise FileExistsError(f"no free temporary name beside {path} after {_TRIES} tries")


def _naming(error, path, folder):
    """``error`` (about the temporary file) as the same kind of OSError about ``path``, the
    user's name: the temporary file is an implementation detail that no longer exists."""
    why = error.strerror or type(error).__name__
    if not os.path.isdir(folder):
        why = f"its folder {folder} does not exist (create it, or choose another path)"
    return OSError(error.errno, f"cannot write {path}: {why}")


def atomic_write(path, write):
    """Call ``write(file_object)`` on a temporary file (binary mode) beside ``path``, then rename it."""
    def to_path(tmp):
        with open(tmp, "wb") as f:
            write(f)
    atomic_replace(path, to_path)


def write_bytes(path, data):
    """Write ``data`` (bytes or str, UTF-8) to ``path`` atomically."""
    if isinstance(data, str):
        data = data.encode()
    atomic_write(path, lambda f: f.write(data))

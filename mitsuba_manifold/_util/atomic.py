"""Atomic file writes: a temporary file beside the target, renamed over it on success.

A reader never sees a half-written file, and an existing file is replaced only when
the new one is complete (GUIDE: nothing existing destroyed or half-written).
"""

import os
import tempfile

# The process's umask, read once: reading it means setting it, which races with other threads.
_UMASK = os.umask(0)
os.umask(_UMASK)


def atomic_replace(path, write):
    """Call ``write(tmp_path)`` on a temporary file beside ``path``, then rename it to ``path``.

    An existing ``path`` is replaced only when ``write`` succeeds; the new file gets the
    usual permissions (umask), not ``mkstemp``'s private ones.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".",
                                   suffix=".tmp" + os.path.splitext(path)[1], dir=folder)
    except OSError as e:
        raise _naming(e, path, folder) from None
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError) and tmp in (e.filename, e.filename2):
            raise _naming(e, path, folder) from None
        raise


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

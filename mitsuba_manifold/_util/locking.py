"""An OS file lock on a folder while a tool writes into it.

:class:`FolderLock` takes ``fcntl.flock(LOCK_EX | LOCK_NB)`` on the folder itself (an open
directory descriptor), so locking adds no file to the folder; where the file system does
not lock directories it locks ``<folder>/.mitsuba-manifold.lock`` instead (and a named lock,
``name=``, locks that file). A lock file is removed as the lock is released, while it is
still held, so a finished or failed run leaves none behind; an acquirer that locked a file
since removed (its descriptor's inode no longer the one at the path) lets it go and locks the
path afresh, so two processes never both hold a lock. The kernel releases the lock when the
process ends, however it ends (kill -9 included, which leaves the file: harmless, the next
run locks and removes it). A second writer does not wait: it gets :class:`FolderLockedError`
naming the folder.

``filelock`` does not serve here: it locks a file it creates (never the folder itself) and
leaves that file in place on release.
"""

from __future__ import annotations

import fcntl
import os
from typing import Literal

from ..errors import FolderLockedError

LOCK_NAME = ".mitsuba-manifold.lock"


class FolderLock:
    """Exclusive, non-blocking lock of a folder (created if missing), as a context manager.

    Parameters
    ----------
    folder : path
    what : str
        What the folder holds, for the error message ("basis folder", "database folder").
    name : str, optional
        Lock this file of the folder instead of the folder itself (another name locks
        something else in the same folder).
    wait : bool
        Block until the lock is free instead of raising (for short critical sections).

    Examples
    --------
    >>> with FolderLock(out, "basis folder"):
    ...     render_into(out)
    """

    def __init__(self, folder, what="folder", name=None, wait=False) -> None:
        self.folder = os.fspath(folder)
        self.what = what
        self.path = self.folder if name is None else os.path.join(self.folder, name)
        self.wait = wait
        self._fd = None

    def _open(self) -> int:
        if os.path.isdir(self.path):
            fd = os.open(self.path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
            try:
                fcntl.flock(
                    fd, fcntl.LOCK_SH | fcntl.LOCK_NB
                )  # does this file system lock folders?
                fcntl.flock(fd, fcntl.LOCK_UN)
                return fd
            except BlockingIOError:
                return fd  # it does: someone holds it
            except OSError:
                os.close(fd)
                self.path = os.path.join(self.folder, LOCK_NAME)
        return os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)

    def _current(self, fd) -> bool:
        """True when ``fd`` is the folder, or the lock file still at :attr:`path` (not one a
        releasing holder removed after this process opened it).
        """
        if self.path == self.folder:
            return True
        try:
            at = os.stat(self.path)
        except FileNotFoundError:
            return False
        held = os.fstat(fd)
        return (at.st_dev, at.st_ino) == (held.st_dev, held.st_ino)

    def acquire(self) -> FolderLock:
        os.makedirs(self.folder, exist_ok=True)
        while True:
            fd = self._open()
            try:
                fcntl.flock(fd, fcntl.LOCK_EX if self.wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
                if self._current(fd):
                    break
            except BlockingIOError:
                os.close(fd)
                raise FolderLockedError(
                    f"{self.what} {self.folder} is being written by another process (it holds "
                    f"the lock on {self.path}); wait for it to finish or choose another folder"
                ) from None
            except BaseException:
                os.close(fd)
                raise
            os.close(fd)  # its holder removed the file as it released it: lock the new one
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            if self.path != self.folder:  # removed while held: no one can have locked it since
                try:
                    os.unlink(self.path)
                except OSError:
                    pass  # gone already, or the folder is read-only: the file is harmless
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc) -> Literal[False]:
        self.release()
        return False


def is_locked(folder) -> bool:
    """True when a :class:`FolderLock` of ``folder`` (on the folder, or on its lock file) is held
    now, by another process or another lock of this one: a tool is writing into it. Takes
    nothing: a shared lock is tried and let go at once.
    """
    folder = os.fspath(folder)
    for path in (folder, os.path.join(folder, LOCK_NAME)):
        try:
            flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if path == folder else 0)
            fd = os.open(path, flags)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            fcntl.flock(fd, fcntl.LOCK_UN)
        except BlockingIOError:
            return True
        except OSError:
            pass
        finally:
            os.close(fd)
    return False

"""An OS file lock on a folder while a tool writes into it.

:class:`FolderLock` takes ``fcntl.flock(LOCK_EX | LOCK_NB)`` on the folder itself (an open
directory descriptor), so locking adds no file to the folder; where the file system does
not lock directories it locks ``<folder>/.mitsuba-manifold.lock`` instead. The kernel
releases the lock when the process ends, however it ends (kill -9 included), so there is
nothing stale to clean up. A second writer does not wait: it gets
:class:`FolderLockedError` naming the folder.
"""

import fcntl
import os

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

    def __init__(self, folder, what="folder", name=None, wait=False):
        self.folder = os.fspath(folder)
        self.what = what
        self.path = self.folder if name is None else os.path.join(self.folder, name)
        self.wait = wait
        self._fd = None

    def _open(self):
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

    def acquire(self):
        os.makedirs(self.folder, exist_ok=True)
        fd = self._open()
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if self.wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise FolderLockedError(
                f"{self.what} {self.folder} is being written by another process (it holds the lock "
                f"on {self.path}); wait for it to finish or choose another folder"
            ) from None
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        return self

    def release(self):
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
        return False

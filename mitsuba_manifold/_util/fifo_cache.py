"""The last few answers of a computation, by key (thread-safe, first in, first out)."""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing import Any


class Recent:
    """Keeps the ``size`` newest answers of :meth:`get`. An answer is made outside the lock, so
    two threads may both make one for the same key (the later is kept); the caller owns what it
    gets back (copy mutable answers).
    """

    def __init__(self, size) -> None:
        self._items: dict
        self.size, self._items, self._lock = int(size), {}, threading.Lock()

    def get(self, key, make) -> Any:
        """The kept answer for ``key``, or ``make()`` kept."""
        with self._lock:
            if key in self._items:
                return self._items[key]
        value = make()
        with self._lock:
            self._items[key] = value
            while len(self._items) > self.size:
                self._items.pop(next(iter(self._items)))
        return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()

"""Process-wide settings applied while Mitsuba creates the package's plugins.

Mitsuba instantiates plugins from a scene file, with only the scene's parameters as
input. When a manifold's database moved, :func:`database_override` tells every
``manifold_brdf`` created meanwhile (without a ``database`` parameter of its own) where
its tables are now (:func:`mitsuba_manifold.render.scene.loading.load_scene` uses it for its ``database`` parameter).
It is process-wide, not thread-local: Mitsuba creates plugins on its own threads.
"""

from __future__ import annotations

import contextlib
import os
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Iterator


_database = None


def database_folder() -> str | None:
    """The folder set by the innermost active :func:`database_override` (or None)."""
    return _database


@contextlib.contextmanager
def database_override(folder) -> Iterator[None]:
    """Within the block, new ``manifold_brdf`` instances without a ``database`` parameter
    read their tables from ``folder``; None changes nothing.
    """
    global _database
    previous = _database
    _database = None if folder is None else os.fspath(folder)
    try:
        yield
    finally:
        _database = previous

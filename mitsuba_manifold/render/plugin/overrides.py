"""Process-wide settings applied while Mitsuba creates the package's plugins.

Mitsuba instantiates plugins from a scene file, with only the scene's parameters as
input. When a manifold's database moved, :func:`database_override` tells every
``manifold_brdf`` created meanwhile (without a ``database`` parameter of its own) where
its tables are now (:func:`mitsuba_manifold.render.scene.loading.load_scene` uses it for its ``database`` parameter).
It is process-wide, not thread-local: Mitsuba creates plugins on its own threads.
"""

import contextlib
import os

_database = None


def database_folder():
    """The folder set by the innermost active :func:`database_override` (or None)."""
    return _database


@contextlib.contextmanager
def database_override(folder):
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

"""Manifolds that ship with the package: the default fit of each built-in measured set.

``merl``, ``rgl``, ``nielsen`` and ``all`` name a manifold wherever a manifold file is taken
(``Manifold.load``, the plugin's ``manifold`` parameter, every tool's ``--manifold``): the
default preset fit on that built-in set (:data:`~mitsuba_manifold.data.sources.BUILTIN`) at
MERL's resolution, whose tables are the built-in ones, made on demand. An existing file or
folder of that name wins over the built-in manifold. ``tools/build_manifolds.py`` refits and
writes them all.
"""

import os

from ..errors import InputError

#: The shipped manifolds: name -> what it is (each the default fit of the built-in set of its name).
SHIPPED = {
    "merl": "the default fit of the 100 MERL materials (the default manifold)",
    "rgl": "the default fit of the 51 RGL-EPFL materials",
    "nielsen": "the default fit of the 8 Nielsen et al. materials",
    "all": "the default fit of all 159 built-in materials",
}
#: The folder holding them, ``<name>.npz``.
FOLDER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "shipped")


def shipped_path(name) -> str:
    """The file of shipped manifold ``name`` (:data:`SHIPPED`).

    Raises
    ------
    InputError
        ``name`` is not a shipped manifold, or its file is missing from this installation.
    """
    if name not in SHIPPED:
        raise InputError(
            f"no shipped manifold {name!r}; the shipped manifolds are {', '.join(SHIPPED)}"
        )
    path = os.path.join(FOLDER, name + ".npz")
    if not os.path.isfile(path):
        raise InputError(
            f"the shipped manifold {name!r} is missing from this installation ({path}); "
            "reinstall the package or run tools/build_manifolds.py"
        )
    return path


def resolve_manifold(path) -> str:
    """The manifold file that ``path`` names: ``path`` itself when it exists (an existing path
    wins), else the shipped manifold of that name (:data:`SHIPPED`), else ``path`` unchanged
    (its reader then says that it does not exist).
    """
    path = os.fspath(path)
    if os.path.exists(path) or path not in SHIPPED:
        return path
    return shipped_path(path)

"""Manifolds that ship with the package: the default fit of each built-in measured set.

``merl``, ``rgl``, ``nielsen`` and ``all`` name a manifold wherever a manifold file is taken
(``Manifold.load``, the plugin's ``manifold`` parameter, every tool's ``--manifold``): the
default preset fit on that built-in set (:data:`~mitsuba_manifold.data.sources.BUILTIN`) at
MERL's resolution, whose tables are the built-in ones, made on demand. Names are read by the
rule of database names (:func:`~mitsuba_manifold.data.sources.builtin_set`): ``builtin:merl``
is always the shipped manifold; a bare ``merl`` is, unless a file or folder of that name
exists, and then the name is ambiguous and refused, naming both. ``tools/build_manifolds.py``
refits and writes them all.
"""

import os

from ...data.sources import BUILTIN_PREFIX
from ...errors import InputError

#: The shipped manifolds: name -> what it is (each the default fit of the built-in set of its name).
SHIPPED = {
    "merl": "the default fit of the 100 MERL materials (the default manifold)",
    "rgl": "the default fit of the 51 RGL-EPFL materials",
    "nielsen": "the default fit of the 8 Nielsen et al. materials",
    "all": "the default fit of all 159 built-in materials",
}
#: The folder holding them, ``<name>.npz``.
FOLDER = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "shipped")


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


def ambiguity(name, existing) -> InputError:
    """The error of a bare shipped manifold's name where a file or folder ``existing`` of that
    name exists: it names both and how to say each.
    """
    kind = "folder" if os.path.isdir(existing) else "file"
    return InputError(
        f"manifold {name!r} is ambiguous: the shipped manifold {name} ({SHIPPED[name]}) and the "
        f"{kind} {os.path.abspath(existing)}; say ./{name} (or its full path) for the {kind} or "
        f"{BUILTIN_PREFIX}{name} for the shipped manifold"
    )


def resolve_manifold(path, *, recorded=False) -> str:
    """The manifold file that ``path`` names.

    * ``builtin:NAME`` is the shipped manifold ``NAME`` (an unknown one is refused);
    * a bare shipped name (``merl``) is the shipped manifold, unless a file or folder of that
      name exists: then it is ambiguous and refused (:func:`ambiguity`). Where the name was
      recorded by this package (``recorded``: a basis manifest), files are absolute paths, so a
      bare name there is always the shipped manifold;
    * anything else is ``path`` unchanged (its reader says when it does not exist).
    """
    path = os.fspath(path)
    if path.startswith(BUILTIN_PREFIX):
        return shipped_path(path[len(BUILTIN_PREFIX) :])
    if path not in SHIPPED:
        return path
    if not recorded and os.path.lexists(path):
        raise ambiguity(path, path)
    return shipped_path(path)


def check_sets(names, what="`sets`") -> list:
    """``names`` when each is a shipped manifold (:data:`SHIPPED`), else an :class:`InputError`
    naming the others.
    """
    unknown = [s for s in names if s not in SHIPPED]
    if unknown:
        raise InputError(f"{what} {','.join(unknown)}: not shipped; one of {', '.join(SHIPPED)}")
    return list(names)


def write(manifold, name, folder=FOLDER):
    """Write the fitted ``manifold`` as shipped manifold ``name`` (``<folder>/<name>.npz``) so
    that the same fit gives the same bytes on every machine: the fit's wall times left out, the
    archive's entries dated 1980-01-01. Returns ``(path, timings)`` (the timings left out).
    """
    from .fit_record import Timings

    os.makedirs(folder, exist_ok=True)
    seconds = manifold.record.timings
    manifold.record.timings = Timings()  # machine-dependent: not in the shipped file
    path = os.path.join(folder, name + ".npz")
    manifold.save(path)
    _fixed_dates(path)
    return path, seconds


def _fixed_dates(path) -> None:
    """Rewrite the ``.npz`` archive ``path`` with every entry dated 1980-01-01 (atomically)."""
    import zipfile

    with zipfile.ZipFile(path) as z:
        entries = [(info.filename, z.read(info)) for info in z.infolist()]
    tmp = path + ".tmp"
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as z:
        for name, data in entries:
            z.writestr(zipfile.ZipInfo(name, (1980, 1, 1, 0, 0, 0)), data)
    os.replace(tmp, path)

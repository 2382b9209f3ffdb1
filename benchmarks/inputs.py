"""Checks of a benchmark's inputs, made before anything is computed or written.

A benchmark can run for minutes to hours (and ``tools/bench.py`` first makes a database of
MERL resolution when none is given), so the files and values it is given are checked up
front: :func:`check` raises :class:`~mitsuba_manifold.errors.InputError` with one line naming
the Python parameter (```manifold```, which the tool writes as its option ``--manifold``).
The checks read files, never write one.
"""

import os

from mitsuba_manifold._util.checks import positive_int
from mitsuba_manifold.errors import InputError, did_you_mean
from mitsuba_manifold.manifold.space import FOLDS


def manifold_file(path, name="`manifold`"):
    """The manifold saved at ``path`` (loaded), or InputError naming ``name``."""
    from mitsuba_manifold.manifold.model import Manifold

    try:
        return Manifold.load(path)
    except InputError as e:
        raise InputError(f"{name}: {e}") from None


def basis_folder(path, manifold=None, name="`basis`"):
    """Check that ``path`` is a basis folder (of ``manifold``, when given); InputError naming ``name``."""
    from mitsuba_manifold.basis.folder import Basis

    if not os.path.isdir(path):
        raise InputError(
            f"{name}: basis folder {path} does not exist"
            if not os.path.exists(path)
            else f"{name}: {path} is not a folder (give a basis folder that render_basis.py wrote)"
        )
    try:
        Basis.load(path, manifold=manifold)
    except InputError as e:
        raise InputError(f"{name}: {e}") from None


def database_names(folder, name="`folder`"):
    """Material names of the database ``folder`` (a folder of tables or a built-in set's name,
    :class:`~mitsuba_manifold.data.database.Database`); InputError naming ``name`` for a folder
    that is missing, unreadable or holds no table.
    """
    from mitsuba_manifold.data.database import SOURCES_NAME, Database, split_spec
    from mitsuba_manifold.data.merl import table_names
    from mitsuba_manifold.data.sources import EXTENSIONS, SET_NAMES
    from mitsuba_manifold.errors import MitsubaManifoldError

    def _other_kinds(path):
        return any(
            f == SOURCES_NAME or (f.endswith(EXTENSIONS) and not f.endswith(".binary"))
            for f in os.listdir(path)
        )

    base, _ = split_spec(folder)
    if base not in SET_NAMES and not os.path.isdir(base):
        raise InputError(
            f"{name}: database folder {folder} does not exist (built-in databases: "
            f"{', '.join(SET_NAMES)})"
            if not os.path.exists(base)
            else f"{name}: {folder} is not a folder (give a folder of measured tables or a built-in "
            f"database: {', '.join(SET_NAMES)})"
        )
    try:
        if base not in SET_NAMES and not _other_kinds(
            base
        ):  # .binary files only: named, not read yet
            names = table_names(base)
        else:
            names = list(Database(folder).names)
    except OSError as e:
        raise InputError(
            f"{name}: database folder {folder} cannot be read ({e.strerror or e})"
        ) from None
    except MitsubaManifoldError as e:
        raise InputError(f"{name}: {e}") from None
    if not names:
        raise InputError(f"{name}: database folder {folder} holds no tables")
    return names


def known(name, values, choices, what):
    """``values`` (a list of names) if each is one of ``choices``; else InputError with a did-you-mean."""
    if values is None:
        return None
    unknown = [v for v in values if v not in choices]
    if unknown:
        listed = (
            f"choose from {', '.join(choices)}"
            if len(choices) <= 20
            else f"{len(choices)} are known"
        )
        raise InputError(
            f"{name}: unknown {what} {unknown[0]!r}{did_you_mean(unknown[0], choices)}; {listed}"
        )
    if not values:
        raise InputError(f"{name} is empty; give at least one {what}")
    return list(values)


def fold_numbers(values, name="`folds`", n=None):
    """``values`` as a list of fold numbers, each in ``0 .. FOLDS - 1``; with ``n`` materials
    (fewer than :data:`FOLDS`), only the first ``n`` folds hold one.
    """
    if values is None:
        return None
    values = list(values)
    top = FOLDS if n is None else min(FOLDS, n)
    bad = [v for v in values if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < top]
    if bad or not values:
        why = (
            f"folds are numbered 0 to {FOLDS - 1} (the {FOLDS} folds of the held-out fidelity)"
            if top == FOLDS
            else f"with {n} materials only folds 0 to {top - 1} hold a material"
        )
        raise InputError(
            f"{name} {bad[0] if bad else values!r} is not allowed: {why}, e.g. {name} 0,{top - 1}"
        )
    return values


def check(  # noqa: PLR0913  the keywords of the benchmarks' run, as given
    which,
    folder,
    *,
    database_given=True,
    manifold=None,
    basis=None,
    names=None,
    configs=None,
    presets=None,
    folds=None,
    res=None,
    config_choices=(),
):
    """Check the inputs of benchmark ``which`` (``tools/bench.py`` passes what its options give;
    the keywords are those of the benchmarks' ``run``). ``folder`` is the database (the basis
    for ``explore``); with ``database_given`` false it is made later, so only its names are checked
    (against the built-in materials). ``config_choices``: the configurations ``configs`` may
    name (the benchmark's ``CONFIGS``).
    """
    m = manifold_file(manifold) if manifold else None
    if basis:
        basis_folder(basis, m)
    available = _available(which, folder, database_given)
    if names is not None and available is not None:
        known("`names`", names, available, "material")
    if configs is not None:
        known("`configs`", configs, list(config_choices), "configuration")
    if presets is not None:
        from mitsuba_manifold.manifold.presets import PRESETS

        known("`presets`", presets, list(PRESETS), "preset")
    materials = len(names or available or ()) or None  # unknown (None) where no database is read
    fold_numbers(folds, n=materials if which == "space" else None)
    if res is not None:
        positive_int("`res`", res, 128)


def _available(which, folder, database_given):
    """Materials of the database ``folder`` (the built-in ones where it is made later), or None
    where the benchmark takes no database (explore) or makes its own when it holds none.
    """
    if which in ("explore", "scaling", "match-render", "measured-space"):
        return None
    if database_given:
        return database_names(folder)
    from mitsuba_manifold.data.database import load_sgd_fits

    return list(load_sgd_fits())

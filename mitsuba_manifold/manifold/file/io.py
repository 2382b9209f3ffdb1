"""The saved manifold: a ``.npz`` file (no pickle) with a JSON ``meta`` entry and arrays.

The fit's :class:`~.fit_record.FitRecord` is stored as the ``meta`` entry's ``info`` dict and the
``history`` array. The ``meta`` entry is declared by :class:`.schema.ManifoldMeta`, with its
versions and the upgrade from each earlier one (version 1 reads as the paper's GP interpolant on
its stored ``l`` and ``mu``; version 3 adds ``added``, the provenance of materials added after
the fit, whose tables are files outside the database folder: a manifold without added materials
is written as version 2); the arrays by :data:`.schema.ARRAYS` (``table_gram`` and ``cos_gram``
are optional: this reader computes them from the tables when a file lacks them). Anything
unreadable fails with a message that names the file and the field, and says to refit.
"""

import json
import os
import zipfile

import numpy as np

from ..._util.atomic import atomic_replace
from ...errors import FormatError, InputError
from . import schema
from .fit_record import FitRecord
from .shipped import SHIPPED, resolve_manifold

FORMAT = "mitsuba-manifold"
FORMAT_VERSION = schema.ManifoldMeta.VERSION
#: Arrays derived from the tables (optional: computed from them on first use when absent).
DERIVED = ("albedos", "gram", "table_gram", "cos_gram")


def _not_a_manifold(path, why):
    return FormatError(
        f"{path} is not a manifold .npz written by fit_manifold ({why}); give the "
        "file that tools/fit_manifold.py or Manifold.save wrote"
    )


def write(m, path):
    """Write manifold ``m`` to ``path`` atomically, and only when what is written reads back:
    the new file is read and checked (:func:`read`, every field against :mod:`.schema`) before
    it replaces ``path``, so a readable manifold file is never replaced by one nothing can read
    (:class:`FormatError` naming ``path`` and the field; the existing file is kept).
    """
    meta = schema.ManifoldMeta.of(m)
    arrays = {"latent": m.latent, "history": m.history, "meta": np.array(json.dumps(meta))}
    for name in DERIVED:
        if getattr(m, name) is not None:
            arrays[name] = getattr(m, name)
    path = os.fspath(path)

    def checked(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        try:
            read(tmp)
        except InputError as e:
            why = str(e).replace(tmp, path).removeprefix(path + ": ").split("; refit")[0]
            kept = "the file there is unchanged" if os.path.exists(path) else "nothing written"
            raise FormatError(
                f"manifold not saved to {path}: it would not be readable ({why}); {kept}"
            ) from None

    atomic_replace(path, checked)


def read(path):
    """The keyword arguments of ``Manifold(...)`` stored in ``path``, every field checked
    against the schema (:mod:`.schema`) before it is used.
    """
    path = resolve_manifold(path)
    if not os.path.exists(path):
        raise InputError(
            f"manifold file {path} does not exist (the shipped manifolds, by name: "
            f"{', '.join(SHIPPED)})"
        )
    if os.path.isdir(path) or not zipfile.is_zipfile(path):
        raise _not_a_manifold(path, "a folder" if os.path.isdir(path) else "not an .npz archive")
    try:
        with zipfile.ZipFile(path) as zf:
            if "meta.npy" not in zf.namelist():
                raise _not_a_manifold(path, "an .npz without the manifold's 'meta' entry")
            try:
                meta = schema.read_meta(path, zf)
            except FormatError as e:
                raise _not_a_manifold(
                    path, f"unreadable: {str(e).removeprefix(path + ': ').split(';')[0]}"
                ) from None
            if not isinstance(meta, dict) or meta.get("format") != FORMAT:
                raise _not_a_manifold(path, "its 'meta' entry is not a mitsuba-manifold one")
            meta = schema.ManifoldMeta.upgrade(meta)
            schema.ManifoldMeta.checked(meta, path)
            arrays = schema.read_arrays(path, zf, meta)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        if isinstance(e, InputError):
            raise
        raise _not_a_manifold(path, f"damaged: {type(e).__name__}: {e}") from None
    info = dict(meta.get("info") or {})
    info.setdefault("preset", "custom")
    return {
        "names": meta["names"],
        "latent": arrays["latent"],
        "database": meta["database"],
        "hashes": meta["hashes"],
        "length_scale": meta["length_scale"],
        "noise": meta["noise"],
        "features": meta["features"],
        "albedos": arrays.get("albedos"),
        "gram": arrays.get("gram"),
        "record": FitRecord.from_info(info, arrays.get("history", ())),
        "interpolant": meta["interpolant"],
        "table_gram": arrays.get("table_gram"),
        "cos_gram": arrays.get("cos_gram"),
        "added": meta.get("added"),
    }


def check_save_path(out, what="`out`") -> None:
    """Raise :class:`InputError` unless ``out`` names a ``.npz`` file (the manifold's format),
    suggesting the name to use.
    """
    folder, base = os.path.split(out)
    if not base.lower().endswith(".npz") or len(base) <= 4:
        fix = os.path.join(folder, (os.path.splitext(base)[0].lstrip(".") or "manifold") + ".npz")
        raise InputError(
            f"{what} must name a .npz file (the manifold is saved as NumPy .npz), got {out!r}: "
            f"use {what} {fix}"
        )

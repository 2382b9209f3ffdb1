"""The saved manifold: a ``.npz`` file (no pickle) with a JSON ``meta`` entry and arrays.

The fit's :class:`~.record.FitRecord` is stored as the ``meta`` entry's ``info`` dict and the
``history`` array, the layout of every release so far.

Version 2 adds the interpolant's parameters and the raw tables' Gram matrix (exact pruning
errors); files of this release add ``cos_gram``, the cosine-weighted Gram matrix of the
"image" pruning rule, an optional array that readers of earlier version-2 files ignore and
that this reader computes from the tables when a file lacks it. Version 1 files (the
previous release) read as the paper's GP interpolant on their stored ``l`` and ``mu``,
what they were used with; anything unreadable fails with a message that names the file
and says to refit.
"""

import json
import os
import zipfile

import numpy as np

from .._util.atomic import atomic_write
from .record import FitRecord
from ..errors import InputError

FORMAT = "mitsuba-manifold"
FORMAT_VERSION = 2
_REFIT = "refit it with tools/fit_manifold.py"
#: Arrays derived from the tables (optional: computed from them on first use when absent).
DERIVED = ("albedos", "gram", "table_gram", "cos_gram")


def _not_a_manifold(path, why):
    return InputError(f"{path} is not a manifold .npz written by fit_manifold ({why}); give the "
                      "file that tools/fit_manifold.py or Manifold.save wrote")


def write(m, path):
    """Write manifold ``m`` to ``path`` atomically."""
    meta = {"format": FORMAT, "version": FORMAT_VERSION, "names": m.names, "database": m.database,
            "hashes": m.hashes, "length_scale": m.length_scale, "noise": m.noise, "features": m.features,
            "info": m.info, "interpolant": m.interpolant.params()}
    arrays = {"latent": m.latent, "history": m.history, "meta": np.array(json.dumps(meta))}
    for name in DERIVED:
        if getattr(m, name) is not None:
            arrays[name] = getattr(m, name)
    atomic_write(os.fspath(path), lambda f: np.savez(f, **arrays))


def read(path):
    """The keyword arguments of ``Manifold(...)`` stored in ``path``."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"manifold file {path} does not exist")
    if os.path.isdir(path) or not zipfile.is_zipfile(path):
        raise _not_a_manifold(path, "a folder" if os.path.isdir(path) else "not an .npz archive")
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files if k != "meta"}
    except KeyError:
        raise _not_a_manifold(path, "an .npz without the manifold's 'meta' entry") from None
    except ValueError as e:  # object arrays are never unpickled; their message would invite it
        why = "it holds Python objects, which are never loaded" if "pickle" in str(e) else str(e)
        raise _not_a_manifold(path, f"unreadable: {why}") from None
    except Exception as e:  # zipfile and json errors mean a damaged file
        raise _not_a_manifold(path, f"damaged: {type(e).__name__}: {e}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise _not_a_manifold(path, "its 'meta' entry is not a mitsuba-manifold one")
    version = meta.get("version", 0)
    if not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
        raise InputError(f"{path}: format version {version!r} is not one this package reads "
                            f"(1 to {FORMAT_VERSION}); {_REFIT}")
    try:
        info = dict(meta.get("info") or {})
        info.setdefault("preset", "paper" if version < 2 else "custom")
        kwargs = {"names": meta["names"], "latent": arrays["latent"], "database": meta["database"],
                  "hashes": meta["hashes"], "length_scale": meta["length_scale"], "noise": meta["noise"],
                  "features": meta["features"], "albedos": arrays.get("albedos"), "gram": arrays.get("gram"),
                  "record": FitRecord.from_info(info, arrays.get("history", ())),
                  "interpolant": meta["interpolant"] if version >= 2 else {"kind": "gp", "exact": True},
                  "table_gram": arrays.get("table_gram"), "cos_gram": arrays.get("cos_gram")}
    except KeyError as e:
        raise InputError(f"{path}: missing field {e}; {_REFIT}") from None
    for name in DERIVED:   # derived arrays: a damaged one would go unnoticed
        a = kwargs[name]
        if a is not None and (a.dtype.kind not in "fiu" or not np.isfinite(a).all()):
            raise InputError(f"{path}: its {name} array is damaged (not finite numbers); {_REFIT}")
    return kwargs

"""The schema of a saved manifold (:mod:`.io`): every field's type, shape, dtype and range.

A manifold ``.npz`` holds a JSON ``meta`` entry (:data:`META`) and arrays (:data:`ARRAYS`).
:func:`read_checked` reads one without trusting it: the zip directory's entry sizes and each
``.npy`` header (dtype, shape) are checked before an entry is read, so an entry larger than
its shape allows (a few MB of zeros that inflate to gigabytes) is refused unread and only
the entries named here are read at all; then each value is checked against its row of the
tables below. Every refusal is one :class:`~mitsuba_manifold.errors.FormatError` line
naming the file and the field.

Beyond types and shapes: names are distinct, hashes are SHA-256 hex digests, two latent
points of different tables do not coincide (a coincident pair would share the weight of
either material), and the Gram matrices (``table_gram``, ``cos_gram``) are what a Gram matrix
is: symmetric, positive semi-definite, with a positive diagonal (a zero or negative one made
pruning keep the wrong material). That they are the Gram matrices *of the tables the file
names* is checked when the tables are read (:func:`check_grams`, by random probes).
"""

import json
import math
import numbers
import os
import re
from typing import NamedTuple

import numpy as np

from ...data.database import FEATURES
from ...errors import FormatError
from ...gp.kernel import MAX_LATENT_DIM
from ..interpolant import KINDS, MAX_COORDINATE, ShepardWeights

#: Largest ``meta`` entry read (a JSON text: names, hashes, settings), bytes.
META_LIMIT = 64 << 20
#: Largest ``history`` (optimiser iterations) read.
HISTORY_LIMIT = 10**7
#: Bytes an ``.npy`` entry may hold beyond its data (its header).
HEADER_SLACK = 1 << 16
_HEX64 = re.compile(r"[0-9a-f]{64}")


def _real(v):
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def _int(v):
    return isinstance(v, int) and not isinstance(v, bool)


def _texts(v):
    return isinstance(v, list) and all(isinstance(s, str) for s in v)


def _names(v, n):
    if not _texts(v) or not v or not all(v):
        return "must be a non-empty list of non-empty texts"
    return None if len(set(v)) == len(v) else "must not name a material twice"


def _hashes(v, n):
    if not _texts(v) or len(v) != n or not all(_HEX64.fullmatch(h) for h in v):
        return f"must be a list of {n} SHA-256 hex digests (one per name)"
    return None


def _dims(v):
    return v is None or (isinstance(v, list) and len(v) == 3 and all(_int(d) and d >= 1 for d in v))


#: ``info`` entries of known meaning and what each must be (others are kept as they are).
INFO = {
    "method": lambda v: isinstance(v, str),
    "preset": lambda v: isinstance(v, str),
    "q": lambda v: _int(v) and v >= 1,
    "d": lambda v: _int(v) and v >= 1,
    "dims": _dims,
    "n_evaluations": lambda v: _int(v) and v >= 0,
    "log_likelihood": lambda v: (
        v is None or isinstance(v, numbers.Real) and not isinstance(v, bool)
    ),
    "converged": lambda v: v is None or isinstance(v, bool),
    "n_iterations": lambda v: v is None or _int(v) and v >= 0,
    "grad_norm": lambda v: v is None or _real(v) and v >= 0 or v == float("inf"),
    "stop": lambda v: v is None or isinstance(v, str),
    **{
        f"time_{k}_s": (lambda v: v is None or _real(v) and v >= 0) for k in ("load", "gram", "fit")
    },
}


def _info(v, n):
    if v is None:
        return None
    if not isinstance(v, dict):
        return "must be a dict of the fit's record"
    bad = [k for k, ok in INFO.items() if k in v and not ok(v[k])]
    return f"has a bad entry {bad[0]!r}: {v[bad[0]]!r}" if bad else None


def _interpolant(v, n):
    if not isinstance(v, dict) or v.get("kind") not in KINDS:
        return f"must be a dict with a 'kind' of {', '.join(map(repr, KINDS))}"
    if "beyond" in v and v["beyond"] not in ShepardWeights.BEYOND:
        return (
            f"has a 'beyond' of {v['beyond']!r}; one of {', '.join(ShepardWeights.BEYOND)} expected"
        )
    bad = [
        k
        for k, x in v.items()
        if k not in ("kind", "beyond") and not (isinstance(x, bool) if k == "exact" else _real(x))
    ]
    return f"has a parameter {bad[0]!r} that is not a finite number: {v[bad[0]]!r}" if bad else None


def _added(v, n):
    if v is None:
        return None
    if not isinstance(v, list) or len(v) >= n:
        return f"must be a list of fewer than {n} added materials"
    for a in v:
        if not isinstance(a, dict) or not {"name", "source", "path", "hash"} <= set(a):
            return "must hold dicts with 'name', 'source', 'path' and 'hash'"
        if (
            not all(isinstance(a[k], str) for k in ("name", "source", "path", "hash"))
            or not _HEX64.fullmatch(a["hash"])
            or not os.path.isabs(a["path"])
            or not isinstance(a.get("origin"), (str, type(None)))
        ):
            return f"has a bad entry for {str(a.get('name'))[:40]!r} (texts, an absolute path, a SHA-256 hash)"
    return None


class MetaField(NamedTuple):
    """A ``meta`` entry: ``check(value, n)`` returns why it is wrong, or None; ``since``: first
    format version that requires it (None: optional).
    """

    name: str
    check: object
    since: object = 1


#: The ``meta`` entries (``n``: the number of names, checked first).
META = (
    MetaField("version", lambda v, n: None if _int(v) else "must be an integer"),
    MetaField("names", _names),
    MetaField("hashes", _hashes),
    MetaField(
        "database", lambda v, n: None if isinstance(v, str) else "must be a folder's path (text)"
    ),
    MetaField(
        "length_scale", lambda v, n: None if _real(v) and v > 0 else "must be a finite number > 0"
    ),
    MetaField(
        "noise", lambda v, n: None if _real(v) and v >= 0 else "must be a finite number >= 0"
    ),
    MetaField(
        "features", lambda v, n: None if v in FEATURES else f"must be one of {', '.join(FEATURES)}"
    ),
    MetaField("info", _info, None),
    MetaField("interpolant", _interpolant, 2),
    MetaField("added", _added, None),
)


class ArrayField(NamedTuple):
    """An array entry: its shape (``"N"`` the materials, ``"q"`` the latent dimension, None any
    length up to ``limit``), whether it must be present and ``check(array, meta)`` beyond
    real, finite numbers of that shape.
    """

    name: str
    shape: tuple
    required: bool = False
    check: object = None
    limit: int = 0


def _symmetric(a, meta):
    scale = max(float(np.abs(a).max()), np.finfo(float).tiny)
    return None if np.abs(a - a.T).max() <= 1e-9 * scale else "is not symmetric"


def _gram(a, meta):
    """Why ``a`` is not a Gram matrix of non-zero tables, or None."""
    diag = np.diag(a)
    if not (diag > 0).all():
        i = int(np.argmin(diag > 0))
        return f"is not a Gram matrix of tables (diagonal entry {i} is {diag[i]:g}, not > 0)"
    bad = _symmetric(a, meta)
    if bad:
        return bad
    unit = a / np.sqrt(np.outer(diag, diag))  # correlations: |.| <= 1, PSD
    low = float(np.linalg.eigvalsh(0.5 * (unit + unit.T)).min()) if len(a) else 0.0
    if low < -1e-6:
        return f"is not a Gram matrix of tables (not positive semi-definite: eigenvalue {low:.3g})"
    return None


def coincident_latent(latent, hashes, names, length_scale=1.0):
    """``(name_i, name_j)`` of two different tables (other hashes) at one latent point, or None."""
    a = np.asarray(latent, dtype=np.float64)
    d2 = np.sum((a[:, None, :] - a[None, :, :]) ** 2, axis=-1)
    for i, j in np.argwhere(np.triu(d2 <= (1e-9 * float(length_scale)) ** 2, 1)):
        if hashes[i] != hashes[j]:
            return names[i], names[j]
    return None


def _latent(a, meta):
    if not 1 <= a.shape[1] <= MAX_LATENT_DIM:
        return f"must have 1 to {MAX_LATENT_DIM} columns (the latent dimension q), has {a.shape[1]}"
    big = float(np.abs(a).max(initial=0.0))
    if big > MAX_COORDINATE:
        row = int(np.argmax(np.abs(a).max(axis=1)))
        return (
            f"has a coordinate {big:.3g} (point {row}, {meta['names'][row]!r}) beyond "
            f"+-{MAX_COORDINATE:.0e}, where no fit places a material: the file is damaged"
        )
    same = coincident_latent(a, meta.get("hashes"), meta["names"], meta.get("length_scale", 1.0))
    if same:
        return (
            f"has coincident points for the different materials {same[0]!r} and {same[1]!r} "
            f"at its length_scale {float(meta.get('length_scale', 1.0)):.4g} (the weights could "
            "not tell them apart)"
        )
    return None


#: The array entries.
ARRAYS = (
    ArrayField("latent", ("N", "q"), True, _latent),
    ArrayField("history", (None,), limit=HISTORY_LIMIT),
    ArrayField("albedos", ("N", 3)),
    ArrayField("gram", ("N", "N"), check=_symmetric),
    ArrayField("table_gram", ("N", "N"), check=_gram),
    ArrayField("cos_gram", ("N", "N"), check=_gram),
)


def _refuse(path, name, why, kind="field"):
    return FormatError(f"{path}: its {name} {kind} {why}; refit it with tools/fit_manifold.py")


def _header(zf, info):
    """``(shape, dtype)`` from the ``.npy`` header of zip entry ``info`` (nothing else read)."""
    with zf.open(info) as f:
        major, _ = np.lib.format.read_magic(f)
        read = (
            np.lib.format.read_array_header_1_0
            if major == 1
            else np.lib.format.read_array_header_2_0
        )
        shape, _, dtype = read(f)
    return shape, dtype


def _entry(path, zf, name, shape_ok, limit, kinds="fiu"):
    """Array entry ``name`` once its size, header, dtype kind and shape are checked."""
    kind = "entry" if name == "meta" else "array"
    info = zf.getinfo(name + ".npy")
    if info.file_size > limit + HEADER_SLACK:
        raise _refuse(
            path,
            name,
            f"is {info.file_size} bytes, more than its shape allows; it is not read",
            kind,
        )
    try:
        shape, dtype = _header(zf, info)
    except Exception as e:  # noqa: BLE001 -- numpy parses a header with ast and tokenize: any error
        raise _refuse(path, name, f"has a damaged header ({type(e).__name__})", kind) from None
    if dtype.hasobject:
        raise _refuse(path, name, "holds Python objects, which are never loaded", kind)
    if dtype.kind not in kinds:
        what = {"b": "booleans", "c": "complex numbers"}.get(dtype.kind, f"dtype {dtype}")
        raise _refuse(
            path,
            name,
            f"holds {what}, not real numbers" if kinds == "fiu" else f"holds {what}",
            kind,
        )
    why = shape_ok(shape)
    if why:
        raise _refuse(path, name, why, kind)
    if math.prod(shape) * dtype.itemsize > info.file_size:
        raise _refuse(path, name, "is truncated", kind)
    with zf.open(info) as f:
        return np.lib.format.read_array(f, allow_pickle=False)


def read_meta(path, zf):
    """The ``meta`` dict of the manifold archive ``zf`` (a :class:`zipfile.ZipFile` of ``path``;
    its size and header checked, not its fields: :func:`check_meta`).
    """
    shape_ok = lambda s: None if s == () else f"must be one text, has shape {s}"  # noqa: E731
    text = _entry(path, zf, "meta", shape_ok, META_LIMIT, kinds="U")
    try:
        return json.loads(str(text))
    except ValueError as e:
        raise _refuse(path, "meta", f"is not JSON ({e})", "entry") from None
    except RecursionError:
        raise _refuse(
            path, "meta", "is JSON nested too deeply to be a manifold's", "entry"
        ) from None


def _shape_check(field, n, q):
    want = tuple({"N": n, "q": q}.get(s, s) for s in field.shape)

    def ok(shape):
        if len(shape) == len(want) and all(w is None or w == s for w, s in zip(want, shape)):
            return (
                None
                if field.limit == 0 or math.prod(shape) <= field.limit
                else f"is longer than {field.limit}"
            )
        text = ", ".join("any" if w is None else str(w) for w in want)
        return f"must have shape ({text}{',' if len(want) == 1 else ''}), has {tuple(shape)}"

    return ok


def check_meta(path, meta, version):
    """Check every :data:`META` field of ``meta`` (format version ``version``)."""
    n = len(meta["names"]) if _texts(meta.get("names")) else 0
    for field in META:
        if field.name not in meta or (meta[field.name] is None and field.since is None):
            if field.since is not None and version >= field.since:
                raise _refuse(path, field.name, "is missing")
            continue
        why = field.check(meta[field.name], n)
        if why:
            raise _refuse(path, field.name, why)


def read_arrays(path, zf, meta):
    """The :data:`ARRAYS` entries of open archive ``zf`` (checked; absent optional ones left out)."""
    n = len(meta["names"])
    entries = {i.filename[:-4] for i in zf.infolist() if i.filename.endswith(".npy")}
    if "latent" not in entries:
        raise _refuse(path, "latent", "is missing", "array")
    try:
        q = int((_header(zf, zf.getinfo("latent.npy"))[0] or (0,))[-1])
    except Exception as e:  # noqa: BLE001 -- as in _entry
        raise _refuse(
            path, "latent", f"has a damaged header ({type(e).__name__})", "array"
        ) from None
    out = {}
    for field in ARRAYS:
        if field.name not in entries:
            if field.required:
                raise _refuse(path, field.name, "is missing", "array")
            continue
        limit = 8 * (field.limit or n * max(n, q, 3))
        a = _entry(path, zf, field.name, _shape_check(field, n, q), limit)
        if not np.isfinite(a).all():
            raise _refuse(path, field.name, "is damaged (not finite numbers)", "array")
        a = a.astype(np.float64)
        why = field.check(a, meta) if field.check else None
        if why:
            raise _refuse(path, field.name, why, "array")
        out[field.name] = a
    return out


def check_grams(tables, table_gram=None, cos_gram=None, weights=None, seed=0):
    """Why the Gram matrices are not those of ``tables`` ((N, d)): the name of the first that
    is not, or None.

    Freivalds' test: for a random vector ``v``, ``G v`` against ``T (T^T v)`` (``T diag(weights)
    (T^T v)`` for ``cos_gram``): three passes over the tables instead of N^2 d operations, and
    a Gram matrix of other tables fails it with probability 1. Float32 products (the tables
    are not copied), compared within 1e-3 of ``max|G| sum|v|``.
    """
    grams = [
        (n, G)
        for n, G in (("table_gram", table_gram), ("cos_gram", cos_gram))
        if G is not None and (n == "table_gram" or weights is not None)
    ]
    if not grams:
        return None
    v = np.random.default_rng(seed).standard_normal(len(tables))
    tv = v.astype(tables.dtype) @ tables
    for name, G in grams:
        want = tables @ (tv if name == "table_gram" else (tv * weights).astype(tables.dtype))
        if np.abs(G @ v - want).max() > 1e-3 * np.abs(G).max() * np.abs(v).sum():
            return name
    return None

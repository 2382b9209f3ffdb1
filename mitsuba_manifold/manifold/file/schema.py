"""The schema of a saved manifold (:mod:`.io`): every field's type, shape, dtype and range.

A manifold ``.npz`` holds a JSON ``meta`` entry, declared by :class:`ManifoldMeta` (a pydantic
model: its keys, their rules, its versions and the upgrade from each earlier one), and arrays,
declared by :data:`ARRAYS` and checked in code. :func:`~.io.read` reads one without trusting
it: the zip directory's entry sizes and each ``.npy`` header (dtype, shape) are checked before
an entry is read (:func:`read_meta`, :func:`read_arrays`), so an entry larger than its shape
allows (a few MB of zeros that inflate to gigabytes) is refused unread and only the entries
named here are read at all; then each value is checked against its declaration. Every refusal
is one :class:`~mitsuba_manifold.errors.FormatError` line naming the file and the field.

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
from typing import Annotated, ClassVar, Literal, NamedTuple, Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from ..._util.schema import FileSchema
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


_REFIT = "refit it with tools/fit_manifold.py"
Sha256 = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$", description="a SHA-256 hex digest")]
_Count = Annotated[int, Field(ge=0)]
_Seconds = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class _Entry(BaseModel):
    model_config = ConfigDict(strict=True, extra="allow", frozen=True)


class FitInfo(_Entry):
    """The ``info`` entry: the fit's record (:class:`~.fit_record.FitRecord`); the entries of
    known meaning are declared, others kept as they are.
    """

    method: str = Field(None, description="a text (the fitting method)")
    preset: str = Field(None, description="a text (the preset fitted with)")
    q: int = Field(None, ge=1, description="an integer >= 1 (the latent dimension)")
    d: int = Field(None, ge=1, description="an integer >= 1 (the features per table)")
    dims: Optional[
        Annotated[list[Annotated[int, Field(ge=1)]], Field(min_length=3, max_length=3)]
    ] = Field(None, description="three positive integers (the tables' resolution)")
    n_evaluations: int = Field(None, ge=0, description="an integer >= 0")
    log_likelihood: Optional[float] = Field(None, description="a number")
    converged: Optional[bool] = Field(None, description="true or false")
    n_iterations: Optional[_Count] = Field(None, description="an integer >= 0")
    grad_norm: Optional[float] = Field(None, ge=0, description="a number >= 0 (or infinity)")
    stop: Optional[str] = Field(None, description="a text (why the fit stopped)")
    time_load_s: Optional[_Seconds] = Field(None, description="a finite number >= 0 (seconds)")
    time_gram_s: Optional[_Seconds] = Field(None, description="a finite number >= 0 (seconds)")
    time_fit_s: Optional[_Seconds] = Field(None, description="a finite number >= 0 (seconds)")


class Interpolant(_Entry):
    """The ``interpolant`` entry: ``kind`` and its parameters
    (:meth:`~mitsuba_manifold.manifold.interpolant.Interpolant.params`), every other key a finite number.
    """

    kind: Literal[KINDS] = Field(description=f"one of {', '.join(map(repr, KINDS))}")
    beyond: Literal[ShepardWeights.BEYOND] = Field(
        None, description=f"one of {', '.join(map(repr, ShepardWeights.BEYOND))}"
    )
    exact: bool = Field(None, description="true or false")

    @model_validator(mode="after")
    def _numbers(self) -> "Interpolant":
        for k, x in (self.model_extra or {}).items():
            if isinstance(x, bool) or not isinstance(x, numbers.Real) or not math.isfinite(x):
                raise ValueError(f"has a parameter {k!r} that is not a finite number: {x!r}")
        return self


class AddedMaterial(_Entry):
    """One entry of ``added``: a material added after the fit (:mod:`mitsuba_manifold.manifold.adding`)."""

    name: str = Field(description="a text (one of the names)")
    source: str = Field(description="a text (what the table was made from)")
    path: str = Field(description="an absolute path (the table's file)")
    hash: Sha256
    origin: Optional[str] = Field(None, description="a text or null")

    @field_validator("path")
    @classmethod
    def _absolute(cls, v: str) -> str:
        if not os.path.isabs(v):
            raise ValueError(f"must be an absolute path, got {v!r}")
        return v


def _upgrade_1(meta: dict) -> dict:
    """To version 2: the paper's GP interpolant on the stored ``l`` and ``mu`` (what version-1
    files were used with), and the ``paper`` preset.
    """
    info = meta.get("info")
    if info is None or isinstance(info, dict):
        meta["info"] = {**(info or {}), "preset": (info or {}).get("preset", "paper")}
    return {**meta, "version": 2, "interpolant": {"kind": "gp", "exact": True}}


def _upgrade_2(meta: dict) -> dict:
    """To version 3: no ``added`` (no material added after the fit; a version-2 reader
    ignored the key).
    """
    meta.pop("added", None)
    return {**meta, "version": 3}


class ManifoldMeta(FileSchema):
    """The ``meta`` entry of a saved manifold (a JSON text), declared.

    Version 1: no ``interpolant`` (read as the paper's GP interpolant, preset ``paper``);
    version 2 adds ``interpolant``; version 3 adds ``added``, the provenance of materials
    added after the fit (a manifold without them is written as version 2).
    """

    VERSION: ClassVar[int] = 3
    UPGRADES: ClassVar[dict] = {1: _upgrade_1, 2: _upgrade_2}
    VERSIONS: ClassVar[str] = (
        "1: no interpolant; 2: the interpolant; 3: added (a manifold without added materials is "
        "written as version 2)."
    )
    FIX: ClassVar[str] = _REFIT

    format: Literal["mitsuba-manifold"] = Field(description="'mitsuba-manifold'")
    version: int = Field(description="the format version (1 to 3)")
    names: list[str] = Field(
        min_length=1, description="a non-empty list of distinct, non-empty material names"
    )
    hashes: list[Sha256] = Field(description="a list of SHA-256 hex digests, one per name")
    database: str = Field(description="a folder's path or a built-in set's name (text)")
    length_scale: float = Field(gt=0, allow_inf_nan=False, description="a finite number > 0")
    noise: float = Field(ge=0, allow_inf_nan=False, description="a finite number >= 0")
    features: Literal[FEATURES] = Field(description=f"one of {', '.join(FEATURES)}")
    info: Optional[FitInfo] = Field(None, description="an object: the fit's record")
    interpolant: Interpolant = Field(
        description=f"an object with a 'kind' of {' or '.join(map(repr, KINDS))}"
    )
    added: Optional[list[AddedMaterial]] = Field(
        None, description="a list of the materials added after the fit"
    )

    @classmethod
    def of(cls, m: object) -> dict:
        """The ``meta`` JSON object of the manifold ``m`` (keys in the order of every file
        written so far): version 3 when it holds added materials (a version-2 reader refuses a
        file naming tables outside its database), else version 2.
        """
        meta = {
            "format": "mitsuba-manifold",
            "version": cls.VERSION if m.added else 2,
            "names": m.names,
            "database": m.database,
            "hashes": m.hashes,
            "length_scale": m.length_scale,
            "noise": m.noise,
            "features": m.features,
            "info": m.info,
            "interpolant": m.interpolant.params(),
        }
        if m.added:
            meta["added"] = [a.as_dict() for a in m.added]
        return meta

    @field_validator("names")
    @classmethod
    def _distinct(cls, v: list) -> list:
        if not all(v):
            raise ValueError("must hold non-empty material names")
        if len(set(v)) != len(v):
            raise ValueError("must not name a material twice")
        return v

    @model_validator(mode="after")
    def _between_fields(self) -> "ManifoldMeta":
        n = len(self.names)
        if len(self.hashes) != n:
            raise ValueError(
                f"its hashes field must hold one SHA-256 hex digest per entry of its names field "
                f"({len(self.hashes)} hashes, {n} names)"
            )
        added = self.added or ()
        if len(added) >= n:
            raise ValueError(f"its added field must list fewer than {n} added materials")
        index = {name: i for i, name in enumerate(self.names)}
        for a in added:
            i = index.get(a.name)
            if i is None or self.hashes[i] != a.hash:
                raise ValueError(
                    f"its added material {a.name!r} is not one of its names with that table's hash"
                )
        return self


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

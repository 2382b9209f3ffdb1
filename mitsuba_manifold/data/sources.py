"""Where a database's tables come from: one typed *source* per material.

A :class:`~mitsuba_manifold.data.database.Database` is a set of named sources, each able to
make its material's reflectance table at a MERL resolution (``table(dims)``, float32
``(3, n_h, n_d, n_p)``, 0 below the horizon, as :func:`.merl.filled_reflectance` makes tables)
and to name that table by a content hash (``digest(dims)``) without making it:

* :class:`BinaryFile`: a MERL ``.binary`` file (its own resolution only; digest: the file's SHA-256);
* :class:`Network`: an NBRDF network (:mod:`.nbrdf`), the built-in sets' and the authors' ``.h5``;
* :class:`SgdFit`: a Shifted-Gamma fit of a MERL material (:mod:`.surrogate`), the set ``sgd``;
* :class:`MeasuredFile`: a Mitsuba ``measured`` file (``.bsdf``, RGL ``tensor_file`` format),
  isotropic only, resampled on the MERL grid by a reader the rendering subsystem registers
  (:func:`register_reader`; importing ``mitsuba_manifold.render`` does).

:func:`builtin` gives the built-in sets (:data:`BUILTIN`) and :func:`folder_sources` the
sources of a folder, whatever mix of kinds it holds. A material is named after its file,
without the extension and a trailing ``_rgb`` or ``_spec``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .._util.cache import file_hash, key_hash
from ..errors import FormatError, InputError, UnavailableError
from . import merl, nbrdf

__all__ = [
    "BUILTIN",
    "BUILTIN_PREFIX",
    "SET_NAMES",
    "BinaryFile",
    "MeasuredFile",
    "Network",
    "SgdFit",
    "builtin",
    "builtin_set",
    "combine",
    "folder_sources",
    "material_name",
    "material_source",
    "material_table",
    "read_tensor_header",
    "register_reader",
]

#: The built-in sets and what they hold.
BUILTIN = {
    "merl": "the 100 MERL materials (NBRDF fits of the MERL measurements)",
    "rgl": "51 isotropic RGL-EPFL materials (NBRDF fits)",
    "nielsen": "8 materials of Nielsen et al. 2015 (NBRDF fits)",
    "all": "merl, rgl and nielsen together (159; a name shared by sets gets the set as suffix: cardboard-rgl)",
    "sgd": "the Shifted-Gamma (SGD) fits of the 100 MERL materials",
}
SET_NAMES = tuple(BUILTIN)
#: Names a built-in set whatever the current folder holds: ``builtin:merl``.
BUILTIN_PREFIX = "builtin:"
#: File kinds a folder may hold, by extension.
EXTENSIONS = (".binary", ".bsdf", ".h5", ".npz")
#: Suffixes dropped from a file's name to name its material.
NAME_SUFFIXES = ("_rgb", "_spec")

#: Where the networks of each built-in set are tabulated (:data:`nbrdf.POSITIONS`): the MERL
#: networks at the bins' starts, where they were trained on the MERL tables' values, so that
#: they reproduce the tables a user with the real files has; the RGL and Nielsen networks at
#: the centres, where they agree best with the real measurements (``docs/`` has the figures).
#: A user's network (``.h5``, or ``.npz`` recording no positions), trained by the authors' tool on
#: a MERL file: starts.
SET_POSITIONS = {"merl": "starts", "rgl": "centres", "nielsen": "centres"}
USER_POSITIONS = "starts"
#: Sample points per axis of a bin where a measured file is resampled (the rendering
#: subsystem's reader; part of the tables' content hash).
MEASURED_SAMPLES = 2

_READERS: dict = {}


def register_reader(kind, reader) -> None:
    """Register ``reader(path, dims) -> (3,) + dims`` float32 reflectance for the sources of ``kind``
    (``"measured"``: :class:`MeasuredFile`; the rendering subsystem registers Mitsuba's).
    """
    _READERS[kind] = reader


def material_name(path) -> str:
    """A material's name from its file: the base name without extension and ``_rgb`` / ``_spec``."""
    stem = os.path.basename(os.fspath(path))
    stem = stem[: -len(".binary")] if stem.endswith(".binary") else os.path.splitext(stem)[0]
    for suffix in NAME_SUFFIXES:
        if stem.endswith(suffix) and len(stem) > len(suffix):
            return stem[: -len(suffix)]
    return stem


def _resolution(dims) -> str:
    return "x".join(map(str, dims))


# ---------------------------------------------------------------------------- kinds


@dataclass(frozen=True)
class BinaryFile:
    """A MERL ``.binary`` file: its table is the file's, at the file's resolution only."""

    name: str
    path: str
    kind = "binary"

    @property
    def origin(self) -> str:
        return self.path

    def native_dims(self) -> tuple[int, ...]:
        """The file's resolution (its header)."""
        return merl.read_header(self.path)

    def digest(self, dims) -> str:
        """SHA-256 of the file (memoised per process, :func:`cache.file_hash`)."""
        return file_hash(self.path)

    def table(self, dims) -> np.ndarray:
        raw = merl.read_binary(self.path)  # format errors name the file
        if raw.shape[1:] != tuple(dims):
            raise FormatError(
                f"{self.path}: a {_resolution(raw.shape[1:])} table, the database is "
                f"{_resolution(dims)}; remake it at {_resolution(dims)} or use tables of one resolution"
            )
        try:
            return merl.filled_reflectance(raw)
        except ValueError as e:
            raise FormatError(f"{self.path}: {e}") from None


@dataclass(frozen=True)
class Network:
    """An NBRDF network (``key`` in ``networks``), tabulated at ``positions`` (:data:`nbrdf.POSITIONS`)."""

    name: str
    networks: nbrdf.NetworkSet
    key: str
    origin: str
    positions: str = USER_POSITIONS
    kind = "nbrdf"

    def native_dims(self) -> None:
        return None

    def digest(self, dims) -> str:
        return key_hash(
            "nbrdf-table-v1", self.networks.digest(self.key), _resolution(dims), self.positions
        )

    def table(self, dims) -> np.ndarray:
        return nbrdf.tabulate(self.networks, self.key, dims, self.positions)


@dataclass(frozen=True)
class SgdFit:
    """The Shifted-Gamma fit of a MERL material (:func:`.surrogate.tabulate_sgd`)."""

    name: str
    params: tuple  # ((field, (r, g, b)), ...) in SGD_FIELDS order
    kind = "sgd"

    @property
    def origin(self) -> str:
        return "sgd"

    def native_dims(self) -> None:
        return None

    def digest(self, dims) -> str:
        values = np.array([v for _, v in self.params], dtype="<f8")
        return key_hash("sgd-table-v1", values, _resolution(dims))

    def table(self, dims) -> np.ndarray:
        from .surrogate import tabulate_sgd

        params = {k: np.asarray(v, dtype=np.float64) for k, v in self.params}
        return _filled(tabulate_sgd(params, dims), dims)


@dataclass(frozen=True)
class MeasuredFile:
    """A Mitsuba ``measured`` file (``.bsdf``), resampled on the MERL grid at the bins' centres."""

    name: str
    path: str
    kind = "measured"

    @property
    def origin(self) -> str:
        return self.path

    def native_dims(self) -> None:
        return None

    def digest(self, dims) -> str:
        return key_hash(
            "measured-table-v2", file_hash(self.path), _resolution(dims), str(MEASURED_SAMPLES)
        )

    def check(self) -> MeasuredFile:
        """Refuse a file that is not an isotropic ``tensor_file`` (before any work)."""
        fields = read_tensor_header(self.path)
        if "phi_i" not in fields or "theta_i" not in fields:
            raise FormatError(
                f"{self.path}: a tensor_file without phi_i/theta_i fields, not a Mitsuba "
                "`measured` BSDF; give an RGL-EPFL .bsdf file"
            )
        n_phi = int(np.prod(fields["phi_i"][1]))
        if n_phi != 1:
            raise FormatError(
                f"{self.path}: an anisotropic measurement ({n_phi} incident azimuths); MERL tables "
                "are isotropic, so only isotropic measured files can be imported: use the "
                "material's isotropic file or leave this one out"
            )
        return self

    def table(self, dims) -> np.ndarray:
        reader = _READERS.get(self.kind)
        if reader is None:
            raise UnavailableError(
                f"{self.path}: reading Mitsuba measured files needs Mitsuba: import "
                "mitsuba_manifold.render first (the command-line tools do)"
            )
        return reader(self.path, tuple(dims))


def _filled(raw, dims) -> np.ndarray:
    """Reflectance of stored values measured in every bin above the horizon (tabulated ones)."""
    above = merl.above_horizon(tuple(dims))
    refl = merl.reflectance(raw, dtype=np.float32)
    return np.where(above, np.maximum(refl, 0.0), np.float32(0.0)).astype(np.float32)


# -------------------------------------------------------------------- tensor files

_TYPES = {
    1: "u1",
    2: "i1",
    3: "<u2",
    4: "<i2",
    5: "<u4",
    6: "<i4",
    7: "<u8",
    8: "<i8",
    9: "<f2",
    10: "<f4",
    11: "<f8",
}


def read_tensor_header(path) -> dict[str, tuple[str, tuple[int, ...], int]]:
    """Fields of a Mitsuba ``tensor_file``: ``{name: (dtype, shape, offset)}`` (the header only),
    after checking that the file holds every field the header describes (offset + size).
    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError as e:
        raise FormatError(f"{path}: cannot be read ({e.strerror or e})") from None
    if not head.startswith(b"tensor_file\0") or len(head) < 18:
        raise FormatError(
            f"{path}: not a Mitsuba tensor_file (a measured .bsdf starts with 'tensor_file')"
        )
    pos = 14
    count = int.from_bytes(head[pos : pos + 4], "little")
    pos += 4
    fields = {}
    try:
        for _ in range(count):
            n = int.from_bytes(head[pos : pos + 2], "little")
            name = head[pos + 2 : pos + 2 + n].decode()
            pos += 2 + n
            ndim = int.from_bytes(head[pos : pos + 2], "little")
            dtype = _TYPES[head[pos + 2]]
            offset = int.from_bytes(head[pos + 3 : pos + 11], "little")
            pos += 11
            shape = tuple(
                int.from_bytes(head[pos + 8 * k : pos + 8 * k + 8], "little") for k in range(ndim)
            )
            pos += 8 * ndim
            fields[name] = (dtype, shape, offset)
    except (KeyError, UnicodeDecodeError, IndexError):
        raise FormatError(f"{path}: a damaged tensor_file header") from None
    needs = (
        max(
            (off + int(np.prod(shape, dtype=np.int64)) * np.dtype(dt).itemsize)
            for dt, shape, off in fields.values()
        )
        if fields
        else 0
    )
    size = os.path.getsize(path)
    if size < needs:
        raise FormatError(
            f"{path}: file is truncated ({size} bytes; its header needs {needs}): copy or "
            "download it again"
        )
    return fields


# ------------------------------------------------------------------------- sets


def _network_sources(path, prefix, origin) -> list:
    nets = nbrdf.NetworkSet.load(path, prefix)
    return [Network(n, nets, n, origin, SET_POSITIONS[prefix]) for n in nets.names]


def builtin_set(name, *, recorded=False, what="database") -> str | None:
    """The built-in set (:data:`SET_NAMES`) that the name ``name`` means, or None when it means a
    path: the one rule by which every database name is read.

    * ``builtin:NAME`` (:data:`BUILTIN_PREFIX`) is always the set ``NAME`` (an unknown one is
      refused, naming the sets);
    * a bare set name (``merl``) is the set, unless a file or folder of that name exists in the
      current folder: then the name is ambiguous and refused (:class:`InputError` naming both and
      how to say each: ``./merl`` for the folder, ``builtin:merl`` for the set). Where the name
      was recorded by this package (``recorded``: a manifold's database, a ``sources.json``
      entry), folders are absolute paths, so a bare set name there is always the set;
    * anything else is a path (None).

    ``what`` names the name's role in the messages (``"database"``, ``"--database"``).
    """
    name = os.fspath(name)
    if name.startswith(BUILTIN_PREFIX):
        set_name = name[len(BUILTIN_PREFIX) :]
        if set_name not in SET_NAMES:
            raise InputError(
                f"{what} {name!r}: no built-in set {set_name!r}; the built-in sets are "
                f"{', '.join(BUILTIN_PREFIX + n for n in SET_NAMES)}"
            )
        return set_name
    if name not in SET_NAMES:
        return None
    if not recorded and os.path.lexists(name):
        kind = "folder" if os.path.isdir(name) else "file"
        raise InputError(
            f"{what} {name!r} is ambiguous: the built-in set {name} ({BUILTIN[name]}) and the "
            f"{kind} {os.path.abspath(name)}; say ./{name} for the {kind} or "
            f"{BUILTIN_PREFIX}{name} for the set"
        )
    return name


def builtin(name) -> list:
    """The sources of a built-in set (:data:`BUILTIN`), in the set's order."""
    if name == "sgd":
        from .surrogate import SGD_FIELDS, load_sgd_fits

        return [
            SgdFit(n, tuple((k, tuple(float(x) for x in p[k])) for k in SGD_FIELDS))
            for n, p in load_sgd_fits().items()
        ]
    if name == "all":
        return combine({s: builtin(s) for s in nbrdf.SETS})
    if name in nbrdf.SETS:
        return _network_sources(nbrdf.WEIGHTS_PATH, name, name)
    raise InputError(
        f"unknown built-in database {name!r}; the built-in ones are {', '.join(SET_NAMES)}"
    )


def combine(groups) -> list:
    """One list of the sources of ``groups`` ({label: sources}, in order), names made unique.

    A name given by more than one group is suffixed ``-<label>`` in each of them
    (``cardboard-rgl``, ``cardboard-nielsen``) when every such group is a built-in set; a
    clash involving a user's files is refused, naming both files.
    """
    seen: dict = {}
    for label, sources in groups.items():
        for s in sources:
            seen.setdefault(s.name, []).append((label, s))
    out = []
    for label, sources in groups.items():
        for s in sources:
            owners = seen[s.name]
            if len(owners) == 1:
                out.append(s)
                continue
            if not all(lab in SET_NAMES for lab, _ in owners):
                a, b = owners[0][1].origin, owners[1][1].origin
                raise FormatError(
                    f"two materials are named {s.name!r} ({a} and {b}); rename one of the files "
                    "(a material is named after its file)"
                )
            out.append(_renamed(s, f"{s.name}-{label}"))
    return out


def _renamed(source, name):
    from dataclasses import replace

    return replace(source, name=name)


def folder_sources(folder) -> list:
    """The sources of the files in ``folder``, sorted by name: ``.binary``, ``.bsdf``, ``.h5``
    (with its ``.json``) and ``.npz`` networks (one network: named after the file; a set: by the
    names it stores). Hidden files are skipped; two files naming one material are refused.
    """
    folder = os.fspath(folder)
    found = []
    for f in sorted(os.listdir(folder)):
        path = os.path.join(folder, f)
        if f.startswith(".") or not os.path.isfile(path):
            continue
        if f.endswith(".binary"):
            found.append(BinaryFile(f[: -len(".binary")], path))
        elif f.endswith(".bsdf"):
            found.append(MeasuredFile(material_name(f), path).check())
        elif f.endswith(".h5"):
            nets = nbrdf.read_keras(path, name=material_name(f))
            found.append(Network(nets.names[0], nets, nets.names[0], path, USER_POSITIONS))
        elif f.endswith(".npz"):
            for prefix in nbrdf.NetworkSet.prefixes(path):
                nets = nbrdf.NetworkSet.load(path, prefix)
                at = nbrdf.NetworkSet.positions(path, prefix, USER_POSITIONS)
                if len(nets) == 1:
                    found.append(Network(material_name(f), nets, nets.names[0], path, at))
                else:
                    found.extend(Network(n, nets, n, path, at) for n in nets.names)
    names: dict = {}
    for s in found:
        if s.name in names:
            raise FormatError(
                f"{folder}: two files give the material {s.name!r} ({names[s.name].origin} and "
                f"{s.origin}); keep one of them"
            )
        names[s.name] = s
    return [names[n] for n in sorted(names)]


def material_source(spec) -> BinaryFile | MeasuredFile | Network:
    """The source of one material: ``SET:NAME`` of a built-in set (``rgl:paper_white``) or a file
    (``.binary``, ``.bsdf``, ``.h5`` with its ``.json``, or an ``.npz`` of one network).
    """
    spec = os.fspath(spec)
    head, sep, tail = spec.partition(":")
    if sep and head in SET_NAMES and not os.path.exists(spec):
        found = {s.name: s for s in builtin(head)}
        if tail not in found:
            from ..errors import UnknownMaterialError, did_you_mean

            raise UnknownMaterialError(
                f"built-in database {head!r} has no material {tail!r}"
                f"{did_you_mean(tail, list(found))}"
            )
        return found[tail]
    if os.path.isdir(spec):
        raise InputError(
            f"material {spec} is a folder, not a file: give one .binary, .bsdf, .h5 or .npz "
            "file (a folder of them is a database: give it where a database is expected)"
        )
    if not os.path.isfile(spec):
        from ..errors import MissingFileError

        raise MissingFileError(
            f"material {spec}: no such file (give a .binary, .bsdf, .h5 or .npz file, "
            f"or SET:NAME of a built-in database: {', '.join(SET_NAMES)})"
        )
    name = material_name(spec)
    if spec.endswith(".binary"):
        return BinaryFile(name, spec)
    if spec.endswith(".bsdf"):
        return MeasuredFile(name, spec).check()
    if spec.endswith(".h5"):
        nets = nbrdf.read_keras(spec, name=name)
        return Network(name, nets, name, spec, USER_POSITIONS)
    if spec.endswith(".npz"):
        prefixes = nbrdf.NetworkSet.prefixes(spec)
        nets = [nbrdf.NetworkSet.load(spec, p) for p in prefixes]
        if sum(len(n) for n in nets) != 1:
            raise FormatError(
                f"{spec}: holds {sum(len(n) for n in nets)} networks; give a file of one network "
                "(or use the file as a database folder's)"
            )
        at = nbrdf.NetworkSet.positions(spec, prefixes[0], USER_POSITIONS)
        return Network(name, nets[0], nets[0].names[0], spec, at)
    raise FormatError(f"{spec}: not a material file (.binary, .bsdf, .h5 or .npz)")


def material_table(spec, dims=None, *, what="material") -> tuple:
    """The source of ``spec`` (:func:`material_source`: a file or ``SET:NAME``) and its reflectance
    table ``(3,) + dims`` float32 at ``dims`` (default: the file's own resolution, a ``.binary``'s).

    Errors keep their class and start with ``what`` (``"table to project"``), except a measured
    file read without Mitsuba's reader registered (:class:`UnavailableError`, whose message says
    to import ``mitsuba_manifold.render``).
    """
    from ..errors import MitsubaManifoldError, one_line

    try:
        source = material_source(spec)
        dims = source.native_dims() if dims is None else tuple(dims)
        if dims is None:
            raise InputError(
                f"{os.fspath(spec)}: has no resolution of its own; give the resolution to tabulate it at"
            )
        return source, source.table(dims)
    except UnavailableError:
        raise
    except MitsubaManifoldError as e:
        raise type(e)(f"{what}: {one_line(e)}") from None

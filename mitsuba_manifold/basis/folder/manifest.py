"""The basis folder's format: its ``manifest.json``, image keys and the identities of scene and manifold.

A *basis* holds the images that blending combines (paper Sec. 5.2, Eq. 13, and Sec. 6):
with one manifold material (*target*) in the scene, ``base`` (the paths that never touch
it) and one image per measured material ``i`` (the paths that touch it exactly once,
rendered with material ``i``); with ``p`` targets, the full ``L1-`` image of every
combination of one material per target (:mod:`mitsuba_manifold.basis.blend` combines them).

A *basis folder* holds those images as float32 EXR files and a ``manifest.json``::

    {"format": "mitsuba-manifold-basis", "version": 2,
     "scene": abs path, "scene_hash": sha256, "manifold": abs path, "manifold_hash": sha256,
     "resolution": [width, height], "spp": int, "variant": str, "seed": int, "max_depth": int,
     "mode": "per-material" | "onepass", "targets": [bsdf id, ...],
     "sensor": int (the scene's sensor rendered; absent in manifests of earlier versions, which
               rendered sensor 0 unless they say otherwise),
     "chunks": int (optional: merged from k chunks),
     "pending": ["<key>.exr", ...] (optional: being written; see render_basis),
     "images": {"base": {"file": "base.exr", "time_s": float, "sha256": hex (of the file's bytes;
                         absent in manifests that do not record it)},
                "<material>": {"file": "<material>.exr", "time_s": float}, ...},
     optional, one-pass bases of one target:
     "components": ["l1"] | ["l1", "l2+"] | ["l1", "l2+", "cross"] (what the basis holds; a
        manifest without it is an older L1- basis), "levels": int (most vertices on the
        material per path in the L2+ images; paths touching it more often are left out),
     "gi_images": {"<material>": {"file": "<material>.gi.exr", "time_s": float}, ...}
        (``touch + L2+``: ``base + gi_images[i]`` is material i's full-GI image),
     "cross": {"file": "cross.npz", "pairs": int, "tol": float} (the cross terms ``C_ij``,
        float16, of the pairs of :mod:`mitsuba_manifold.basis.crossterms`),
     "left_out": {"l2+" | "cross": "why"}, "gi_stats": {...} (measurements of the render),
     optional, what loading the scene again needs:
     "integrator": {...} (the scene's integrator settings rendered with), "scene_resolution":
        [width, height] or null (the resolution the scene was loaded with; null: its own film
        size; absent: the image size),
     and keys the format leaves to the jobs that write it (kept and written back as they are:
     a chunked render's marks, :class:`mitsuba_manifold.render.jobs.chunks.ChunkMark`)}

With one target the keys are ``base`` and material names; with ``p`` targets they are
``"<matA>+<matB>..."`` (one name per target, in target order). From version 2 on, each
material name in a key is escaped (:func:`mitsuba_manifold._util.names.escape`: ``gold-paint``
stays, ``base`` or ``a+b`` cannot collide with the base image or the separator) and the
file is ``<key>.exr``; ``manifold_hash`` is the manifold's content identity
(:func:`mitsuba_manifold.manifold.file.identity.manifold_identity`), so an identical refit is accepted.
Version 1 manifests (raw names, SHA-256 of the manifold file) are still read.
``scene_hash`` is the SHA-256 of the scene XML and the files it names (:func:`scene_hash`).
:class:`ManifestSchema` declares the JSON object (every key, its type and rule, the versions);
:class:`Manifest` alone reads, writes and checks the format (the renderers make one with
:meth:`Manifest.new`, change its fields and :meth:`Manifest.write` it; its image entries are
:class:`ImageEntry`, its cross terms a :class:`CrossEntry`);
:class:`~mitsuba_manifold.basis.folder.Basis` opens a folder and its images,
:mod:`mitsuba_manifold.basis.folder.owned_files` says which files a basis folder owns, and
:func:`mitsuba_manifold.basis.blend.blend` and :func:`~mitsuba_manifold.basis.blend.blend_path` combine the images.
"""

import copy
import dataclasses
import enum
import hashlib
import json
import os
import warnings
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..._util import names as names_mod
from ..._util.atomic import write_bytes
from ..._util.cache import file_hash
from ..._util.checks import scene_xml
from ..._util.schema import FileSchema
from ...errors import MismatchError
from ...manifold.file.identity import manifold_identity
from ...manifold.file.shipped import resolve_manifold

FORMAT = "mitsuba-manifold-basis"
FORMAT_VERSION = 2
MANIFEST = "manifest.json"
BASE = "base"
#: Joins one material name per target into an image key (multilinear bases).
SEP = "+"
MODES = ("per-material", "onepass")


# ------------------------------------------------------------------ hashes


def _named(scene):
    """``(value, is_include)`` of each file the scene XML ``scene`` names (``$parameters`` skipped)."""
    out = []
    for el in scene_xml(scene).iter():  # a scene XML, or an error naming the file
        value = (
            el.get("filename")
            if el.tag == "include"
            else (el.get("value") if el.get("name") == "filename" else None)
        )
        if value and "$" not in value:
            out.append((value, el.tag == "include"))
    return out


def scene_files(scene):
    """Files a scene XML names (``filename`` properties and ``<include>``), resolved
    against the scene's folder; values holding ``$parameters`` are skipped.
    """
    folder = os.path.dirname(os.path.abspath(os.fspath(scene)))
    return [(v, os.path.join(folder, v)) for v, _ in _named(os.fspath(scene))]


#: Deepest chain of ``<include>`` files followed by :func:`scene_hash`.
MAX_INCLUDE_DEPTH = 16


def _hash_included(h, xml, folders, seen):
    """Add to ``h`` the name and bytes of every file the included XML ``xml`` names, found
    beside the main scene or beside ``xml`` (Mitsuba resolves them against either), and of
    the files the XML files it includes name, recursively; ``seen``: the XML files already
    followed (each once: no cycle, no exponential fan-out).
    """
    if os.path.realpath(xml) in seen or len(folders) > MAX_INCLUDE_DEPTH:
        return
    seen.add(os.path.realpath(xml))
    try:
        named = _named(xml)
    except MismatchError:  # not a scene XML: its bytes are hashed, Mitsuba refuses it
        return
    folders = folders + [os.path.dirname(os.path.abspath(xml))]
    for value, include in named:
        h.update(b"\1" + value.encode())
        found = list(
            dict.fromkeys(p for p in (os.path.join(f, value) for f in folders) if os.path.isfile(p))
        )
        for path in found:
            h.update(b"\1" + file_hash(path).encode())
        if include and found:
            _hash_included(h, found[-1], folders, seen)


def scene_hash(scene):
    """SHA-256 (hex) of a scene: its XML bytes, then the name and bytes of every file it
    names (:func:`scene_files`) that exists beside it, and for each ``<include>``d XML the
    files that one names, recursively (:func:`_hash_included`). Meshes, environment maps and
    included scenes are thereby part of the scene's identity; the manifold (a ``$manifold``
    parameter) is not. A scene without includes hashes as its XML and named files alone.
    """
    scene = os.fspath(scene)
    if not os.path.isfile(scene):
        raise MismatchError(f"scene {scene} does not exist")
    h = hashlib.sha256()
    with open(scene, "rb") as f:
        h.update(f.read())
    folder = os.path.dirname(os.path.abspath(scene))
    for value, include in _named(scene):
        path = os.path.join(folder, value)
        h.update(b"\0" + value.encode())
        if os.path.isfile(path):
            h.update(b"\0" + file_hash(path).encode())
            if include:
                _hash_included(h, path, [folder], {os.path.realpath(scene)})
    return h.hexdigest()


# ---------------------------------------------------------------- manifest


def image_key(materials, version=FORMAT_VERSION):
    """Image key of one material per target: ``"a"`` or ``"a+b"``, names escaped
    (:func:`names.escape`) from format version 2 on; the image file is ``<key>.exr``.
    """
    materials = [materials] if isinstance(materials, str) else list(materials)
    if version >= 2:
        return SEP.join(
            names_mod.escape(m) for m in materials
        )  # InputError for a name no file can have
    for m in materials:
        if not m or SEP in m or m == BASE:
            raise MismatchError(
                f"material name {m!r} cannot be used in an image key of a version-1 basis; "
                "render the basis again with this version"
            )
    return SEP.join(materials)


def key_materials(key, version=FORMAT_VERSION):
    """Material names (one per target) of an image key: the inverse of :func:`image_key`."""
    parts = key.split(SEP)
    return [names_mod.unescape(p) for p in parts] if version >= 2 else parts


def image_changed(folder, entry):
    """True when the file of manifest ``entry`` (:class:`ImageEntry` or :class:`CrossEntry`) is
    not the one written (its SHA-256 is recorded and differs: edited in place, replaced); False
    when unchanged or not recorded.
    """
    return (
        entry.sha256 is not None
        and file_hash(os.path.join(os.fspath(folder), entry.file)) != entry.sha256
    )


class _FileEntry:
    """A file a manifest lists, as a JSON object of the keys :data:`KEYS` (those not recorded
    absent) and keys this version does not know (:attr:`extra`).
    """

    KEYS = ()

    @classmethod
    def from_json(cls, data):
        """The entry of a JSON object (checked by :meth:`Manifest.from_json`)."""
        return cls(
            **{k: data[k] for k in cls.KEYS if k in data},
            extra={k: v for k, v in data.items() if k not in cls.KEYS},
        )

    def to_json(self):
        """The JSON object: the keys of :data:`KEYS` that are recorded, then :attr:`extra`."""
        out = {k: getattr(self, k) for k in self.KEYS if getattr(self, k) is not None}
        out.update(self.extra)
        return out


@dataclass(frozen=True)
class ImageEntry(_FileEntry):
    """One image file a manifest lists (in ``images`` or ``gi_images``): the JSON object
    ``{"file", "time_s"[, "sha256"]}``.

    Attributes
    ----------
    file : str
        The EXR file's name inside the basis folder.
    time_s : float or None
        Seconds its render took (None: not recorded, written as an absent key).
    sha256 : str or None
        SHA-256 (hex) of the file's bytes (None: not recorded).
    extra : dict
        Keys this version does not know (kept, and written back).
    """

    file: str
    time_s: Optional[float] = None
    sha256: Optional[str] = None
    extra: dict = field(default_factory=dict)

    #: The JSON keys, in the order written.
    KEYS = ("file", "time_s", "sha256")


@dataclass(frozen=True)
class CrossEntry(_FileEntry):
    """The cross terms' file a manifest lists (``cross``): the JSON object
    ``{"file", "pairs", "tol"[, "sha256"]}`` (:mod:`mitsuba_manifold.basis.crossterms`).

    Attributes
    ----------
    file : str
        The ``.npz`` file's name inside the basis folder.
    pairs : int or None
        Number of cross terms (pairs of materials) it holds.
    tol : float or None
        Smallest weight product of a candidate pair it was rendered with.
    sha256 : str or None
        SHA-256 (hex) of the file's bytes (None: not recorded).
    extra : dict
        Keys this version does not know (kept, and written back).
    """

    file: str
    pairs: Optional[int] = None
    tol: Optional[float] = None
    sha256: Optional[str] = None
    extra: dict = field(default_factory=dict)

    #: The JSON keys, in the order written.
    KEYS = ("file", "pairs", "tol", "sha256")


def _entries_from_json(section):
    return None if section is None else {k: ImageEntry.from_json(e) for k, e in section.items()}


def _entries_to_json(section):
    return None if section is None else {k: e.to_json() for k, e in section.items()}


#: What a basis may hold (``components`` of the manifest; absent: ``["l1"]``, an older basis).
COMPONENTS = ("l1", "l2+", "cross")

Sha256 = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$", description="a SHA-256 hex digest")]
Text = Annotated[str, Field(min_length=1, description="a non-empty string")]
ExrName = Annotated[
    str,
    Field(
        pattern=r"^[^/.][^/]*\.exr$",
        description="a plain '<name>.exr' file name inside the folder",
    ),
]
Size = Annotated[
    list[Annotated[int, Field(ge=1)]],
    Field(min_length=2, max_length=2, description="[width, height] (positive integers)"),
]


class _Entry(BaseModel):
    model_config = ConfigDict(strict=True, extra="allow", frozen=True)


class GiImageFile(_Entry):
    """A full-GI image a manifest lists (``gi_images``): ``{"file", "time_s", "sha256"}``."""

    file: ExrName
    time_s: Optional[float] = Field(
        None, ge=0, allow_inf_nan=False, description="a non-negative number (render seconds)"
    )
    sha256: Sha256 = None


class ImageFile(GiImageFile):
    """An image a manifest lists (``images``): ``{"file", "time_s"[, "sha256"]}``."""

    time_s: float = Field(
        ge=0, allow_inf_nan=False, description="a non-negative number (render seconds)"
    )


class CrossFile(_Entry):
    """The cross terms' file (``cross``): ``{"file", "pairs", "tol"[, "sha256"]}``."""

    file: str = Field(pattern=r"^[^/]+\.npz$", description="a plain '<name>.npz' file name")
    sha256: Sha256 = None


class ManifestSchema(FileSchema):
    """A basis folder's ``manifest.json``: what its images are, how they were made and which
    files hold them (read and written by :class:`Manifest`).

    Version 1 (raw material names in image keys, the manifold file's SHA-256) reads as it is;
    :meth:`Manifest.upgraded` makes it version 2 given the manifold file it was made with (the
    manifold's content identity needs the file, so the upgrade is not a JSON rewrite).
    """

    VERSION: ClassVar[int] = FORMAT_VERSION
    VERSIONS: ClassVar[str] = (
        "1: raw material names in the image keys, the manifold file's SHA-256 as manifold_hash; "
        "2: escaped names, the manifold's content identity. A version-1 manifest reads as it is; "
        "Manifest.upgraded(manifold) makes it version 2 given the manifold file it was made with."
    )
    FIX: ClassVar[str] = "render the basis again with render_basis"
    ERROR: ClassVar[type] = MismatchError

    format: Literal["mitsuba-manifold-basis"] = Field(description=f"{FORMAT!r} (a basis manifest)")
    version: int = Field(description="the format version (1 or 2)")
    scene: Text = Field(description="a non-empty string (the scene XML's absolute path)")
    scene_hash: Sha256
    manifold: Text = Field(description="a non-empty string (the manifold's absolute path)")
    manifold_hash: Sha256
    resolution: Size
    spp: int = Field(ge=1, description="a positive integer (samples per pixel)")
    variant: Text = Field(description="a non-empty string (the Mitsuba variant)")
    seed: int = Field(description="an integer (the images' seed)")
    max_depth: int = Field(ge=-1, description="an integer >= -1 (-1: unbounded)")
    mode: Literal["per-material", "onepass"] = Field(description=f"one of {MODES}")
    targets: list[Text] = Field(min_length=1, description="a non-empty list of BSDF ids")
    images: dict[str, ImageFile] = Field(description="an object: image key -> image file")
    sensor: int = Field(None, ge=0, description="an integer >= 0 (the sensor rendered)")
    chunks: int = Field(None, ge=1, description="an integer >= 1 (merged from this many chunks)")
    pending: list[ExrName] = Field(None, description="a list of image files being written")
    components: list[Literal[COMPONENTS]] = Field(
        None, min_length=1, description=f"a list of {COMPONENTS}: what the basis holds"
    )
    levels: int = Field(None, ge=1, description="an integer >= 1 (most vertices per L2+ path)")
    gi_images: dict[str, GiImageFile] = Field(
        None, description="an object: material key -> full-GI image file"
    )
    cross: Optional[CrossFile] = Field(None, description="the cross terms' file")
    left_out: dict[str, Any] = Field(None, description="an object: component -> why")
    gi_stats: dict[str, Any] = Field(None, description="an object (render measurements)")
    integrator: dict[str, Any] = Field(None, description="an object (the integrator's settings)")
    scene_resolution: Optional[Size] = Field(
        None, description="[width, height] the scene was loaded with, or null (its film's size)"
    )

    @model_validator(mode="after")
    def _between_fields(self) -> "ManifestSchema":
        targets = self.targets
        if len(set(targets)) != len(targets):
            raise ValueError(f"its targets field must name distinct BSDF ids, got {targets!r}")
        comps = self.components or ["l1"]
        if (
            comps[0] != "l1"
            or len(set(comps)) != len(comps)
            or ("cross" in comps and "l2+" not in comps)
        ):
            raise ValueError(
                f"its components field must list 'l1', then 'l2+' and 'cross' if held, got {comps!r}"
            )
        files = set()
        for key, entry in self.images.items():
            parts = key.split(SEP)
            escaped = self.version < 2 or all(names_mod.is_escaped(p) for p in parts if p)
            if key != BASE and (
                len(parts) != len(targets) or not all(parts) or BASE in parts or not escaped
            ):
                raise ValueError(
                    f"image key {key!r} must name {len(targets)} material(s) joined by {SEP!r} "
                    f"(one per target {targets})"
                )
            if entry.file in files:
                raise ValueError(f"image {key!r}: file {entry.file!r} is listed twice")
            files.add(entry.file)
        self._check_files_are_their_keys()
        return self

    def _check_files_are_their_keys(self) -> None:
        """Each image's file is its own: an entry listing the file named after another image
        key (``"a": {"file": "b.exr", ...}``: two entries' ``file`` and ``sha256`` swapped) is
        refused, since every file's hash is then right and every material wrong. The renderers
        name each file after its key (``<key>.exr``; full-GI images ``<key>.gi.exr``).
        """
        sections = (("images", ".exr"), ("gi_images", ".gi.exr"))
        for section, _ in sections:
            for key, entry in (getattr(self, section) or {}).items():
                for other, suffix in sections:
                    owner = entry.file[: -len(suffix)] if entry.file.endswith(suffix) else None
                    if owner in (getattr(self, other) or {}) and (other, owner) != (section, key):
                        where = "" if other == section else f" in {other}"
                        raise ValueError(
                            f"image {key!r} lists the file {entry.file!r}, the file of image "
                            f"{owner!r}{where}: the manifest's entries were swapped or edited"
                        )


def manifold_file_identity(manifold):
    """Content identity of a manifold file (:func:`manifold_identity`)."""
    from ...manifold.model import Manifold

    return manifold_identity(Manifold.load(manifold))


class NotRecorded(enum.Enum):
    """A field a manifest of an earlier version does not record (written as an absent key)."""

    NOT_RECORDED = "not recorded"


#: The value of a manifest field that is absent from its file (not the same as JSON ``null``).
NOT_RECORDED = NotRecorded.NOT_RECORDED


@dataclass(frozen=True)
class RenderSettings:
    """The settings a basis's images are rendered with, as its :class:`Manifest` records them.

    Parameters
    ----------
    resolution : (int, int)
        ``(width, height)``.
    spp, seed, max_depth : int
    variant : str
        Mitsuba variant used.
    mode : {"per-material", "onepass"}
    sensor : int or None
        The scene's sensor (view) the images are rendered from; a new basis always records it,
        so that a reference of the basis renders the same view (None: a manifest of an earlier
        version, which rendered sensor 0).
    """

    resolution: tuple
    spp: int
    variant: str
    seed: int
    max_depth: int
    mode: str
    sensor: Optional[int] = 0


#: JSON keys of :class:`RenderSettings` written before ``targets`` (``sensor`` comes after
#: ``images``: the order of the files written so far).
_SETTINGS_HEAD = ("resolution", "spp", "variant", "seed", "max_depth", "mode")


@dataclass
class Manifest:
    """A basis folder's ``manifest.json`` (the format of this module's doc): what the images
    are, how they were made and which files hold them. Alone it reads (:meth:`read`), writes
    (:meth:`write`) and checks (:meth:`check`) the format; the JSON keys are its field names,
    with the render settings' (:class:`RenderSettings`) at the top level of the object.

    Attributes
    ----------
    scene, manifold : str
        Absolute paths of the scene XML and the saved manifold.
    scene_hash, manifold_hash : str
        Their identities (:func:`scene_hash`; :func:`manifold_file_identity`, version 1: the
        file's SHA-256).
    settings : RenderSettings
        What the images are rendered with (also read as :attr:`resolution`, :attr:`spp`,
        :attr:`variant`, :attr:`seed`, :attr:`max_depth`, :attr:`mode`, :attr:`sensor`).
    targets : list of str
        BSDF ids of the scene's manifold materials, in the order of the image keys.
    images : dict
        Image key -> its :class:`ImageEntry`.
    version : int
        Format version (1 or 2).
    chunks : int or None
        Merged from this many chunks.
    pending : list of str or None
        Files being written (:mod:`mitsuba_manifold.render.jobs.render_basis`).
    components : list of str or None
        What the basis holds (:data:`COMPONENTS`; None: not recorded, L1- only).
    levels : int or None
        Most vertices on the material per path in the L2+ images.
    gi_images : dict or None
        Material key -> the :class:`ImageEntry` of its ``touch + L2+`` image.
    cross : CrossEntry or None
        The cross terms' file.
    left_out : dict or None
        Component -> why it was left out.
    gi_stats : dict or None
        Measurements of the full-GI render.
    integrator : dict or None
        The scene's integrator settings the images were rendered with
        (:meth:`~mitsuba_manifold.render.scene.scenes.SceneIntegrator.to_manifest`).
    scene_resolution : list of int, None or NOT_RECORDED
        The ``resolution`` the scene was loaded with (None: its own film size; see
        :attr:`loaded_resolution`).
    extra : dict
        Keys the format leaves to the jobs that write it (a chunked render's marks,
        :class:`~mitsuba_manifold.render.jobs.chunks.ChunkMark`) or that this version does not know
        (kept, and written back).
    """

    scene: str
    scene_hash: str
    manifold: str
    manifold_hash: str
    settings: RenderSettings
    targets: list
    images: dict = field(default_factory=dict)
    version: int = FORMAT_VERSION
    chunks: Optional[int] = None
    pending: Optional[list] = None
    components: Optional[list] = None
    levels: Optional[int] = None
    gi_images: Optional[dict] = None
    cross: Optional[CrossEntry] = None
    left_out: Optional[dict] = None
    gi_stats: Optional[dict] = None
    integrator: Optional[dict] = None
    scene_resolution: Union[list, None, NotRecorded] = NOT_RECORDED
    extra: dict = field(default_factory=dict)

    # ----------------------------------------------------------- making one
    @classmethod
    def new(cls, scene, manifold, settings, *, targets, images=None, components=("l1",)):
        """A new, checked manifest of a basis of ``scene`` rendered with ``manifold``.

        Computes the absolute paths and the identities (:func:`scene_hash`,
        :func:`manifold_file_identity`) itself, so every writer and reader agree on them.

        Parameters
        ----------
        scene, manifold : str
            Scene XML and saved manifold (``.npz``) paths.
        settings : RenderSettings
            What the images are rendered with.
        targets : list of str
            BSDF ids of the scene's manifold materials, in the order of the image keys.
        images : dict, optional
            ``{key: ImageEntry}`` (default: none yet).
        components : sequence of str
            What the basis holds (:data:`COMPONENTS`; default L1- only). A renderer that adds
            full-GI images sets it when it writes them.
        """
        manifold = resolve_manifold(manifold)
        if not os.path.isfile(manifold):
            raise MismatchError(f"manifold {manifold} does not exist")
        settings = RenderSettings(
            resolution=tuple(int(v) for v in settings.resolution),
            spp=int(settings.spp),
            variant=str(settings.variant),
            seed=int(settings.seed),
            max_depth=int(settings.max_depth),
            mode=settings.mode,
            sensor=int(settings.sensor or 0),
        )
        return cls(
            scene=os.path.abspath(scene),
            scene_hash=scene_hash(scene),
            manifold=os.path.abspath(manifold),
            manifold_hash=manifold_file_identity(manifold),
            settings=settings,
            targets=[str(t) for t in targets],
            images=dict(images or {}),
            components=[str(c) for c in components],
        ).check("new manifest")

    def _chunk_mark(name):  # builds the deprecated properties below (not a method)
        def get(self):
            warnings.warn(
                f"Manifest.{name} is deprecated: read it with "
                "mitsuba_manifold.render.jobs.chunks.ChunkMark.of(manifest)",
                DeprecationWarning,
                stacklevel=2,
            )
            return self.extra.get(name)

        def put(self, value):
            warnings.warn(
                f"Manifest.{name} is deprecated: set it with "
                "mitsuba_manifold.render.jobs.chunks.ChunkMark(...).put(manifest)",
                DeprecationWarning,
                stacklevel=2,
            )
            self.extra.pop(name, None)
            if value is not None:
                self.extra[name] = value

        return property(get, put, doc=f"Deprecated: ``ChunkMark.of(manifest).{name}``.")

    chunk_complete = _chunk_mark("chunk_complete")
    chunk_run = _chunk_mark("chunk_run")
    chunk_key = _chunk_mark("chunk_key")
    del _chunk_mark

    def copy(self):
        """A deep copy (its entries can be changed without changing this one's)."""
        return copy.deepcopy(self)

    def upgraded(self, manifold):
        """The manifest as version 2 when it is a version-1 manifest made with the file
        ``manifold`` (same bytes): the manifold hash becomes its content identity and the images
        whose keys are the same in both versions (names that escaping leaves unchanged) are kept.
        Any other manifest is returned as it is.
        """
        if self.version != 1 or file_hash(manifold) != self.manifold_hash:
            return self
        images = {
            k: e
            for k, e in self.images.items()
            if k == BASE or all(names_mod.is_escaped(p) for p in k.split(SEP))
        }
        return dataclasses.replace(
            self,
            version=FORMAT_VERSION,
            manifold_hash=manifold_file_identity(manifold),
            images=images,
        )

    # ----------------------------------------------------------- JSON
    @classmethod
    def from_json(cls, data, where=MANIFEST):
        """The manifest of a JSON object, checked (:class:`MismatchError` naming ``where``)."""
        if isinstance(data, cls):
            return data
        ManifestSchema.checked(data, where)  # does not require any image listed: see Basis.load
        data = dict(data)
        settings = RenderSettings(
            resolution=tuple(data.pop("resolution")),
            **{k: data.pop(k) for k in _SETTINGS_HEAD[1:]},
            sensor=data.pop("sensor", None),
        )
        names = {f.name for f in dataclasses.fields(cls)} - {"extra", "settings"}
        known = {k: v for k, v in data.items() if k in names}
        known["images"] = _entries_from_json(known["images"])
        known["gi_images"] = _entries_from_json(known.get("gi_images"))
        if known.get("cross") is not None:
            known["cross"] = CrossEntry.from_json(known["cross"])
        return cls(
            **known,
            settings=settings,
            extra={k: v for k, v in data.items() if k not in names and k != "format"},
        )

    def to_json(self):
        """The JSON object of the format: ``format``, ``version``, the fields set (the settings'
        at the top level), then :attr:`extra`; its keys in the order of the files written so far.
        """
        out = {"format": FORMAT, "version": self.version}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "settings":
                out["resolution"] = list(value.resolution)
                out.update({k: getattr(value, k) for k in _SETTINGS_HEAD[1:]})
                continue
            if f.name in ("version", "extra") or value is NOT_RECORDED:
                continue
            if value is None and f.default is None:
                continue
            if f.name in ("images", "gi_images"):
                value = _entries_to_json(value)
            elif f.name == "cross":
                value = value.to_json()
            out[f.name] = value
            if f.name == "images" and self.settings.sensor is not None:
                out["sensor"] = self.settings.sensor
        out.update(self.extra)
        return out

    def check(self, where="manifest"):
        """Return this manifest, its fields checked (:class:`MismatchError` naming ``where``)."""
        ManifestSchema.checked(self.to_json(), where)
        return self

    # ----------------------------------------------------------- files
    @classmethod
    def read(cls, folder):
        """The manifest of the basis folder ``folder``, checked.

        Raises
        ------
        MismatchError
            No such folder, no manifest, not JSON, or a field at fault.
        """
        folder = os.fspath(folder)
        if not os.path.isdir(folder):
            raise MismatchError(
                f"basis folder {folder} does not exist"
                if not os.path.exists(folder)
                else f"{folder} is a file, not a basis folder (give the folder render_basis wrote)"
            )
        path = os.path.join(folder, MANIFEST)
        if not os.path.isfile(path):
            held = sorted(
                f for f in os.listdir(folder) if os.path.isfile(os.path.join(folder, f, MANIFEST))
            )
            if held:  # render_basis of several scenes or views: one basis per sub-folder
                shown = ", ".join(os.path.join(folder, f) for f in held[:4])
                raise MismatchError(
                    f"{folder}: no {MANIFEST}; it holds {len(held)} basis folder(s) (one per "
                    f"scene or view): give one of them ({shown}{', ...' if len(held) > 4 else ''})"
                )
            raise MismatchError(
                f"{folder}: no {MANIFEST} (not a basis folder, or render_basis has not "
                "written one yet)"
            )
        try:
            with open(path, encoding="utf-8") as f:
                data = json.load(f)
        except (ValueError, UnicodeDecodeError) as e:
            raise MismatchError(f"{path}: not valid JSON ({e})") from None
        except RecursionError:
            raise MismatchError(
                f"{path}: not a basis manifest (its JSON is nested too deeply to be one)"
            ) from None
        return cls.from_json(data, where=path)

    def write(self, folder):
        """Check this manifest and write ``folder/manifest.json`` atomically; returns its path."""
        path = os.path.join(os.fspath(folder), MANIFEST)
        data = self.to_json()
        ManifestSchema.checked(data, path)
        write_bytes(path, json.dumps(data, indent=1, sort_keys=False) + "\n")
        return path

    # ----------------------------------------------------------- meaning
    @property
    def resolution(self):
        """``(width, height)`` of the images."""
        return self.settings.resolution

    @property
    def spp(self):
        """Samples per pixel of every image."""
        return self.settings.spp

    @property
    def variant(self):
        """The Mitsuba variant rendered in."""
        return self.settings.variant

    @property
    def seed(self):
        """The images' seed."""
        return self.settings.seed

    @property
    def max_depth(self):
        """Path depth (-1: unbounded)."""
        return self.settings.max_depth

    @property
    def mode(self):
        """``"per-material"`` or ``"onepass"``."""
        return self.settings.mode

    @property
    def sensor(self):
        """The scene's sensor rendered (None: not recorded; sensor 0)."""
        return self.settings.sensor

    @property
    def sensor_index(self):
        """The sensor the images were rendered from (0 when not recorded)."""
        return 0 if self.sensor is None else self.sensor

    @property
    def held_components(self):
        """What the basis holds (``["l1"]`` when not recorded)."""
        return list(self.components) if self.components is not None else ["l1"]

    @property
    def loaded_resolution(self):
        """The ``resolution`` the basis's scene was loaded with (None: the scene's own film
        size), to load it again as the basis saw it (its references, refinements); a manifest
        that does not record it (an earlier version) was rendered at its image size.
        """
        if self.scene_resolution is NOT_RECORDED:
            return tuple(self.resolution)
        value = self.scene_resolution
        return None if value is None else tuple(int(v) for v in value)

    def section(self, name):
        """The entries of ``"images"`` or ``"gi_images"`` (an empty one set first when absent)."""
        if name not in ("images", "gi_images"):
            raise ValueError(f"no image section {name!r}")
        if getattr(self, name) is None:
            setattr(self, name, {})
        return getattr(self, name)

    def entries(self):
        """``(key, entry)`` of every image file: L1- images, then full-GI ones (``gi:<key>``)."""
        return list(self.images.items()) + [(GI + k, e) for k, e in (self.gi_images or {}).items()]

    def set_entry(self, key, entry):
        """List ``entry`` (:class:`ImageEntry`) as image ``key`` of :meth:`entries` (``gi:<key>``:
        a full-GI image).
        """
        if key.startswith(GI):
            self.section("gi_images")[key[len(GI) :]] = entry
        else:
            self.section("images")[key] = entry

    def listed_files(self):
        """The files the manifest lists: its images, full-GI images and cross terms."""
        files = {e.file for _, e in self.entries()}
        return files | ({self.cross.file} if self.cross else set())

    def differences(self, other, ignore=()):
        """Setting fields (:data:`SETTINGS`, but those in ``ignore``) whose values differ from
        ``other``'s: empty when images rendered for one are valid for the other (resume).
        """
        other = Manifest.from_json(other)

        def value(m, k):
            if k == "format":
                return FORMAT
            v = m.sensor_index if k == "sensor" else getattr(m, k)
            return list(v) if isinstance(v, tuple) else v

        return [k for k in SETTINGS if k not in ignore and value(self, k) != value(other, k)]


#: Prefix of the keys of full-GI images (``Manifest.gi_images``) among a basis's images.
GI = "gi:"

#: Manifest fields that define what the images are (all but "images" and the paths).
SETTINGS = (
    "format",
    "version",
    "scene_hash",
    "manifold_hash",
    "resolution",
    "spp",
    "variant",
    "seed",
    "max_depth",
    "mode",
    "targets",
    "sensor",
    "chunks",
    "levels",
)


def is_basis_folder(folder):
    """True when ``folder`` holds a basis manifest (whether or not it is complete)."""
    try:
        with open(os.path.join(os.fspath(folder), MANIFEST), encoding="utf-8") as f:
            return json.load(f).get("format") == FORMAT
    except (OSError, ValueError, AttributeError, RecursionError):
        return False

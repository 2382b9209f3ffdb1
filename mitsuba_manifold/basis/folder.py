"""The basis folder: per-material images of a scene, their manifest, and :class:`Basis`.

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
     "sensor": int (optional, default 0), "chunks": int (optional: merged from k chunks),
     "pending": ["<key>.exr", ...] (optional: being written; see render_basis),
     "images": {"base": {"file": "base.exr", "time_s": float},
                "<material>": {"file": "<material>.exr", "time_s": float}, ...}}

With one target the keys are ``base`` and material names; with ``p`` targets they are
``"<matA>+<matB>..."`` (one name per target, in target order). From version 2 on, each
material name in a key is escaped (:func:`mitsuba_manifold._util.names.escape`: ``gold-paint``
stays, ``base`` or ``a+b`` cannot collide with the base image or the separator) and the
file is ``<key>.exr``; ``manifold_hash`` is the manifold's content identity
(:func:`mitsuba_manifold.manifold.identity.manifold_identity`), so an identical refit is accepted.
Version 1 manifests (raw names, SHA-256 of the manifold file) are still read.
``scene_hash`` is the SHA-256 of the scene XML and the files it names (:func:`scene_hash`). :func:`make_manifest` and :func:`write_manifest` write the format,
:class:`Basis` reads and checks it, :func:`mitsuba_manifold.basis.blend.blend` and :func:`~mitsuba_manifold.basis.blend.blend_path` combine it.
"""

import hashlib
import json
import os
import re
import time

import numpy as np

from ..imaging import io as imageio
from .._util import names as names_mod
from .._util.atomic import write_bytes
from .._util.cache import file_hash
from ..errors import FormatError, ForeignFileError, InputError, MismatchError
from ..manifold.identity import manifold_identity
from .._util.checks import scene_xml

FORMAT = "mitsuba-manifold-basis"
FORMAT_VERSION = 2
MANIFEST = "manifest.json"
BASE = "base"
#: Joins one material name per target into an image key (multilinear bases).
SEP = "+"
MODES = ("per-material", "onepass")

_HEX64 = re.compile(r"^[0-9a-f]{64}$")


# ------------------------------------------------------------------ hashes

def scene_files(scene):
    """Files a scene XML names (``filename`` properties and ``<include>``), resolved
    against the scene's folder; values holding ``$parameters`` are skipped."""
    scene = os.fspath(scene)
    root = scene_xml(scene)   # a scene XML, or an error naming the file
    folder = os.path.dirname(os.path.abspath(scene))
    names = []
    for el in root.iter():
        value = el.get("value") if el.get("name") == "filename" else None
        if el.tag == "include":
            value = el.get("filename")
        if value and "$" not in value:
            names.append(value)
    return [(v, os.path.join(folder, v)) for v in names]


def scene_hash(scene):
    """SHA-256 (hex) of a scene: its XML bytes, then the name and bytes of every file it
    names (:func:`scene_files`) that exists beside it. Meshes and environment maps are
    thereby part of the scene's identity; the manifold (a ``$manifold`` parameter) is not."""
    scene = os.fspath(scene)
    if not os.path.isfile(scene):
        raise MismatchError(f"scene {scene} does not exist")
    h = hashlib.sha256()
    with open(scene, "rb") as f:
        h.update(f.read())
    for value, path in scene_files(scene):
        h.update(b"\0" + value.encode())
        if os.path.isfile(path):
            h.update(b"\0" + file_hash(path).encode())
    return h.hexdigest()


# ---------------------------------------------------------------- manifest

def image_key(materials, version=FORMAT_VERSION):
    """Image key of one material per target: ``"a"`` or ``"a+b"``, names escaped
    (:func:`names.escape`) from format version 2 on; the image file is ``<key>.exr``."""
    materials = [materials] if isinstance(materials, str) else list(materials)
    if version >= 2:
        try:
            return SEP.join(names_mod.escape(m) for m in materials)
        except InputError as e:
            raise MismatchError(str(e)) from None
    for m in materials:
        if not m or SEP in m or m == BASE:
            raise MismatchError(f"material name {m!r} cannot be used in an image key of a version-1 basis; "
                             "render the basis again with this version")
    return SEP.join(materials)


def key_materials(key, version=FORMAT_VERSION):
    """Material names (one per target) of an image key: the inverse of :func:`image_key`."""
    parts = key.split(SEP)
    return [names_mod.unescape(p) for p in parts] if version >= 2 else parts


def _is_int(v):
    return isinstance(v, int) and not isinstance(v, bool)


def validate_manifest(manifest, where=MANIFEST):
    """Check the fields and types of a manifest dict; returns it.

    Does not require any image to be listed (a basis being rendered grows one image at a
    time); :meth:`Basis.load` checks that the blend's images are there.

    Raises
    ------
    MismatchError
        Naming ``where`` and the field at fault.
    """
    def bad(msg):
        raise MismatchError(f"{where}: {msg}")

    if not isinstance(manifest, dict):
        bad("not a JSON object")
    if manifest.get("format") != FORMAT:
        bad(f"not a basis manifest (format {manifest.get('format')!r}, expected {FORMAT!r})")
    version = manifest.get("version")
    if not _is_int(version) or version < 1:
        bad(f"invalid version {version!r}")
    if version > FORMAT_VERSION:
        bad(f"format version {version} is newer than this package reads ({FORMAT_VERSION})")
    for key in ("scene", "manifold", "variant"):
        if not isinstance(manifest.get(key), str) or not manifest[key]:
            bad(f"field {key!r} must be a non-empty string, got {manifest.get(key)!r}")
    for key in ("scene_hash", "manifold_hash"):
        if not isinstance(manifest.get(key), str) or not _HEX64.match(manifest[key]):
            bad(f"field {key!r} must be a SHA-256 hex digest, got {manifest.get(key)!r}")
    res = manifest.get("resolution")
    if not (isinstance(res, list) and len(res) == 2 and all(_is_int(v) and v > 0 for v in res)):
        bad(f"resolution must be [width, height] (positive integers), got {res!r}")
    if not _is_int(manifest.get("spp")) or manifest["spp"] < 1:
        bad(f"spp must be a positive integer, got {manifest.get('spp')!r}")
    if not _is_int(manifest.get("seed")):
        bad(f"seed must be an integer, got {manifest.get('seed')!r}")
    if not _is_int(manifest.get("max_depth")) or manifest["max_depth"] < -1:
        bad(f"max_depth must be an integer >= -1, got {manifest.get('max_depth')!r}")
    if manifest.get("mode") not in MODES:
        bad(f"mode must be one of {MODES}, got {manifest.get('mode')!r}")
    for key in ("sensor", "chunks"):  # optional: absent means sensor 0, one chunk
        if key in manifest and (not _is_int(manifest[key]) or manifest[key] < (0 if key == "sensor" else 1)):
            bad(f"{key} must be an integer >= {0 if key == 'sensor' else 1}, got {manifest[key]!r}")
    targets = manifest.get("targets")
    if (not isinstance(targets, list) or not targets or not all(isinstance(t, str) and t for t in targets)
            or len(set(targets)) != len(targets)):
        bad(f"targets must be a non-empty list of distinct BSDF ids, got {targets!r}")
    pending = manifest.get("pending", [])
    if not isinstance(pending, list) or not all(_plain_exr(f) for f in pending):
        bad(f"pending must be a list of plain '<name>.exr' file names, got {pending!r}")
    images = manifest.get("images")
    if not isinstance(images, dict):
        bad(f"images must be an object, got {type(images).__name__}")
    files = set()
    for key, entry in images.items():
        if key != BASE:
            parts = key.split(SEP)
            escaped = version < 2 or all(names_mod.is_escaped(pt) for pt in parts if pt)
            if len(parts) != len(targets) or not all(parts) or BASE in parts or not escaped:
                bad(f"image key {key!r} must name {len(targets)} material(s) joined by {SEP!r} "
                    f"(one per target {targets})")
        if not isinstance(entry, dict):
            bad(f"image {key!r}: entry must be an object with 'file' and 'time_s'")
        name = entry.get("file")
        if not _plain_exr(name):
            bad(f"image {key!r}: file must be a plain '<name>.exr' inside the folder, got {name!r}")
        if name in files:
            bad(f"image {key!r}: file {name!r} is listed twice")
        files.add(name)
        t = entry.get("time_s")
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not np.isfinite(t) or t < 0:
            bad(f"image {key!r}: time_s must be a non-negative number, got {t!r}")
    return manifest


def _plain_exr(name):
    return (isinstance(name, str) and name.endswith(".exr") and os.path.basename(name) == name
            and not name.startswith("."))


def make_manifest(scene, manifold, resolution, spp, variant, seed, max_depth, mode, targets,
                  images=None):
    """A validated manifest dict for a basis of ``scene`` rendered with ``manifold``.

    Computes the absolute paths and the hashes (:func:`scene_hash`, :func:`file_hash`)
    itself, so every writer and reader agree on them.

    Parameters
    ----------
    scene, manifold : str
        Scene XML and saved manifold (``.npz``) paths.
    resolution : (int, int)
        ``(width, height)``.
    spp, seed, max_depth : int
    variant : str
        Mitsuba variant used.
    mode : {"per-material", "onepass"}
    targets : list of str
        BSDF ids of the scene's manifold materials, in the order of the image keys.
    images : dict, optional
        ``{key: {"file": ..., "time_s": ...}}`` (default: none yet).
    """
    manifold = os.fspath(manifold)
    if not os.path.isfile(manifold):
        raise MismatchError(f"manifold {manifold} does not exist")
    manifest = {
        "format": FORMAT, "version": FORMAT_VERSION,
        "scene": os.path.abspath(scene), "scene_hash": scene_hash(scene),
        "manifold": os.path.abspath(manifold), "manifold_hash": manifold_file_identity(manifold),
        "resolution": [int(v) for v in resolution], "spp": int(spp), "variant": str(variant),
        "seed": int(seed), "max_depth": int(max_depth), "mode": mode,
        "targets": [str(t) for t in targets], "images": dict(images or {})}
    return validate_manifest(manifest, where="new manifest")


def manifold_file_identity(manifold):
    """Content identity of a manifold file (:func:`manifold_identity`)."""
    from ..manifold.model import Manifold
    return manifold_identity(Manifold.load(manifold))


def upgrade_manifest(manifest, manifold):
    """A version-1 manifest as version 2, when it was made with the file ``manifold`` (same
    bytes): the manifold hash becomes its content identity and the images whose keys are
    the same in both versions (names that escaping leaves unchanged) are kept. Any other
    manifest is returned as it is."""
    if manifest.get("version") != 1 or file_hash(manifold) != manifest.get("manifold_hash"):
        return manifest
    images = {k: e for k, e in manifest["images"].items()
              if k == BASE or all(names_mod.is_escaped(p) for p in k.split(SEP))}
    return dict(manifest, version=FORMAT_VERSION, manifold_hash=manifold_file_identity(manifold), images=images)


def write_manifest(folder, manifest):
    """Validate ``manifest`` and write ``folder/manifest.json`` atomically; returns its path."""
    validate_manifest(manifest, where=os.path.join(os.fspath(folder), MANIFEST))
    path = os.path.join(os.fspath(folder), MANIFEST)
    text = json.dumps(manifest, indent=1, sort_keys=False) + "\n"
    write_bytes(path, text)
    return path


def read_manifest(folder):
    """Read and validate ``folder/manifest.json``."""
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise MismatchError(f"basis folder {folder} does not exist")
    path = os.path.join(folder, MANIFEST)
    if not os.path.isfile(path):
        raise MismatchError(f"{folder}: no {MANIFEST} (not a basis folder, or render_basis has not "
                         "written one yet)")
    try:
        with open(path, encoding="utf-8") as f:
            manifest = json.load(f)
    except (ValueError, UnicodeDecodeError) as e:
        raise MismatchError(f"{path}: not valid JSON ({e})") from None
    return validate_manifest(manifest, where=path)


#: Manifest fields that define what the images are (all but "images" and the paths).
SETTINGS = ("format", "version", "scene_hash", "manifold_hash", "resolution", "spp", "variant",
            "seed", "max_depth", "mode", "targets", "sensor", "chunks")


def manifest_differences(a, b, ignore=()):
    """Setting fields (:data:`SETTINGS`, but those in ``ignore``) whose values differ between two manifests.

    An empty list means images rendered for one are valid for the other (resume)."""
    return [k for k in SETTINGS if k not in ignore and a.get(k) != b.get(k)]


# -------------------------------------------------------------------- basis

def manifold_object(manifold):
    from ..manifold.model import Manifold

    if isinstance(manifold, (str, os.PathLike)):
        return Manifold.load(manifold)
    _check_manifold_type(manifold)
    return manifold


def _check_manifold_type(manifold):
    if not isinstance(manifold, (str, os.PathLike)) and not (
            hasattr(manifold, "weights") and hasattr(manifold, "names")):
        raise MismatchError(f"manifold: expected a Manifold or the path of one, got {type(manifold).__name__} "
                         "(give a latent point as x=..., weights as w=...)")


class Basis:
    """A basis folder: its manifest and its images (read on first use, then kept).

    Attributes
    ----------
    folder : str
    manifest : dict
    resolution : (int, int)
        ``(width, height)``.
    targets : list of str
    p : int
        Number of targets.
    keys : list of str
        Image keys other than ``base``.
    materials : list of list of str
        Per target, the materials that appear in some image key.
    """

    def __init__(self, folder, manifest):
        self.folder = os.fspath(folder)
        self.manifest = manifest
        self.resolution = tuple(manifest["resolution"])
        self.targets = list(manifest["targets"])
        self.p = len(self.targets)
        self.version = manifest["version"]
        self.keys = [k for k in manifest["images"] if k != BASE]
        parts = [key_materials(k, self.version) for k in self.keys]
        self.materials = [sorted({pt[t] for pt in parts}) for t in range(self.p)]
        self._rows = {}  # image key -> row of self._store
        self._store = None  # float32 (capacity, H, W, 3): the images read so far
        self._checked = {}  # manifold path or object -> manifold object, checked against the manifest

    @classmethod
    def load(cls, folder, manifold=None, scene=None, verify=False):
        """Open a basis folder and check it.

        Parameters
        ----------
        folder : str
        manifold : Manifold or str, optional
            Checked against the manifest: file hash (when the manifold has a path) and
            material names.
        scene : str, optional
            Scene XML, checked against the manifest's scene hash.
        verify : bool
            Also read every image in full now (finds files truncated after their header).

        Raises
        ------
        MismatchError
            Missing or malformed manifest, a listed image that is missing, not an RGB EXR
            or not of the manifest's resolution, no ``base`` image for a one-target basis,
            a manifest made for another scene or manifold.
        """
        folder = os.fspath(folder)
        manifest = read_manifest(folder)
        basis = cls(folder, manifest)
        if basis.p == 1 and BASE not in manifest["images"]:
            raise MismatchError(f"{folder}: the manifest lists no '{BASE}' image (paths that never touch "
                             "the material); the basis is incomplete")
        if not basis.keys:
            raise MismatchError(f"{folder}: the manifest lists no material image; the basis is incomplete")
        for key, entry in manifest["images"].items():
            try:
                imageio.check_exr_header(basis.path(key), basis.resolution)
            except FormatError as e:
                raise MismatchError(f"basis {folder}, image {key!r}: {e}") from None
        if scene is not None:
            basis.check_scene(scene)
        if manifold is not None:
            basis.check_manifold(manifold)
        if verify:
            basis.verify()
        return basis

    def __repr__(self):
        return (f"Basis({self.folder!r}: {len(self.keys)} images, targets {self.targets}, "
                f"{self.resolution[0]}x{self.resolution[1]}, {self.manifest['spp']} spp)")

    def path(self, key):
        """File of image ``key``."""
        try:
            return os.path.join(self.folder, self.manifest["images"][key]["file"])
        except KeyError:
            raise MismatchError(f"basis {self.folder} has no image {key!r}") from None

    def has(self, key):
        return key in self.manifest["images"]

    def key(self, materials):
        """Image key of one material name per target (:func:`image_key` for this basis's version)."""
        return image_key(materials, self.version)

    def material_keys(self, names):
        """Image keys of single materials ``names`` (a one-target basis), in order."""
        return [self.key([n]) for n in names]

    def image(self, key):
        """Image ``key`` as float32 (H, W, 3), read once and kept (a read-only view)."""
        row = self._rows.get(key)
        if row is None:
            path = self.path(key)
            try:
                img = imageio.read_exr(path)
            except FormatError as e:
                raise MismatchError(f"basis {self.folder}, image {key!r}: {e}") from None
            w, h = self.resolution
            if img.shape != (h, w, 3):
                raise MismatchError(f"basis {self.folder}, image {key!r}: {path} is {img.shape[1]}x{img.shape[0]}, "
                                 f"the manifest says {w}x{h}")
            row = len(self._rows)
            if self._store is None or row == len(self._store):  # grow by doubling, up to every image
                cap = min(max(8, 2 * row), len(self.manifest["images"]))
                store = np.empty((cap, h, w, 3), dtype=np.float32)
                if row:
                    store[:row] = self._store[:row]
                self._store = store
            self._store[row] = img
            self._rows[key] = row
        view = self._store[row]
        view.setflags(write=False)
        return view

    def read(self, keys):
        """Read the images ``keys`` not read before; returns the seconds spent."""
        t0 = time.perf_counter()
        for k in keys:
            self.image(k)
        return time.perf_counter() - t0

    def weighted_sum(self, keys, weights):
        """``sum_j weights[..., j] * image(keys[j])`` as float32 (..., H, W, 3).

        The images read so far live in one array: when the blend uses at least half of
        them the product runs over all of them with zero weights elsewhere (no copy),
        otherwise over a gathered copy of the ones used.
        """
        weights = np.asarray(weights, dtype=np.float32)
        self.read(keys)
        rows = np.array([self._rows[k] for k in keys], dtype=np.intp)
        n = len(self._rows)
        if 2 * len(rows) >= n:
            dense = np.zeros(weights.shape[:-1] + (n,), dtype=np.float32)
            dense[..., rows] = weights
            return np.tensordot(dense, self._store[:n], axes=1)
        return np.tensordot(weights, self._store[rows], axes=1)

    def verify(self):
        """Read every listed image in full (raises :class:`MismatchError` on the first bad one)."""
        for key in self.manifest["images"]:
            self.image(key)
        return self

    def check_scene(self, scene):
        """Raise unless ``scene`` (an XML path) is the scene the basis was rendered from."""
        h = scene_hash(scene)
        if h != self.manifest["scene_hash"]:
            raise MismatchError(
                f"basis {self.folder} was rendered from another scene: {self.manifest['scene']} "
                f"(hash {self.manifest['scene_hash'][:12]}), not {os.path.abspath(scene)} (hash {h[:12]}); "
                "the scene or a file it uses changed, render the basis again")

    def check_manifold(self, manifold=None):
        """The manifold object, checked against the manifest (loaded from the manifest's
        path when ``manifold`` is None).

        Checks that every material of the basis is a material of the manifold, and its
        content identity (version 1: the file hash, when the manifold has a path).
        """
        if manifold is None:
            manifold = self.manifest["manifold"]
            if not os.path.isfile(manifold):
                raise MismatchError(f"basis {self.folder}: its manifold {manifold} no longer exists; "
                                 "give the manifold explicitly")
        _check_manifold_type(manifold)
        key = os.path.abspath(manifold) if isinstance(manifold, (str, os.PathLike)) else manifold
        if key in self._checked:
            return self._checked[key]
        m = manifold_object(manifold)
        unknown = sorted({n for mats in self.materials for n in mats} - set(m.names))
        if unknown:
            raise MismatchError(f"basis {self.folder} holds materials the manifold does not know: "
                             f"{', '.join(unknown[:8])}{' ...' if len(unknown) > 8 else ''}; it was "
                             "rendered with another manifold")
        path = manifold if isinstance(manifold, (str, os.PathLike)) else getattr(m, "file", None)
        if self.version >= 2 or path is not None:
            h = manifold_identity(m) if self.version >= 2 else file_hash(path)
            if h != self.manifest["manifold_hash"]:
                where = os.path.abspath(path) if path is not None else "the manifold given"
                raise MismatchError(
                    f"basis {self.folder} was rendered with another manifold: {self.manifest['manifold']} "
                    f"(identity {self.manifest['manifold_hash'][:12]}), not {where} (identity {h[:12]}: other "
                    "latent points, hyperparameters, materials or tables)")
        self._checked[key] = m
        return m


def is_basis_folder(folder):
    """True when ``folder`` holds a basis manifest (whether or not it is complete)."""
    try:
        with open(os.path.join(os.fspath(folder), MANIFEST), encoding="utf-8") as f:
            return json.load(f).get("format") == FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def check_output_outside_basis(out, basis_folder=None):
    """Raise unless ``out`` lies outside every basis folder (``basis_folder`` included):
    a blend never writes into a basis, whose files the basis's manifest owns."""
    folder = os.path.realpath(os.path.dirname(os.path.abspath(os.fspath(out))))
    inside = basis_folder is not None and folder == os.path.realpath(os.fspath(basis_folder))
    if inside or is_basis_folder(folder):
        raise ForeignFileError(f"--out {out} lies in the basis folder {folder}; a blend never writes into a "
                               "basis (its images belong to render_basis): choose another folder")

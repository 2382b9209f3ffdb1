"""Images of any latent point from a basis of per-material renders (paper Sec. 5.2 and 6).

Rendering is linear in the BRDF. With one manifold material (one *target*) in the scene,
the part of the image made of paths that scatter off it at most once (``L1-``) is

    I(x) = base + sum_i w_i(x) I_i                                   (paper Eq. 13)

``base``: the paths that never touch the target; ``I_i``: the paths that touch it exactly
once, rendered with measured material ``i``; ``w(x)``: the manifold's affine weights.
Materials whose ``|w_i|`` is pruned away are skipped (:meth:`Manifold.prune` rescales the
kept weights to the same sum). With ``p`` targets (paper Sec. 6) the image is multilinear:

    I(x^1..x^p) = sum_{i_1..i_p} prod_t w^t_{i_t} I[i_1..i_p]

where ``I[i_1..i_p]`` is the full ``L1-`` image (base included) with target ``t`` set to
material ``i_t``.

A *basis folder* holds those images as float32 EXR files and a ``manifest.json``::

    {"format": "mitsuba-manifold-basis", "version": 1,
     "scene": abs path, "scene_hash": sha256, "manifold": abs path, "manifold_hash": sha256,
     "resolution": [width, height], "spp": int, "variant": str, "seed": int, "max_depth": int,
     "mode": "per-material" | "onepass", "targets": [bsdf id, ...],
     "images": {"base": {"file": "base.exr", "time_s": float},
                "<material>": {"file": "<material>.exr", "time_s": float}, ...}}

With one target the keys are ``base`` and material names; with ``p`` targets they are
``"<matA>+<matB>..."`` (one name per target, in target order). ``manifold_hash`` is the
SHA-256 of the manifold file; ``scene_hash`` that of the scene XML and the files it names
(:func:`scene_hash`). :func:`make_manifest` and :func:`write_manifest` write the format,
:class:`Basis` reads and checks it, :func:`blend` and :func:`blend_path` combine it.
"""

import hashlib
import itertools
import json
import os
import re
import time
import xml.etree.ElementTree as ET

import numpy as np

from . import imageio
from .imageio import ImageError
from .merl import atomic_write, file_hash

FORMAT = "mitsuba-manifold-basis"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
BASE = "base"
#: Joins one material name per target into an image key (multilinear bases).
SEP = "+"
MODES = ("per-material", "onepass")
#: Default pruning threshold (fraction of ``sum |w|``), as the ``manifold_brdf`` plugin.
DEFAULT_PRUNE = 1e-3
#: How far the weights of one target may sum away from 1 in a multilinear blend.
AFFINE_TOL = 1e-6

_HEX64 = re.compile(r"^[0-9a-f]{64}$")
_PARAM = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")


class BasisError(ValueError):
    """A basis folder that is missing, damaged or does not match the scene or manifold."""


# ------------------------------------------------------------------ hashes

def scene_files(scene):
    """Files a scene XML names (``filename`` properties and ``<include>``), resolved
    against the scene's folder; values holding ``$parameters`` are skipped."""
    scene = os.fspath(scene)
    try:
        root = ET.parse(scene).getroot()
    except ET.ParseError as e:
        raise BasisError(f"scene {scene}: not a readable XML file ({e})") from None
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
        raise BasisError(f"scene {scene} does not exist")
    h = hashlib.sha256()
    with open(scene, "rb") as f:
        h.update(f.read())
    for value, path in scene_files(scene):
        h.update(b"\0" + value.encode())
        if os.path.isfile(path):
            h.update(b"\0" + file_hash(path).encode())
    return h.hexdigest()


# ---------------------------------------------------------------- manifest

def image_key(materials):
    """Image key of one material per target: ``"a"`` or ``"a+b"``."""
    materials = [materials] if isinstance(materials, str) else list(materials)
    for m in materials:
        if not m or SEP in m or m == BASE:
            raise BasisError(f"material name {m!r} cannot be used in an image key")
    return SEP.join(materials)


def _is_int(v):
    return isinstance(v, int) and not isinstance(v, bool)


def validate_manifest(manifest, where=MANIFEST):
    """Check the fields and types of a manifest dict; returns it.

    Does not require any image to be listed (a basis being rendered grows one image at a
    time); :meth:`Basis.load` checks that the blend's images are there.

    Raises
    ------
    BasisError
        Naming ``where`` and the field at fault.
    """
    def bad(msg):
        raise BasisError(f"{where}: {msg}")

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
    targets = manifest.get("targets")
    if (not isinstance(targets, list) or not targets or not all(isinstance(t, str) and t for t in targets)
            or len(set(targets)) != len(targets)):
        bad(f"targets must be a non-empty list of distinct BSDF ids, got {targets!r}")
    images = manifest.get("images")
    if not isinstance(images, dict):
        bad(f"images must be an object, got {type(images).__name__}")
    files = set()
    for key, entry in images.items():
        if key != BASE:
            parts = key.split(SEP)
            if len(parts) != len(targets) or not all(parts) or BASE in parts:
                bad(f"image key {key!r} must name {len(targets)} material(s) joined by {SEP!r} "
                    f"(one per target {targets})")
        if not isinstance(entry, dict):
            bad(f"image {key!r}: entry must be an object with 'file' and 'time_s'")
        name = entry.get("file")
        if (not isinstance(name, str) or not name.endswith(".exr") or os.path.basename(name) != name
                or name.startswith(".")):
            bad(f"image {key!r}: file must be a plain '<name>.exr' inside the folder, got {name!r}")
        if name in files:
            bad(f"image {key!r}: file {name!r} is listed twice")
        files.add(name)
        t = entry.get("time_s")
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not np.isfinite(t) or t < 0:
            bad(f"image {key!r}: time_s must be a non-negative number, got {t!r}")
    return manifest


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
        raise BasisError(f"manifold {manifold} does not exist")
    manifest = {
        "format": FORMAT, "version": FORMAT_VERSION,
        "scene": os.path.abspath(scene), "scene_hash": scene_hash(scene),
        "manifold": os.path.abspath(manifold), "manifold_hash": file_hash(manifold),
        "resolution": [int(v) for v in resolution], "spp": int(spp), "variant": str(variant),
        "seed": int(seed), "max_depth": int(max_depth), "mode": mode,
        "targets": [str(t) for t in targets], "images": dict(images or {})}
    return validate_manifest(manifest, where="new manifest")


def write_manifest(folder, manifest):
    """Validate ``manifest`` and write ``folder/manifest.json`` atomically; returns its path."""
    validate_manifest(manifest, where=os.path.join(os.fspath(folder), MANIFEST))
    path = os.path.join(os.fspath(folder), MANIFEST)
    text = json.dumps(manifest, indent=1, sort_keys=False) + "\n"
    atomic_write(path, lambda f: f.write(text.encode()))
    return path


def read_manifest(folder):
    """Read and validate ``folder/manifest.json``."""
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise BasisError(f"basis folder {folder} does not exist")
    path = os.path.join(folder, MANIFEST)
    if not os.path.isfile(path):
        raise BasisError(f"{folder}: no {MANIFEST} (not a basis folder, or render_basis has not "
                         "written one yet)")
    try:
        with open(path, encoding="utf-8") as f:
            manifest = json.load(f)
    except (ValueError, UnicodeDecodeError) as e:
        raise BasisError(f"{path}: not valid JSON ({e})") from None
    return validate_manifest(manifest, where=path)


#: Manifest fields that define what the images are (all but "images" and the paths).
SETTINGS = ("format", "version", "scene_hash", "manifold_hash", "resolution", "spp", "variant",
            "seed", "max_depth", "mode", "targets")


def manifest_differences(a, b):
    """Setting fields (:data:`SETTINGS`) whose values differ between two manifests.

    An empty list means images rendered for one are valid for the other (resume)."""
    return [k for k in SETTINGS if a.get(k) != b.get(k)]


# -------------------------------------------------------------------- basis

def _manifold_object(manifold):
    from .manifold import Manifold

    if isinstance(manifold, (str, os.PathLike)):
        return Manifold.load(manifold)
    if not hasattr(manifold, "weights") or not hasattr(manifold, "names"):
        raise BasisError(f"expected a Manifold or the path of one, got {type(manifold).__name__}")
    return manifold


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
        self.keys = [k for k in manifest["images"] if k != BASE]
        parts = [k.split(SEP) for k in self.keys]
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
        BasisError
            Missing or malformed manifest, a listed image that is missing, not an RGB EXR
            or not of the manifest's resolution, no ``base`` image for a one-target basis,
            a manifest made for another scene or manifold.
        """
        folder = os.fspath(folder)
        manifest = read_manifest(folder)
        basis = cls(folder, manifest)
        if basis.p == 1 and BASE not in manifest["images"]:
            raise BasisError(f"{folder}: the manifest lists no '{BASE}' image (paths that never touch "
                             "the material); the basis is incomplete")
        if not basis.keys:
            raise BasisError(f"{folder}: the manifest lists no material image; the basis is incomplete")
        for key, entry in manifest["images"].items():
            try:
                imageio.check_exr_header(basis.path(key), basis.resolution)
            except ImageError as e:
                raise BasisError(f"basis {folder}, image {key!r}: {e}") from None
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
            raise BasisError(f"basis {self.folder} has no image {key!r}") from None

    def has(self, key):
        return key in self.manifest["images"]

    def image(self, key):
        """Image ``key`` as float32 (H, W, 3), read once and kept (a read-only view)."""
        row = self._rows.get(key)
        if row is None:
            path = self.path(key)
            try:
                img = imageio.read_exr(path)
            except ImageError as e:
                raise BasisError(f"basis {self.folder}, image {key!r}: {e}") from None
            w, h = self.resolution
            if img.shape != (h, w, 3):
                raise BasisError(f"basis {self.folder}, image {key!r}: {path} is {img.shape[1]}x{img.shape[0]}, "
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
        """Read every listed image in full (raises :class:`BasisError` on the first bad one)."""
        for key in self.manifest["images"]:
            self.image(key)
        return self

    def check_scene(self, scene):
        """Raise unless ``scene`` (an XML path) is the scene the basis was rendered from."""
        h = scene_hash(scene)
        if h != self.manifest["scene_hash"]:
            raise BasisError(
                f"basis {self.folder} was rendered from another scene: {self.manifest['scene']} "
                f"(hash {self.manifest['scene_hash'][:12]}), not {os.path.abspath(scene)} (hash {h[:12]}); "
                "the scene or a file it uses changed, render the basis again")

    def check_manifold(self, manifold=None):
        """The manifold object, checked against the manifest (loaded from the manifest's
        path when ``manifold`` is None).

        Checks the file hash when the manifold has a path, and that every material of the
        basis is a material of the manifold.
        """
        if manifold is None:
            manifold = self.manifest["manifold"]
            if not os.path.isfile(manifold):
                raise BasisError(f"basis {self.folder}: its manifold {manifold} no longer exists; "
                                 "give the manifold explicitly")
        key = os.path.abspath(manifold) if isinstance(manifold, (str, os.PathLike)) else manifold
        if key in self._checked:
            return self._checked[key]
        m = _manifold_object(manifold)
        path = manifold if isinstance(manifold, (str, os.PathLike)) else getattr(m, "path", None)
        if path is not None:
            h = file_hash(path)
            if h != self.manifest["manifold_hash"]:
                raise BasisError(
                    f"basis {self.folder} was rendered with another manifold: {self.manifest['manifold']} "
                    f"(hash {self.manifest['manifold_hash'][:12]}), not {os.path.abspath(path)} "
                    f"(hash {h[:12]})")
        unknown = sorted({n for mats in self.materials for n in mats} - set(m.names))
        if unknown:
            raise BasisError(f"basis {self.folder} holds materials the manifold does not know: "
                             f"{', '.join(unknown[:8])}{' ...' if len(unknown) > 8 else ''}; it was "
                             "rendered with another manifold")
        self._checked[key] = m
        return m


# -------------------------------------------------------------------- blend

def latent_points(basis, manifold, x):
    """``x`` as (p, q): one latent point per target.

    Accepts (q,) for one target, (p, q), or p*q numbers in target order."""
    p, q = basis.p, manifold.q
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise BasisError(f"x must be numbers, got {x!r}") from None
    if arr.size != p * q or arr.ndim > 2 or (arr.ndim == 2 and arr.shape != (p, q)):
        raise BasisError(
            f"x has shape {arr.shape} ({arr.size} numbers), but the basis has {p} target(s) "
            f"{basis.targets} on a {q}-dimensional manifold: x needs {p * q} numbers "
            f"({'q' if p == 1 else 'p x q'})")
    arr = arr.reshape(p, q)
    if not np.isfinite(arr).all():
        raise BasisError(f"x contains NaN or Inf: {arr.tolist()}")
    return arr


def _target_weights(basis, manifold, x, w):
    """Affine weights (p, N) from ``x`` or ``w``, plus the latent points (or None)."""
    if (x is None) == (w is None):
        raise BasisError("give exactly one of x (latent point) and w (weights)")
    if x is not None:
        pts = latent_points(basis, manifold, x)
        return manifold.weights(pts)[1], pts
    try:
        arr = np.asarray(w, dtype=np.float64)
    except (TypeError, ValueError):
        raise BasisError(f"w must be numbers, got {w!r}") from None
    n = len(manifold.names)
    if arr.size != basis.p * n or arr.ndim > 2 or (arr.ndim == 2 and arr.shape != (basis.p, n)):
        raise BasisError(f"w has shape {arr.shape}; the basis has {basis.p} target(s) and the manifold "
                         f"{n} materials: w needs shape ({n},) or ({basis.p}, {n})")
    arr = arr.reshape(basis.p, n)
    if not np.isfinite(arr).all():
        raise BasisError("w contains NaN or Inf")
    return arr, None


def _plan(basis, manifold, W, prune, renormalise):
    """Image keys and their weights for one blend.

    Returns ``(keys, weights, info)``; ``weights`` multiply the images ``keys`` (plus
    ``base`` with weight 1 for a one-target basis).
    """
    p, names = basis.p, manifold.names
    kept, info = [], {"weights": [], "dropped_weight": []}
    for t in range(p):
        if p > 1 and abs(W[t].sum() - 1.0) > AFFINE_TOL:
            raise BasisError(f"weights of target {basis.targets[t]!r} sum to {W[t].sum():.9g}; a "
                             "multilinear blend needs weights summing to 1 per target (its images "
                             "include the base)")
        keep, wk, dropped = manifold.prune(W[t], prune)
        kept.append((keep, wk))
        info["weights"].append({names[i]: float(v) for i, v in zip(keep, wk)})
        info["dropped_weight"].append(dropped)
    if p == 1:
        keys = [names[i] for i in kept[0][0]]
        cw = kept[0][1].copy()
    else:
        keys = [SEP.join(names[i] for i in combo) for combo in itertools.product(*(k for k, _ in kept))]
        cw = kept[0][1]
        for _, wk in kept[1:]:
            cw = np.multiply.outer(cw, wk).ravel()
    total = cw.sum()
    present = np.array([basis.has(k) for k in keys], dtype=bool)
    missing = {k: float(v) for k, v, ok in zip(keys, cw, present) if not ok}
    info["missing"] = missing
    info["renormalised"] = False
    if missing:
        if not renormalise:
            listed = ", ".join(f"{k} (w={v:.4g})" for k, v in sorted(missing.items(), key=lambda kv: -abs(kv[1]))[:10])
            raise BasisError(
                f"basis {basis.folder} lacks {len(missing)} image(s) whose weight survives pruning "
                f"(prune={prune:g}): {listed}{' ...' if len(missing) > 10 else ''}. Render them, raise "
                "--prune, or renormalise over the images present (an approximation)")
        if not present.any() or abs(cw[present].sum()) < 1e-12:
            raise BasisError(f"basis {basis.folder}: none of the images this blend needs is present "
                             f"(missing: {', '.join(sorted(missing)[:10])}); cannot renormalise")
        keys = [k for k, ok in zip(keys, present) if ok]
        cw = cw[present] * (total / cw[present].sum())
        info["renormalised"] = True
    info["keys"] = keys
    info["image_weights"] = cw
    return keys, cw, info


def blend(basis, manifold=None, x=None, w=None, prune=DEFAULT_PRUNE, renormalise=False):
    """The image of latent point ``x`` (or weights ``w``) from a basis.

    Parameters
    ----------
    basis : Basis or str
    manifold : Manifold or str, optional
        Default: the manifest's manifold. Checked against the manifest.
    x : array_like
        Latent point: (q,) for one target, (p, q) (or p*q numbers) for p targets.
    w : array_like
        Weights instead of ``x``: (N,) or (p, N). With one target any weights are allowed
        (the touch images are linear in the BRDF); with several, each row must sum to 1.
    prune : float
        Skip materials with ``|w_i| <= prune * sum |w|`` (:meth:`Manifold.prune`; the kept
        weights are rescaled to the same sum).
    renormalise : bool
        When images the blend needs are missing from the basis (e.g. a ``--near`` basis),
        drop them and rescale the remaining image weights to the same sum instead of
        raising. This approximates the missing materials by the present ones.

    Returns
    -------
    image : ndarray float32 (H, W, 3)
    info : dict
        ``weights`` (per target, kept material -> weight), ``dropped_weight`` (per target),
        ``keys``/``image_weights`` (images combined), ``missing``, ``renormalised``, ``x``,
        ``time_ms`` (weights, pruning, gathering and summing the images in memory),
        ``time_read_s`` (reading from disk the images not read before).
    """
    if not isinstance(basis, Basis):
        basis = Basis.load(basis)
    manifold = basis.check_manifold(manifold)
    t0 = time.perf_counter()
    W, pts = _target_weights(basis, manifold, x, w)
    keys, cw, info = _plan(basis, manifold, W, prune, renormalise)
    t_plan = time.perf_counter() - t0
    image, t_read, t_sum = _compose(basis, keys, cw)
    info.update(x=None if pts is None else (pts[0] if basis.p == 1 else pts),
                time_ms=1e3 * (t_plan + t_sum), time_read_s=t_read, n_images=len(keys))
    return image, info


def _compose(basis, keys, weights):
    """Eq. 13: ``base + sum_j weights[..., j] image(keys[j])`` (no base with several targets).

    Returns the image(s), the seconds spent reading images and the seconds of the sum.
    """
    t_read = basis.read(keys + ([BASE] if basis.p == 1 else []))
    t0 = time.perf_counter()
    images = basis.weighted_sum(keys, weights)
    if basis.p == 1:
        images += basis.image(BASE)
    return images, t_read, time.perf_counter() - t0


def _endpoint(manifold, v):
    if isinstance(v, str):
        return manifold.latent[manifold.index(v)].copy()
    arr = np.asarray(v, dtype=np.float64).ravel()
    if arr.size != manifold.q or not np.isfinite(arr).all():
        raise BasisError(f"path end {v!r}: expected a material name or {manifold.q} finite numbers")
    return arr


def blend_path(basis, manifold=None, a=None, b=None, steps=20, prune=DEFAULT_PRUNE, renormalise=False,
               target=0, x=None):
    """Images along the latent segment from ``a`` to ``b`` (paper Fig. 12).

    Parameters
    ----------
    a, b : str or array_like (q,)
        Material names (their latent points) or latent points.
    steps : int
        Number of images, ``t = 0 .. 1`` inclusive (>= 2).
    target : int
        With several targets: which one moves along the segment.
    x : array_like (p, q), optional
        With several targets: the latent points of the others (row ``target`` ignored).

    Returns
    -------
    images : ndarray float32 (steps, H, W, 3)
    xs : ndarray (steps, q)
        The latent points of the moving target.
    info : dict
        ``steps`` (the per-image info of :func:`blend`), ``time_ms`` (all images, as
        :func:`blend`), ``time_read_s``.
    """
    if not isinstance(basis, Basis):
        basis = Basis.load(basis)
    manifold = basis.check_manifold(manifold)
    if not isinstance(steps, (int, np.integer)) or steps < 2:
        raise BasisError(f"steps must be an integer >= 2, got {steps!r}")
    if not 0 <= target < basis.p:
        raise BasisError(f"target {target} out of range: the basis has {basis.p} target(s)")
    xa, xb = _endpoint(manifold, a), _endpoint(manifold, b)
    t = np.linspace(0.0, 1.0, steps)[:, None]
    xs = (1.0 - t) * xa + t * xb
    if basis.p > 1:
        if x is None:
            raise BasisError(f"the basis has {basis.p} targets: give x for the targets that stay fixed")
        fixed = latent_points(basis, manifold, x)
    t0 = time.perf_counter()
    plans = []
    for xi in xs:
        pts = xi[None] if basis.p == 1 else np.where(np.arange(basis.p)[:, None] == target, xi, fixed)
        W = manifold.weights(pts)[1]
        plans.append(_plan(basis, manifold, W, prune, renormalise))
    keys = sorted({k for ks, _, _ in plans for k in ks})
    col = {k: j for j, k in enumerate(keys)}
    M = np.zeros((steps, len(keys)), dtype=np.float32)
    for s, (ks, cw, _) in enumerate(plans):
        M[s, [col[k] for k in ks]] = cw
    t_plan = time.perf_counter() - t0
    images, t_read, t_sum = _compose(basis, keys, M)
    for (_, _, inf), xi in zip(plans, xs):
        inf["x"] = xi
    return images, xs, {"steps": [p[2] for p in plans], "time_ms": 1e3 * (t_plan + t_sum),
                        "time_read_s": t_read}


def write_contact_sheet(path, images, labels=None, columns=None, exposure=0.0, pad=4):
    """PNG grid of tonemapped images (one exposure for all), with optional labels; atomic.

    Parameters
    ----------
    images : array_like (n, H, W, 3)
        Linear radiance.
    labels : list of str, optional
        Drawn under each image.
    columns : int, optional
        Default: ``ceil(sqrt(n))``.
    """
    from PIL import Image, ImageDraw

    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3 or len(images) == 0:
        raise ValueError(f"contact sheet needs images of shape (n, H, W, 3), got {images.shape}")
    n, h, w, _ = images.shape
    if labels is not None and len(labels) != n:
        raise ValueError(f"{len(labels)} labels for {n} images")
    cols = int(columns or np.ceil(np.sqrt(n)))
    rows = -(-n // cols)
    label_h = 14 if labels else 0
    sheet = np.full((rows * (h + label_h + pad) + pad, cols * (w + pad) + pad, 3), 32, dtype=np.uint8)
    tiles = imageio.tonemap(images, exposure)
    for i in range(n):
        r, c = divmod(i, cols)
        y, x0 = pad + r * (h + label_h + pad), pad + c * (w + pad)
        sheet[y:y + h, x0:x0 + w] = tiles[i]
    if labels:
        pil = Image.fromarray(sheet)
        draw = ImageDraw.Draw(pil)
        for i, text in enumerate(labels):
            r, c = divmod(i, cols)
            draw.text((pad + c * (w + pad) + 2, pad + r * (h + label_h + pad) + h + 1), str(text),
                      fill=(230, 230, 230))
        sheet = np.asarray(pil)
    imageio.write_png(path, sheet)


# ---------------------------------------------------------------- reference

def scene_parameters(scene):
    """Names of the ``$parameters`` a scene XML uses, and its ``<default>`` values."""
    scene = os.fspath(scene)
    if not os.path.isfile(scene):
        raise BasisError(f"scene {scene} does not exist")
    with open(scene, encoding="utf-8") as f:
        text = f.read()
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise BasisError(f"scene {scene}: not a readable XML file ({e})") from None
    defaults = {el.get("name"): el.get("value") for el in root.iter("default")}
    return set(_PARAM.findall(text)), defaults


def load_scene(scene_path, manifold_path, spp=None, resolution=None, max_depth=None, x=None,
               variant=None):
    """Load a scene XML with its ``$parameters`` set, and find its manifold materials.

    Only the parameters the XML uses are passed (Mitsuba refuses others): ``$manifold``,
    ``$x``, ``$spp``, ``$max_depth``, ``$integrator`` (``path``) and the size through
    ``$res`` (square) or ``$width``/``$height``.

    Parameters
    ----------
    scene_path, manifold_path : str
    spp : int, optional
    resolution : int or (int, int), optional
        Square size or ``(width, height)``; checked against the film.
    max_depth : int, optional
        Default: the scene's ``$max_depth`` default, else -1 (unbounded).
    x : array_like (q,), optional
    variant : str, optional
        Default: the active variant, else ``llvm_ad_rgb``.

    Returns
    -------
    scene : mi.Scene
    targets : list
        The scene's ``manifold_brdf`` instances (shape order), checked to use ``manifold_path``.
    max_depth : int
    """
    import mitsuba as mi

    import mitsuba_manifold
    from .integrators import manifold_bsdfs

    scene_path, manifold_path = os.fspath(scene_path), os.fspath(manifold_path)
    if not os.path.isfile(manifold_path):
        raise BasisError(f"manifold {manifold_path} does not exist")
    used, defaults = scene_parameters(scene_path)
    if variant is not None and variant != mi.variant():
        mi.set_variant(variant)
    elif mi.variant() is None:
        mi.set_variant("llvm_ad_rgb" if "llvm_ad_rgb" in mi.variants() else "scalar_rgb")
    mitsuba_manifold.register()
    if spp is not None and int(spp) < 1:
        raise BasisError(f"spp must be >= 1, got {spp}")
    params = {}
    if "manifold" in used:
        params["manifold"] = os.path.abspath(manifold_path)
    if "x" in used and x is not None:
        params["x"] = ", ".join(repr(float(v)) for v in np.ravel(x))
    if "spp" in used and spp is not None:
        params["spp"] = str(int(spp))
    if "integrator" in used:
        params["integrator"] = "path"
    if max_depth is None:
        max_depth = int(defaults.get("max_depth", -1)) if "max_depth" in used else -1
    if "max_depth" in used:
        params["max_depth"] = str(int(max_depth))
    size = None
    if resolution is not None:
        size = (int(resolution), int(resolution)) if np.isscalar(resolution) else tuple(int(v) for v in resolution)
        if "res" in used and size[0] == size[1]:
            params["res"] = str(size[0])
        for name, value in zip(("width", "height"), size):
            if name in used:
                params[name] = str(value)
    try:
        scene = mi.load_file(scene_path, **params)
    except Exception as e:
        raise BasisError(f"scene {scene_path}: cannot load ({e})") from None
    targets = manifold_bsdfs(scene)
    if not targets:
        raise BasisError(f"scene {scene_path} has no manifold_brdf material (give the material to edit "
                         "type=\"manifold_brdf\" and take the manifold as $manifold)")
    want = file_hash(manifold_path)
    for bsdf in targets:
        path = getattr(bsdf, "manifold_path", None)
        if path is None or file_hash(path) != want:
            raise BasisError(f"scene {scene_path}: material {bsdf.id()!r} uses manifold {path}, not "
                             f"{manifold_path} (the scene does not take it as $manifold)")
    film_size = tuple(int(v) for v in scene.sensors()[0].film().size())
    if size is not None and film_size != size:
        raise BasisError(f"scene {scene_path} renders {film_size[0]}x{film_size[1]}, not {size[0]}x{size[1]} "
                         "(it takes no $res/$width/$height parameter for this size)")
    return scene, targets, int(max_depth)


def render_reference(scene_path, manifold_path, x, spp, seed=0, resolution=None, max_depth=None,
                     variant=None, targets=None):
    """Full global-illumination image of the interpolated material, with Mitsuba's ``path``.

    Loads the scene (:func:`load_scene`), sets every manifold material to its latent
    point, and renders with a ``path`` integrator.

    Parameters
    ----------
    scene_path, manifold_path : str
    x : array_like
        (q,): every manifold material of the scene at x; or (p, q): one point per target.
    targets : list of str, optional
        BSDF ids of the rows of a (p, q) ``x`` (a basis's ``targets``); default: the
        scene's manifold materials in the order of its shapes.
    spp, seed : int
    resolution, max_depth, variant
        As :func:`load_scene`.

    Returns
    -------
    ndarray float32 (H, W, 3)
    """
    import mitsuba as mi

    pts = np.atleast_2d(np.asarray(x, dtype=np.float64))
    if pts.ndim != 2 or not np.isfinite(pts).all():
        raise BasisError(f"x must be finite numbers of shape (q,) or (p, q), got {np.shape(x)}")
    if int(spp) < 1:
        raise BasisError(f"spp must be >= 1, got {spp}")
    scene, found, max_depth = load_scene(scene_path, manifold_path, spp, resolution, max_depth, pts[0], variant)
    ids = [b.id() for b in found]
    if len(pts) == 1:
        rows = [0] * len(found)
    else:
        order = ids if targets is None else list(targets)
        if len(order) != len(pts) or sorted(order) != sorted(ids):
            raise BasisError(f"x gives {len(pts)} latent points for targets {order}; the scene's manifold "
                             f"materials are {ids}")
        rows = [order.index(i) for i in ids]
    for bsdf, row in zip(found, rows):
        bsdf.set_latent(pts[row])
    integrator = mi.load_dict({"type": "path", "max_depth": int(max_depth)})
    img = mi.render(scene, integrator=integrator, spp=int(spp), seed=int(seed))
    return np.array(img, dtype=np.float32)[..., :3].copy()

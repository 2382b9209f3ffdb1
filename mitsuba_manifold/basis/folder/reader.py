"""The reader of a basis folder: :class:`Basis`, its manifest and its images (read on first use).

The format (``manifest.json``, image keys, hashes) is :mod:`.manifest`.
"""

import os
import threading
import time
import zipfile

import numpy as np

from ..._util.blas import axpy, one_thread
from ..._util.cache import file_hash
from ..._util.locking import is_locked
from ...errors import FormatError, MismatchError
from ...imaging import io as imageio
from ...manifold.file.identity import manifold_identity
from ...manifold.file.shipped import resolve_manifold
from .manifest import BASE, GI, Manifest, image_changed, image_key, key_materials, scene_hash

# -------------------------------------------------------------------- basis

#: What a reader says when a basis it finds changed is being written now.
IN_PROGRESS = (
    "render_basis is writing into this basis now (it holds the folder's lock): wait until it "
    "finishes, then run this again"
)


def _in_progress(folder, where, why):
    """``where: why``, or where a render holds the folder's lock (:func:`is_locked`), ``where``
    and the render in progress (what changed is being written, not damaged).
    """
    return f"{where}: {IN_PROGRESS if is_locked(folder) else why}"


def manifold_object(manifold):
    from ...manifold.model import Manifold

    if isinstance(manifold, (str, os.PathLike)):
        return Manifold.load(manifold)
    _check_manifold_type(manifold)
    return manifold


def _check_manifold_type(manifold):
    if not isinstance(manifold, (str, os.PathLike)) and not (
        hasattr(manifold, "weights") and hasattr(manifold, "names")
    ):
        raise MismatchError(
            f"manifold: expected a Manifold or the path of one, got {type(manifold).__name__} "
            "(give a latent point as x=..., weights as w=...)"
        )


class Basis:
    """A basis folder: its manifest and its images (read on first use, then kept).

    Attributes
    ----------
    folder : str
    manifest : Manifest
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
        self.manifest = manifest = Manifest.from_json(manifest)
        self.resolution = tuple(manifest.resolution)
        self.targets = list(manifest.targets)
        self.p = len(self.targets)
        self.version = manifest.version
        self.keys = [k for k in manifest.images if k != BASE]
        parts = [key_materials(k, self.version) for k in self.keys]
        self.materials = [sorted({pt[t] for pt in parts}) for t in range(self.p)]
        self._rows = {}  # image key -> row of self._store
        self._store = None  # float32 (capacity, H, W, 3): the images read so far
        self._checked = {}  # manifold path or object -> manifold object, checked against the manifest
        #: What the basis holds (:data:`manifest.COMPONENTS`); an older basis: L1- only.
        self.components = manifest.held_components
        self.legacy = manifest.components is None
        self._cross = None  # (pairs {(a, b): row}, float16 (P, H, W, 3)) once read
        self._cross32 = {}  # row -> float32 (H, W, 3), the rows blended so far
        self._derived = {}  # name -> what derived() made from the folder's files
        self._read_lock = threading.RLock()  # one reader of a file kept here (explorer threads)

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
        manifest = Manifest.read(folder)
        basis = cls(folder, manifest)
        if basis.p == 1 and BASE not in manifest.images:
            raise MismatchError(
                f"{folder}: the manifest lists no '{BASE}' image (paths that never touch "
                "the material); the basis is incomplete"
            )
        if not basis.keys:
            raise MismatchError(
                f"{folder}: the manifest lists no material image; the basis is incomplete"
            )
        for key in list(manifest.images) + [GI + k for k in manifest.gi_images or {}]:
            try:
                imageio.check_exr_header(basis.path(key), basis.resolution)
            except FormatError as e:
                raise MismatchError(
                    _in_progress(folder, f"basis {folder}, image {key!r}", str(e))
                ) from None
        if scene is not None:
            basis.check_scene(scene)
        if manifold is not None:
            basis.check_manifold(manifold)
        if verify:
            basis.verify()
        return basis

    def derived(self, name, make):
        """``make(self)`` once per basis object, kept under ``name``: what other modules read from
        the folder's files (e.g. its AOVs for denoising) without re-reading them per blend.
        """
        with self._read_lock:
            if name not in self._derived:
                self._derived[name] = make(self)
            return self._derived[name]

    def __repr__(self):
        return (
            f"Basis({self.folder!r}: {len(self.keys)} images, targets {self.targets}, "
            f"{self.resolution[0]}x{self.resolution[1]}, {self.manifest.spp} spp)"
        )

    @property
    def sensor(self):
        """The scene's sensor (view) the images were rendered from (0 when the manifest does
        not say: :attr:`sensor_known`).
        """
        return self.manifest.sensor_index

    @property
    def sensor_known(self):
        """True when the manifest records its sensor (manifests of earlier versions recorded
        only sensors other than 0).
        """
        return self.manifest.sensor is not None

    def _entry(self, key):
        if key.startswith(GI):
            return (self.manifest.gi_images or {}).get(key[len(GI) :])
        return self.manifest.images.get(key)

    def path(self, key):
        """File of image ``key`` (``"gi:<key>"``: the material's full-GI image less base)."""
        entry = self._entry(key)
        if entry is None:
            raise MismatchError(f"basis {self.folder} has no image {key!r}")
        return os.path.join(self.folder, entry.file)

    def has(self, key):
        return self._entry(key) is not None

    def gi_key(self, key):
        """Key of the full-GI image (``touch + L2+``) of material image ``key``."""
        return GI + key

    def cross_terms(self):
        """The cross terms ``C_ij`` (:mod:`.crossterms`): ``({(name_i, name_j): row}, float16
        (P, H, W, 3))``, read once and kept as stored (half the memory of float32; a blend
        converts the few rows it uses); empty without them.
        """
        with self._read_lock:
            if self._cross is None:
                self._cross = self._read_cross()
            return self._cross

    def _read_cross(self):
        entry = self.manifest.cross
        w, h = self.resolution
        if entry is None or "cross" not in self.components:
            return {}, np.zeros((0, h, w, 3), np.float16)
        path = os.path.join(self.folder, entry.file)
        again = "run the same render_basis command again to render them anew"
        if os.path.isfile(path) and image_changed(self.folder, entry):
            raise MismatchError(
                _in_progress(
                    self.folder,
                    f"basis {self.folder}",
                    f"cross terms {path} were changed after render_basis "
                    f"wrote them (their SHA-256 is not the manifest's); {again}",
                )
            )
        try:
            with np.load(path) as data:
                pairs, images = data["pairs"], np.asarray(data["images"], np.float16)
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise MismatchError(
                f"basis {self.folder}: cross terms {path} unreadable ({e}); {again}"
            ) from None
        if images.shape != (len(pairs), h, w, 3):
            raise MismatchError(
                f"basis {self.folder}: {path} holds {len(images)} images of shape {images.shape[1:]} "
                f"for {len(pairs)} pairs; the basis is {w}x{h}: {again}"
            )
        return {(str(a), str(b)): r for r, (a, b) in enumerate(pairs)}, images

    def cross_term(self, row):
        """Cross term ``row`` of :meth:`cross_terms` as float32 (H, W, 3), converted once and kept
        (NumPy's float16 conversion costs more than the blend itself; only the rows blended are kept
        twice).
        """
        if row not in self._cross32:
            self._cross32[row] = self.cross_terms()[1][row].astype(np.float32)
        return self._cross32[row]

    def warm_cross_terms(self):
        """Convert every cross term to float32 now (:meth:`cross_term`), as a long interactive
        session ends up holding them anyway; the first blends of a drag then skip the conversion.
        """
        for row in range(len(self.cross_terms()[1])):
            self.cross_term(row)

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
            if os.path.isfile(path) and image_changed(self.folder, self._entry(key)):
                raise MismatchError(
                    _in_progress(
                        self.folder,
                        f"basis {self.folder}, image {key!r}",
                        f"{path} was changed after render_basis "
                        "wrote it (its SHA-256 is not the manifest's); run the same render_basis "
                        "command again to render it anew",
                    )
                )
            try:
                img = imageio.read_exr(path)
            except FormatError as e:
                raise MismatchError(
                    _in_progress(self.folder, f"basis {self.folder}, image {key!r}", str(e))
                ) from None
            w, h = self.resolution
            if img.shape != (h, w, 3):
                raise MismatchError(
                    f"basis {self.folder}, image {key!r}: {path} is {img.shape[1]}x{img.shape[0]}, "
                    f"the manifest says {w}x{h}"
                )
            row = len(self._rows)
            if self._store is None or row == len(
                self._store
            ):  # grow by doubling, up to every image
                cap = min(
                    max(8, 2 * row), len(self.manifest.images) + len(self.manifest.gi_images or {})
                )
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
        if weights.ndim == 1 and len(rows):  # one image: in-place axpy, no gathered copy
            return _axpy_sum(self._store, rows, weights)
        if 2 * len(rows) >= n:
            dense = np.zeros(weights.shape[:-1] + (n,), dtype=np.float32)
            dense[..., rows] = weights
            return np.tensordot(dense, self._store[:n], axes=1)
        return np.tensordot(weights, self._store[rows], axes=1)

    def verify(self):
        """Read every listed image in full (raises :class:`MismatchError` on the first bad one)."""
        for key in list(self.manifest.images) + [GI + k for k in self.manifest.gi_images or {}]:
            self.image(key)
        self.cross_terms()
        return self

    def check_scene(self, scene):
        """Raise unless ``scene`` (an XML path) is the scene the basis was rendered from."""
        h = scene_hash(scene)
        if h != self.manifest.scene_hash:
            raise MismatchError(
                f"basis {self.folder} was rendered from another scene: {self.manifest.scene} "
                f"(hash {self.manifest.scene_hash[:12]}), not {os.path.abspath(scene)} (hash {h[:12]}); "
                "the scene or a file it uses changed, render the basis again"
            )

    def check_manifold(self, manifold=None):
        """The manifold object, checked against the manifest (loaded from the manifest's
        path when ``manifold`` is None).

        Checks that every material of the basis is a material of the manifold, and its
        content identity (version 1: the file hash, when the manifold has a path).
        """
        if manifold is None:
            manifold = resolve_manifold(self.manifest.manifold, recorded=True)
            if not os.path.isfile(manifold):
                raise MismatchError(
                    f"basis {self.folder}: its manifold {manifold} no longer exists; "
                    "give the manifold explicitly"
                )
        _check_manifold_type(manifold)
        key = os.path.abspath(manifold) if isinstance(manifold, (str, os.PathLike)) else manifold
        if key in self._checked:
            return self._checked[key]
        m = manifold_object(manifold)
        unknown = sorted({n for mats in self.materials for n in mats} - set(m.names))
        if unknown:
            raise MismatchError(
                f"basis {self.folder} holds materials the manifold does not know: "
                f"{', '.join(unknown[:8])}{' ...' if len(unknown) > 8 else ''}; it was "
                "rendered with another manifold"
            )
        path = manifold if isinstance(manifold, (str, os.PathLike)) else getattr(m, "file", None)
        if self.version >= 2 or path is not None:
            h = manifold_identity(m) if self.version >= 2 else file_hash(path)
            if h != self.manifest.manifold_hash:
                where = os.path.abspath(path) if path is not None else "the manifold given"
                what = (
                    "its file's SHA-256 (what a version-1 manifest records)"
                    if self.version < 2
                    else "its identity (latent points, hyperparameters, materials, tables)"
                )
                if where == os.path.abspath(self.manifest.manifold):
                    raise MismatchError(
                        f"basis {self.folder}: its manifold {where} is not the one it was rendered "
                        f"with: {what} is {h[:12]}, the manifest records "
                        f"{self.manifest.manifold_hash[:12]}; render the basis again with it, or "
                        "give the manifold it was rendered with"
                    )
                raise MismatchError(
                    f"basis {self.folder} was rendered with another manifold: {self.manifest.manifold} "
                    f"(identity {self.manifest.manifold_hash[:12]}), not {where} (identity {h[:12]}: "
                    "other latent points, hyperparameters, materials or tables)"
                )
        self._checked[key] = m
        return m


def _axpy_sum(store, rows, weights):
    """``sum_j weights[j] * store[rows[j]]`` (float32) by one in-place ``saxpy`` per image used
    (:func:`~mitsuba_manifold._util.blas.axpy`, on one BLAS thread), without gathering them (a ``tensordot`` copies
    them first).
    """
    out = np.zeros(store.shape[1:], dtype=np.float32)
    with one_thread():
        for r, w in zip(rows, weights):
            if w != 0.0:
                axpy(out, store[r], w)
    return out

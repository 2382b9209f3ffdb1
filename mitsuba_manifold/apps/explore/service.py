"""The explorer's state and answers, independent of HTTP: bases in memory, blends, frames.

:class:`Explorer` holds each basis with all its images read into one float32 array (the
``(N + 1, H*W*3)`` matrix of :class:`~mitsuba_manifold.basis.folder.Basis`) and answers every
request of the page from a latent point: the blended frame (:func:`blend.blend`, then
:func:`encode.tonemap` and an encoder), the material's description, the preview table, the
latent map, the snippets, the reference renders and refinements. Bad requests raise
:class:`InputError` naming the parameter, its value and what is expected.
"""

import base64
import functools
import json
import os
import shlex
import threading
import time
from xml.sax.saxutils import escape

import numpy as np

from ..._util.blas import one_thread
from ...basis.blend import DEFAULT_PRUNE, blend
from ...basis.composition import compose
from ...basis.folder import Basis
from ...data.database import cache_folder
from ...errors import InputError
from ...manifold import paths as path_kinds
from ...manifold.file.shipped import resolve_manifold
from ...manifold.model import Manifold
from . import encode, fireflies, hdri, latentmap, material
from .acquire import MAX_UPLOAD, Acquisitions, read_upload
from .bases import names as _names
from .bases import scene_of as _scene_of
from .bases import warm as _warm
from .reference import MAX_SPP, References
from .walks import MAX_STEPS, STEPS, Walks
from .web.inputs import extent, latent_point, map_dims, number, path_kind, show

#: Maps kept for repeated requests of the same slice.
MAPS_KEPT = 8
#: Map resolutions (pixels per side): at rest, and while the slice moves.
FULL_MAP, COARSE_MAP = 192, 96
#: The longest a map's next rows wait for a drag's frames to pause (seconds): a map still
#: comes during a long drag, a few rows every FRAME_WAIT.
FRAME_WAIT = 2.0
#: Frames this far apart (seconds) are a drag at rest: a map's rows run between them.
DRAG_QUIET = 0.6
#: How often a request waiting for a map made elsewhere asks whether it is still wanted (s).
MAP_POLL = 0.25
#: The longest a path's next evaluation of the metric waits for a frame being made (s).
PATH_YIELD = 0.1
TOOLS = os.path.join(
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))),
    "tools",
)


def _one_blas_thread(method):
    """``method`` run with BLAS on one thread (:func:`~mitsuba_manifold._util.blas.one_thread`):
    the answers a drag asks for on every move (frame, material, sphere table) are small products
    whose BLAS threads would wait on each other and then spin on the cores the page's browser
    needs.
    """

    @functools.wraps(method)
    def run(*args, **kwargs):
        with one_thread():
            return method(*args, **kwargs)

    return run


class Explorer:
    """Bases and manifold of one explore session.

    Parameters
    ----------
    bases : list of str
        Basis folders (rendered with the same manifold, one manifold material each).
    manifold : str, optional
        Saved manifold (default: the first basis's manifest's; checked by hash).
    database : str, optional
        Tables for the preview, the negative-bin fraction and the BRDF slice (default: the
        manifold's database).
    prune : float
        Pruning threshold of the blends (:meth:`Manifold.prune`), in [0, 1).
    load_tables : bool
        Load the tables (in a background thread) for the preview, negative bins and slice.
    scene : str, optional
        Scene XML (or shipped scene name) for the reference renders, checked against each
        basis's scene hash (default: the manifest's scene, or the shipped scene of that name
        and hash when the manifest's file has moved).
    thumbnails : bool
        Render the materials' thumbnails in the background (:mod:`.thumbs`; cached by the first basis).
    refine_spp : int
        Samples per pixel of L2+ of the page's refinement where a drag ends (:meth:`start_refine`; 0: none).
    """

    def __init__(
        self,
        bases,
        manifold=None,
        database=None,
        prune=DEFAULT_PRUNE,
        load_tables=True,
        scene=None,
        thumbnails=False,
        refine_spp=0,
    ):
        if not bases:
            raise InputError("give at least one basis folder")
        if not 0.0 <= float(prune) < 1.0:
            raise InputError(
                f"`prune` must be in [0, 1) (a fraction of the table's L2 norm), got {prune}"
            )
        self.prune, self._last_blend = float(prune), (None, None)
        self.refine_spp = int(self.number(refine_spp, "`refine_spp`", 0, MAX_SPP, 0))
        self.bases = {}
        self.manifold_path = None
        for name, folder in _names([os.fspath(b) for b in bases]).items():
            basis = Basis.load(folder)
            if basis.p != 1:
                raise InputError(
                    f"basis {folder} has {basis.p} manifold materials {basis.targets}; the "
                    "explorer moves one material (render a basis of a scene with one)"
                )
            if self.manifold_path is None:
                self.manifold_path = os.path.abspath(
                    resolve_manifold(manifold or basis.manifest.manifold)
                )
                self.manifold = Manifold.load(self.manifold_path)
                if database is not None:  # given, so it must be there (the default may be missing)
                    material.check_database(database, self.manifold)
            basis.check_manifold(
                self.manifold
            )  # every basis: rendered with this manifold (loaded once)
            basis.verify()  # every image in memory now: no disk read while dragging
            self.bases[name] = basis
        self.scenes = {name: _scene_of(b, scene) for name, b in self.bases.items()}
        cache = (
            cache_folder(next(iter(self.bases.values())).folder) if load_tables else None
        )  # beside the basis
        self.tables = material.TableStack(self.manifold, database, cache) if load_tables else None
        self._walks, self._walks_lock, self._walks_error = None, threading.Lock(), None
        if (
            self.tables
        ):  # the metric's features of every measured table, prepared once the tables are in
            threading.Thread(target=self._prepare_walks, name="explore-walks", daemon=True).start()
        self.thumbs = None
        if thumbnails:
            from .thumbs import Thumbnails

            self.thumbs = Thumbnails(
                self.manifold_path,
                self.manifold,
                cache_folder(next(iter(self.bases.values())).folder),
                after=self.tables and self.tables.wait,
            )
        self.references = References()
        self.database = database
        self.acquisitions = Acquisitions()
        self._framing = _Count()  # frames being made: the maps' work waits for them
        self._maps, self._maps_lock = {}, threading.Lock()
        self._making = {}  # key -> Event of the maps being made (a second request waits for it)
        threading.Thread(target=self._first_map, name="explore-map", daemon=True).start()

    def _first_map(
        self,
    ):  # meanwhile: the maps the page opens on (coarse, then full), then the float32 cross terms
        try:
            for coarse in (True, False):
                self.map_png("0,1", self.start_point(), coarse=coarse)
        except Exception:  # the page asks for it anyway (and gets the error there)
            pass
        _warm(self.bases)

    # ------------------------------------------------------------ requests
    def key(self, name):
        """Name of a basis (None or "": the first one)."""
        if name is None or name == "":
            return next(iter(self.bases))
        if not isinstance(name, str) or name not in self.bases:
            raise InputError(
                f"unknown basis {show(name)}; this explorer serves {sorted(self.bases)}"
            )
        return name

    def basis(self, name):
        return self.bases[self.key(name)]

    def point(self, value, what="x"):
        """Latent point of a request value (:func:`.inputs.latent_point`)."""
        return latent_point(self.manifold, value, what)

    #: A number of a request in ``[lo, hi]`` (:func:`.inputs.number`).
    number = staticmethod(number)

    def blend(self, name, x, l2="denoised"):
        """Linear image (H, W, 3) of latent point ``x`` and the blend's info (``l2``: of :func:`blend`;
        ``"raw"``, a drag's, has the fireflies of its part beyond L1- clamped:
        :func:`.fireflies.drag_image`); the last one is kept (the exposure slider tonemaps it
        again, without denoising again).
        """
        key, last = (name, np.asarray(x, np.float64).tobytes(), l2), self._last_blend
        if last[0] != key:
            basis = self.basis(name)
            img, info = blend(basis, self.manifold, x=x, prune=self.prune, l2=l2)
            if info.l2 == "raw" and basis.p == 1:  # a drag's frame: no lone bright pixels
                l1, _, _ = compose(basis, info.plan.keys, info.plan.image_weights, None)
                img, _ = fireflies.drag_image(img, l1)
            last = self._last_blend = (key, (img, info))
        return last[1]

    @_one_blas_thread
    def frame(self, name, x, exposure=0.0, fmt="jpeg", coarse=False, rest=False):
        """Encoded frame of ``x``: ``(bytes, meta)``. ``coarse`` (a drag): L2+ summed, not denoised
        (its fireflies clamped). ``rest`` (the page's frame where a drag rests): denoised only
        where that changes the 8-bit image visibly (:func:`.fireflies.rest_change`), else the
        drag's frame (``meta["rest"]``: the estimated change and whether it was denoised).
        """
        if fmt not in encode.FORMATS:
            raise InputError(f"format must be one of {encode.FORMATS}, got {show(fmt)}")
        with self._framing:
            t0 = time.perf_counter()
            rest_meta = None
            if rest and not coarse:
                img, info, rest_meta = self._rest_blend(name, x, exposure)
            else:
                img, info = self.blend(name, x, "raw" if coarse else "denoised")
            t1 = time.perf_counter()
            rgb8 = encode.tonemap(img, exposure)
            t2 = time.perf_counter()
            data = encode.encode(rgb8, fmt)
            t3 = time.perf_counter()
        h, w, _ = img.shape
        return data, {
            "width": w,
            "height": h,
            "format": fmt,
            "n_images": info.n_images,
            "l2": info.l2,
            "blend_ms": 1e3 * (t1 - t0),
            "tonemap_ms": 1e3 * (t2 - t1),
            "encode_ms": 1e3 * (t3 - t2),
            "total_ms": 1e3 * (t3 - t0),
            "rest": rest_meta,
        }

    def _rest_blend(self, name, x, exposure) -> tuple:
        """``(image, info, {"change", "denoised"})`` of the frame where a drag rests: the drag's
        (summed) blend, denoised only where :func:`.fireflies.rest_change` says more than
        :data:`~.fireflies.REST_FRACTION` of the 8-bit values would change.
        """
        img, info = self.blend(name, x, "raw")
        if info.l2 is None:  # no part beyond L1-: nothing to denoise
            return img, info, {"change": 0.0, "denoised": False}
        basis = self.basis(name)
        l1, _, _ = compose(basis, info.plan.keys, info.plan.image_weights, None)
        change = fireflies.rest_change(img, l1, exposure)
        if change <= fireflies.REST_FRACTION:
            return img, info, {"change": change, "denoised": False}
        img, info = self.blend(name, x, "denoised")
        return img, info, {"change": change, "denoised": True}

    def start_point(self):
        """Where the page opens: the measured material closest to the mean of the latent points."""
        lat = self.manifold.latent
        return lat[int(np.argmin(((lat - lat.mean(axis=0)) ** 2).sum(axis=1)))].copy()

    def _prepare_walks(self):
        if self.tables.wait() == "ready":
            try:
                _ = self.walks  # builds the path metric now, off the request path
            except Exception as e:  # no paths nor distances; the rest of the page works
                self._walks_error = f"perceptual metric unavailable: {e}"

    @property
    def walks(self):
        """The :class:`~.walks.Walks` (paths, distances) of the manifold, once the tables are loaded."""
        if not self.tables or self.tables.state != "ready":
            raise InputError(
                "perceptual paths and distances need the material tables: "
                + (self.tables.message if self.tables else "not loaded (--no-tables)")
            )
        with self._walks_lock:
            if self._walks_error:
                raise InputError(self._walks_error)
            if self._walks is None:
                self._walks = Walks(self.manifold, self.tables.metric_rows, pause=self._path_pause)
        return self._walks

    def _path_pause(self) -> None:
        """Called by the path thread before each evaluation of the metric: a frame being made
        goes first (at most :data:`PATH_YIELD` s, so that the path goes on during a drag).
        """
        self._framing.wait_quiet(0.0, PATH_YIELD)

    @_one_blas_thread
    def material(self, x, with_slice=True, live=False):
        """Description of the material at ``x`` (JSON-ready), with the table-based parts
        when the tables are loaded: the negative-bin fraction (while a drag runs, ``live``, that
        of the sphere's coarse table of the point, cached), the measured material nearest
        under the perceptual metric (``measured``: name, distance, and the median spacing of
        the measured materials for scale; not while a drag runs, ``live``) and (``with_slice``)
        the server's BRDF slice image.
        """
        out = material.describe(self.manifold, x, self.prune)
        out["tables"] = self.tables.state if self.tables else "unavailable"
        out["tables_message"] = self.tables.message if self.tables else "not loaded (--no-tables)"
        if self.tables and self.tables.state == "ready":
            _, out["negative_fraction"] = self.tables.preview(x, self.prune, coarse=live)
            # never waits for the metric being prepared (a second or two after the tables)
            out["measured"] = (
                self._walks.nearest_measured(x) if self._walks is not None and not live else None
            )
            kept = [w for w in out["weights"] if w["kept"]]
            if (
                out["measured"] is not None
                and out["n_kept"] == len(kept) == 1
                and kept[0]["w"] == 1.0
            ):
                # the table of one measured material alone: it is that material, at distance 0
                out["measured"] = dict(out["measured"], name=kept[0]["name"], distance=0.0)
            out["live"] = bool(live)
        if self.tables and self.tables.state == "ready" and with_slice:
            rgb, (lo, hi) = material.slice_image(self.tables.slice(x, self.prune))
            out["slice"] = {
                "png": "data:image/png;base64," + base64.b64encode(encode.png_bytes(rgb)).decode(),
                "log10_range": [lo, hi],
                "phi_d_deg": 90.0,
            }
        return out

    @_one_blas_thread
    def preview_table(self, x, coarse=False):
        """Float16 bytes of the reduced interpolated table and its layout (``coarse``: every
        other texel, :meth:`~.material.TableStack.preview`).
        """
        if not self.tables or self.tables.state != "ready":
            raise InputError(self.tables.message if self.tables else "material tables not loaded")
        table, negative = self.tables.preview(x, self.prune, bool(coarse))
        strides = [s * (2 if coarse else 1) for s in material.preview_strides(self.tables.dims)]
        return table.tobytes(), {
            "dims": list(table.shape[1:]),
            "full_dims": list(self.tables.dims),
            "strides": strides,
            "negative_fraction": negative,
            "coarse": bool(coarse),
        }

    def latent_map(self, dims, center, bounds=None):
        """The map of the slice through ``center``; ``bounds``: ``"x0,x1,y0,y1"`` (zoom) or None."""
        dims = self._dims(dims)
        if bounds is not None and bounds != "":
            bounds = self._bounds(bounds)
        else:
            bounds = None
        return latentmap.render(self.manifold, center, dims, bounds=bounds)

    _bounds = staticmethod(extent)

    def _dims(self, dims):
        return map_dims(self.manifold, dims)

    def map_key(self, dims, center, bounds=None, coarse=False):
        """What tells one map of :meth:`map_png` from another: its axes, the slice (the
        coordinates of ``center`` not in ``dims``), its bounds and whether it is coarse.
        """
        dims = self._dims(dims)
        bounds = self._bounds(bounds) if bounds is not None and bounds != "" else None
        c = np.asarray(center, dtype=np.float64)
        return (
            dims,
            tuple(float(v) for k, v in enumerate(c) if k not in dims),
            bounds,
            bool(coarse),
        )

    def map_png(self, dims, center, bounds=None, coarse=False, stale=None):
        """PNG bytes and description of the map of the slice through ``center``.

        The map depends on ``center`` only through the coordinates not in ``dims`` (the
        slice): the last few maps are kept by slice, so moving within the slice (every move
        for ``q = 2``) costs nothing. ``coarse``: a quarter of the pixels (:data:`COARSE_MAP`,
        while a slider or the path scrubber moves the slice). A map takes seconds of CPU where
        a frame takes milliseconds: it is made once (a request for a map being made waits for
        it), a few rows at a time, each waiting while a drag's frames come (until they pause for
        :data:`DRAG_QUIET`, at most :data:`FRAME_WAIT`: the frames go first), and ``stale()``,
        when given, is asked before each: it raises to abandon a map no longer wanted (the
        session's :class:`~.session.Superseded`, a newer map asked for).
        """
        key = self.map_key(dims, center, bounds, coarse)
        dims, bounds = key[0], key[2]
        c = np.asarray(center, dtype=np.float64)
        with self._maps_lock:
            if key in self._maps:
                self._maps[key] = self._maps.pop(key)  # most recently used last
                return self._maps[key]
            making = self._making.get(key)
            if making is None:
                made_here = making = self._making[key] = threading.Event()
            else:
                made_here = None
        if made_here is None:  # the same map is being made (the first map, another tab): waits
            while not making.wait(MAP_POLL):
                if stale is not None:
                    stale()
            with self._maps_lock:
                if key in self._maps:
                    return self._maps[key]
            return self.map_png(dims, center, bounds, coarse, stale)  # abandoned there: made here

        def pause():
            self._framing.wait_quiet(DRAG_QUIET, FRAME_WAIT)
            if stale is not None:
                stale()

        try:
            m = latentmap.render(
                self.manifold,
                c,
                dims,
                resolution=COARSE_MAP if coarse else FULL_MAP,
                bounds=bounds,
                pause=pause,
            )
            out = (encode.png_bytes(m.image), dict(m.info(), slice=[list(dims), list(key[1])]))
            with self._maps_lock:
                self._maps[key] = out
                while len(self._maps) > MAPS_KEPT:
                    self._maps.pop(next(iter(self._maps)))
        finally:
            with self._maps_lock:
                self._making.pop(key, None)
            made_here.set()
        return out

    def snippet_folder(self):
        """The folder the snippets name the manifold relative to by default: that of the first
        basis's scene (a snippet pasted into that scene finds the manifold).
        """
        scene = next(iter(self.scenes.values()))
        return os.path.dirname(os.path.abspath(scene)) if scene else os.getcwd()

    def snippets(self, x, folder=None):
        """``<bsdf>`` XML and ``mi.load_dict`` Python for ``x``, naming the manifold through a
        ``$manifold`` parameter whose default is its path relative to ``folder`` (the scene's
        folder: Mitsuba resolves it from there; default :meth:`snippet_folder`), so that a scene
        and its manifold moved together still render.
        """
        folder = self.snippet_folder() if folder is None or folder == "" else folder
        if not isinstance(folder, str) or len(folder) > 4096 or not os.path.isabs(folder):
            raise InputError(
                f"folder must be an absolute folder path (the scene's), got {show(folder)}"
            )
        rel = os.path.relpath(self.manifold_path, os.path.normpath(folder)).replace(os.sep, "/")
        xs = ", ".join(f"{v:.6g}" for v in x)
        xml = (
            f"<!-- in the <scene>, before this: the manifold, relative to the scene file's folder -->\n"
            f'<default name="manifold" value="{escape(rel, {chr(34): "&quot;"})}"/>\n\n'
            f'<bsdf type="manifold_brdf" id="material">\n'
            f'    <string name="manifold" value="$manifold"/>\n'
            f'    <string name="x" value="{xs}"/>\n'
            f"</bsdf>"
        )
        py = (
            'import os\n\nimport mitsuba as mi\nimport mitsuba_manifold\n\nmi.set_variant("llvm_ad_rgb")\n'
            "mitsuba_manifold.register()\n"
            f"# the manifold, relative to the folder of this script (or set MANIFOLD)\n"
            f'manifold = os.environ.get("MANIFOLD", os.path.join(os.path.dirname(os.path.abspath(__file__)), '
            f"{json.dumps(rel)}))\n"
            f'bsdf = mi.load_dict({{"type": "manifold_brdf", "manifold": manifold, "x": "{xs}"}})'
        )
        return {
            "xml": xml,
            "python": py,
            "x": [float(v) for v in x],
            "folder": folder,
            "manifold": rel,
        }

    def path_command(self, name, a, b, steps, kind=None):
        """The ``tools/blend.py --path`` command rendering the sequence from ``a`` to ``b``
        (``kind``: its ``--path-kind``; None: blend.py's default, the same as :meth:`route`'s).
        """
        basis = self.basis(name)
        kind = None if kind is None or kind == "" else self._kind(kind)
        ends = []
        for v, what in ((a, "a"), (b, "b")):
            if isinstance(v, str) and v.strip() in self.manifold.names:
                ends.append(v.strip())
            else:
                ends.append(",".join(f"{c:.6g}" for c in self.point(v, what)))
        if ends[0] == ends[1]:
            raise InputError("the path's two ends are the same point; choose two different ends")
        steps = int(self.number(steps, "steps", 2, 1000, 20))
        tool = os.path.join(TOOLS, "blend.py")  # absolute: the command works pasted in any folder
        head = ["python3", tool] if os.path.isfile(tool) else ["mitsuba-manifold", "blend"]
        return shlex.join(
            head
            + [
                "--basis",
                os.path.abspath(basis.folder),
                "--manifold",
                self.manifold_path,
                "--path",
                ends[0],
                ends[1],
                "--steps",
                str(steps),
            ]
            + (["--path-kind", kind] if kind else [])
            + ["--out", "path.exr", "--png"]
        )

    def route(self, a, b, steps=None, kind=None):
        """Future of the path from ``a`` to ``b`` (material names or points) of ``kind``
        (default: :data:`Manifold.path`'s), ``steps`` points (:meth:`.walks.Walks.submit`).
        """
        kind = path_kinds.DEFAULT_KIND if kind is None or kind == "" else self._kind(kind)
        steps = int(self.number(steps, "steps", 2, MAX_STEPS, STEPS))
        return self.walks.submit(self.point(a, "a"), self.point(b, "b"), steps, kind)

    _kind = staticmethod(path_kind)

    def info(self):
        m = self.manifold
        bases = [
            {
                "name": n,
                "folder": b.folder,
                "resolution": list(b.resolution),
                "spp": b.manifest.spp,
                "scene": self.scenes[n] or b.manifest.scene,
                "images": len(b.keys),
                "scene_available": self.scenes[n] is not None,
            }
            for n, b in self.bases.items()
        ]
        return {
            "manifold": self.manifold_path,
            "q": m.q,
            "names": m.names,
            "latent": m.latent.tolist(),
            "albedos": None if m.albedos is None else m.albedos.tolist(),
            "bases": bases,
            "prune": self.prune,
            "tables": self.tables.state if self.tables else "unavailable",
            "max_reference_spp": MAX_SPP,
            "refine_spp": self.refine_spp,
            "thumbs": self.thumbs.info() if self.thumbs else None,
            "path_kinds": list(path_kinds.KINDS),
            "path_kind": path_kinds.DEFAULT_KIND,
            "snippet_folder": self.snippet_folder(),
            "max_upload": MAX_UPLOAD,
        }

    def environment(self, name):
        """The environment light of basis ``name``'s scene as its camera sees it, for the preview
        sphere: float16 RGB bytes of a :data:`~.hdri.WIDTH` x :data:`~.hdri.HEIGHT`
        equirectangular map in the sphere's frame (``y`` up, ``z`` towards the viewer; the
        layout of :mod:`.hdri`) and ``{"width", "height", "emitter"}``; the scene's point lights
        in ``"lights"`` (direction in that frame, irradiance at the centre of the scene's
        manifold-material shapes). Raises InputError when the scene is missing or has no
        environment light.
        """
        key = self.key(name)
        with self._maps_lock:
            if ("env", key) in self._maps:
                return self._maps[("env", key)]
        basis, scene_path = self.bases[key], self.scenes[key]
        if scene_path is None:
            raise InputError(
                f"the scene of basis {key!r} is missing or has changed; start with --scene "
                "to light the sphere like it"
            )
        out = hdri.scene_environment(scene_path, self.manifold_path, basis)
        with self._maps_lock:
            self._maps[("env", key)] = out
        return out

    # ---------------------------------------------------------- references
    def _job_args(self, name, x, spp, default):
        """``(key, basis, scene, spp, blend image)`` of a background job of basis ``name`` at ``x``."""
        name = self.key(name)
        basis, scene = self.bases[name], self.scenes[name]
        if scene is None:
            raise InputError(
                f"the scene of basis {name!r} ({basis.manifest.scene}) is missing or has "
                "changed since the basis was rendered; give it with --scene"
            )
        return (
            name,
            basis,
            scene,
            int(self.number(spp, "spp", 1, MAX_SPP, default)),
            self.blend(name, x)[0],
        )

    def start_reference(self, name, x, spp, tab=None):
        """A full-GI reference render at ``x`` in the background (``tab``: the page asking)."""
        name, basis, scene, spp, img = self._job_args(name, x, spp, 256)
        return self.references.submit(
            name, basis, scene, self.manifold_path, x, spp, img, tab=_tab(tab)
        )

    def start_refine(self, name, x, spp, tab=None):
        """A refinement of the blend at ``x`` (``blend.py --refine``) in the background."""
        name, basis, scene, spp, img = self._job_args(name, x, spp, 16)
        where = {"scene": scene, "manifold_file": self.manifold_path, "prune": self.prune}
        return self.references.submit_refine(
            name, basis, self.manifold, x, spp, img, tab=_tab(tab), **where
        )

    def reference_image(self, job_id, which, exposure=0.0):
        job = self.references.get(job_id)
        if job is None:
            raise InputError(f"unknown reference job {show(job_id)}")
        if job.state != "done" and not (
            job.kind == "refine" and job.images
        ):  # a refinement: after each pass
            raise InputError(f"reference job {job_id} is {job.state}, not done")
        if which == "error":
            from ...imaging.metrics import error_image, false_colour

            other = job.images["reference"] if "reference" in job.images else job.images["refined"]
            rgb, _ = false_colour(error_image(job.images["blend"], other))
            return encode.png_bytes(rgb)
        if which not in job.images:
            raise InputError(
                f"image must be 'blend', 'reference', 'refined' or 'error', got {show(which)}"
            )
        return encode.png_bytes(encode.tonemap(job.images[which], exposure))

    # --------------------------------------------------------- acquisition
    def start_acquire(self, name, photo, mask=None):
        """Acquire the material of a photo of basis ``name``'s scene in the background
        (:mod:`.acquire`): ``photo`` and ``mask`` are files' contents as base64 (data: URLs),
        decoded and checked here (InputError naming what is wrong); returns the job.
        """
        name = self.key(name)
        basis = self.bases[name]
        target, m, notes = read_upload(photo, mask, basis.resolution)
        return self.acquisitions.submit(self, name, target, m, notes)

    def close(self, wait=0.0):
        """Stop the reference renders (waits up to ``wait`` s); returns whether none still runs."""
        if self.thumbs:
            self.thumbs.close()
        self.acquisitions.close()
        return self.references.shutdown(wait)


class _Count:
    """How many threads are inside ``with`` it, and when the last one left; :meth:`wait_quiet`
    waits for none to be inside for a while.
    """

    def __init__(self):
        self._n, self._idle = 0, threading.Condition()
        self._left = float("-inf")  # time.monotonic() of the last exit

    def __enter__(self):
        with self._idle:
            self._n += 1

    def __exit__(self, *exc):
        with self._idle:
            self._n -= 1
            self._left = time.monotonic()
            if not self._n:
                self._idle.notify_all()

    def wait_quiet(self, quiet, timeout):
        """Wait until no thread has been inside for ``quiet`` s, at most ``timeout`` s; returns
        whether that is so.
        """
        end = time.monotonic() + timeout
        with self._idle:
            while True:
                now = time.monotonic()
                calm = 0.0 if self._n else quiet - (now - self._left)
                if not self._n and calm <= 0:
                    return True
                if now >= end:
                    return False
                self._idle.wait(min(end - now, calm) if not self._n else end - now)


def _tab(tab):
    """The page id of a job (None: no page), or InputError."""
    if tab is None or tab == "":
        return None
    if not isinstance(tab, str) or len(tab) > 64 or not tab.isascii() or not tab.isprintable():
        raise InputError(
            f"tab must be the page's id (at most 64 ASCII characters), got {show(tab)}"
        )
    return tab

"""What the page shows about the material at a latent point (paper Sec. 3 and Eq. 2).

:func:`describe` gives the weights (largest first, each saying whether pruning keeps it), the albedo, the GP predictive
variance of Eq. 2 (as a confidence) and the nearest training materials from the
:class:`~mitsuba_manifold.manifold.model.Manifold`'s public methods alone. :class:`TableStack`
adds what needs the tables themselves, from a reduced copy held in memory (one
matrix-vector product per point):

- the interpolated table at reduced resolution, in 16-bit floats, for the WebGL preview
  (every ``stride``-th bin along each axis, so each value is a true bin of the table);
- the fraction of negative bins of the interpolated table, estimated on those bins
  (``manifold_brdf`` clamps them to 0; a blend of images cannot);
- a ``theta_h x theta_d`` slice at ``phi_d = 90 deg`` at full resolution, for a log plot;
- the bins of the perceptual metric's search sub-grid (:func:`.walks.metric_columns`), for
  the paths and the distance to the nearest measured material (:mod:`.walks`).

Reading every table takes seconds per hundred MERL tables; the reduced copy is therefore
cached (``preview-<key>.npz`` in a cache folder, by default ``<basis>/.manifold-cache``),
named by the content hashes of the tables the manifold was fit on: the next start reads
that one file and opens no table.
"""

from __future__ import annotations

import math
import os
import threading
from typing import TYPE_CHECKING

import cachetools
import numpy as np

from ..._util.float32 import weights32
from .walks import metric_columns

if TYPE_CHECKING:
    from typing import Any


#: Largest preview table (n_theta_h, n_theta_d, n_phi_d) sent to the browser.
PREVIEW_DIMS = (45, 45, 90)
#: Weights shown in the bar chart.
TOP_WEIGHTS = 12
NEAREST = 5
HALF_MAX = float(np.finfo(np.float16).max)
#: Preview tables kept for repeated requests at the same point.
RECENT = 4
#: Version of the cached reduced tables (part of the cache key).
CACHE_VERSION = "explore-preview-v2"


def describe(manifold, x, prune) -> dict[str, Any]:
    """Weights, albedo, variance and neighbours of latent point ``x`` (q,), as JSON-ready dict."""
    _, w = manifold.weights(x)
    report = manifold.prune_report(w, prune)  # what pruning keeps and the bounds it reaches
    keep, dropped = report.keep, report.dropped
    order = np.argsort(-np.abs(w))
    kept = set(int(i) for i in np.asarray(keep).ravel())
    top = [
        {"name": manifold.names[i], "w": float(w[i]), "kept": int(i) in kept}
        for i in order[:TOP_WEIGHTS]
    ]
    dist = np.linalg.norm(manifold.latent - np.asarray(x, dtype=np.float64)[None], axis=1)
    near = np.argsort(dist)[:NEAREST]
    out = {
        "x": [float(v) for v in x],
        "weights": top,
        "n_kept": int(len(keep)),
        "dropped_weight": float(dropped),
        "negative_weight": float(-w[w < 0].sum()),
        "pruning": str(report),
        "pruning_albedo": None
        if report.albedo_change is None
        else float(max(report.albedo_change)),
        "pruning_albedo_budget": report.albedo_budget,
        "variance": max(0.0, float(manifold.variance(x))),
        "prior_variance": 1.0 + manifold.noise,
        "nearest": [{"name": manifold.names[i], "distance": float(dist[i])} for i in near],
        "albedo": None,
    }
    if manifold.albedos is not None:
        out["albedo"] = [float(v) for v in manifold.albedo(x)]
    return out


def check_database(folder, manifold) -> None:
    """Raise :class:`InputError` naming ``folder`` (an explicitly given ``--database``: a folder
    or a built-in set's name) unless it holds a table for each of ``manifold``'s materials.

    Only the sources are checked here, at once; the content hashes are checked while the
    tables load (:class:`TableStack`).
    """
    from ...data.database import Database, split_spec
    from ...data.sources import EXTENSIONS, SET_NAMES
    from ...errors import InputError, MitsubaManifoldError

    folder = os.fspath(folder)
    base, _ = split_spec(folder)
    if base not in SET_NAMES and not os.path.exists(base):
        raise InputError(
            f"--database {folder} does not exist; give the folder of the manifold's tables or a "
            f"built-in database ({', '.join(SET_NAMES)}), or leave --database out (default: the "
            "manifold's database)"
        )
    if base not in SET_NAMES and not os.path.isdir(base):
        raise InputError(
            f"--database {folder} is a file, not a database folder (a folder of <name>.binary "
            "MERL tables); give the folder of the manifold's tables"
        )
    empty = base not in SET_NAMES and not any(f.endswith(EXTENSIONS) for f in os.listdir(base))
    try:
        available = set() if empty else set(Database(folder).names)
    except (MitsubaManifoldError, OSError) as e:
        raise InputError(
            f"--database {folder} is not a database of this manifold ({e}); give the "
            "folder of its tables, or leave --database out"
        ) from None
    missing = [n for n in manifold.names if n not in available]
    if missing:
        raise InputError(
            f"--database {folder} is not a database folder of this manifold: it holds no table for "
            f"{len(missing)} of its {manifold.n} materials ({', '.join(missing[:3])}"
            f"{' ...' if len(missing) > 3 else ''}); give the folder of its tables (<name>.binary), "
            "or leave --database out"
        )


def preview_strides(dims, target=PREVIEW_DIMS) -> tuple:
    """Bin stride per axis so the preview table is at most ``target``."""
    return tuple(max(1, math.ceil(n / t)) for n, t in zip(dims, target))


class TableStack:
    """Reduced tables of every material of a manifold, loaded in a background thread.

    Parameters
    ----------
    manifold : Manifold
    database : str, optional
        Folder of the tables (default: the manifold's; checked against its hashes).
    cache_dir : str, optional
        Folder for the cached reduced tables (none: no cache).

    Attributes
    ----------
    state : {"loading", "ready", "unavailable"}
    message : str
        Why the tables are unavailable (or the loading progress).
    dims : tuple
        Full table resolution; ``preview_dims``: the reduced one.
    """

    def __init__(self, manifold, database=None, cache_dir=None) -> None:
        self.manifold = manifold
        self.database = database
        self.cache_dir = cache_dir
        self.state, self.message = "loading", "loading tables"
        self.dims = self.preview_dims = self.metric_rows = self._coarse = None
        self._ready = threading.Event()
        self._recent: cachetools.FIFOCache
        self._recent, self._recent_lock = cachetools.FIFOCache(RECENT), threading.Lock()
        self._thread = threading.Thread(target=self._load, name="explore-tables", daemon=True)
        self._thread.start()

    def wait(self, timeout=None) -> str:
        """Block until loaded (or failed); returns the state."""
        self._ready.wait(timeout)
        return self.state

    def cache_path(self) -> str | None:
        """The cache file of this manifold's reduced tables (named by the tables' hashes), or None."""
        if self.cache_dir is None:
            return None
        from ..._util.cache import key_hash

        key = key_hash(CACHE_VERSION, str(PREVIEW_DIMS), *self.manifold.hashes, length=24)
        return os.path.join(self.cache_dir, f"preview-{key}.npz")

    def _load(self) -> None:
        try:
            cached = self._read_cache()
            dims, reduced, slices, preview_dims, metric = (
                cached if cached is not None else self._read_tables()
            )
            self.preview_dims, self.metric_rows = preview_dims, metric
            self.dims, self._reduced, self._slices = dims, reduced, slices
            full = reduced.reshape(
                (-1, 3) + tuple(preview_dims)
            )  # a drag's tables, made before the first drag
            self._coarse = np.ascontiguousarray(full[:, :, ::2, ::2, ::2]).reshape(len(full), -1)
            n = self.manifold.n
            self.state, self.message = (
                "ready",
                f"{n} tables, preview {self.preview_dims}"
                + (" (cached)" if cached is not None else ""),
            )
            if cached is None:
                self._write_cache()
        except Exception as e:  # a missing or changed database leaves the rest of the page working
            self.state, self.message = "unavailable", f"material tables unavailable: {e}"
        finally:
            self._ready.set()

    def _read_tables(self) -> tuple:
        db = self.manifold.open_database(self.database)
        dims = tuple(int(v) for v in db.dims)
        s = preview_strides(dims)
        n = self.manifold.n
        slice_col = min(dims[2] // 2, dims[2] - 1)  # phi_d = 90 deg
        reduced, slices, preview_dims = (
            None,
            np.empty((n, 3, dims[0], dims[1]), dtype=np.float32),
            None,
        )
        cols = metric_columns(dims)
        metric = np.empty((n, cols.size), dtype=np.float32)
        for i, name in enumerate(self.manifold.names):
            table = db.reflectance(name)
            metric[i] = table.reshape(-1)[cols]
            small = np.ascontiguousarray(table[:, :: s[0], :: s[1], :: s[2]], dtype=np.float32)
            if reduced is None:
                reduced = np.empty((n, small.size), dtype=np.float32)
                preview_dims = small.shape[1:]
            reduced[i] = small.ravel()
            slices[i] = table[:, :, :, slice_col]
            self.message = f"loading tables {i + 1}/{n}"
        return dims, reduced, slices.reshape(n, -1), tuple(preview_dims), metric

    def _read_cache(self) -> tuple | None:
        path = self.cache_path()
        if path is None or not os.path.isfile(path):
            return None
        try:
            with np.load(path, allow_pickle=False) as f:
                dims, preview_dims = (
                    tuple(int(v) for v in f["dims"]),
                    tuple(int(v) for v in f["preview_dims"]),
                )
                reduced, slices, metric = f["reduced"], f["slices"], f["metric"]
        except (OSError, ValueError, KeyError):
            return None
        n = self.manifold.n
        if (
            reduced.shape != (n, 3 * int(np.prod(preview_dims)))
            or slices.shape != (n, 3 * dims[0] * dims[1])
            or metric.shape != (n, metric_columns(dims).size)
        ):
            return None
        return dims, reduced, slices, preview_dims, metric

    def _write_cache(self) -> None:
        path = self.cache_path()
        if path is None:
            return
        from ..._util.atomic import atomic_write

        try:
            os.makedirs(os.path.dirname(path), exist_ok=True)
            atomic_write(
                path,
                lambda f: np.savez(
                    f,
                    dims=np.array(self.dims),
                    preview_dims=np.array(self.preview_dims),
                    reduced=self._reduced,
                    slices=self._slices,
                    metric=self.metric_rows,
                ),
            )
        except OSError:  # a read-only place: no cache, the page works the same
            pass

    def _combine(self, rows, x, prune):
        _, w = self.manifold.weights(x)
        keep, w_kept, _ = self.manifold.prune(w, prune)
        return weights32(w_kept) @ rows[keep]

    def preview(self, x, prune, coarse=False) -> tuple:
        """Interpolated table at reduced resolution: float16 (3, n_h, n_d, n_p), and the
        fraction of those bins below 0 (an estimate of the full table's).

        ``coarse``: every other texel of that along each axis (an eighth of the work and of
        the bytes: the page's sphere while a drag runs). The page asks for the material's
        description and its table at the same point: the last few answers are kept.
        """
        return self._preview(x, prune, coarse)

    @cachetools.cachedmethod(
        lambda self: self._recent,
        key=lambda self, x, prune, coarse: (
            np.asarray(x, dtype=np.float64).tobytes(),
            float(prune),
            bool(coarse),
        ),
        lock=lambda self: self._recent_lock,
    )
    def _preview(self, x, prune, coarse) -> tuple[Any, float]:
        table = self._combine(self._coarse if coarse else self._reduced, x, prune)
        negative = float((table < 0).mean())
        half = np.clip(table, -HALF_MAX, HALF_MAX).astype(np.float16)  # peaks above 65504 saturate
        dims = tuple(-(-d // 2) for d in self.preview_dims) if coarse else tuple(self.preview_dims)
        return half.reshape((3,) + dims), negative

    def slice(self, x, prune) -> np.ndarray:
        """``theta_h x theta_d`` slice at ``phi_d = 90 deg``: float32 (3, n_h, n_d)."""
        return self._combine(self._slices, x, prune).reshape(3, self.dims[0], self.dims[1])


def slice_image(slice_rgb, floor=1e-3, cmap="magma") -> tuple[np.ndarray, tuple[float, float]]:
    """8-bit RGB image of ``log10`` of a slice's mean over RGB, ``theta_d`` right, ``theta_h`` up.

    Values at or below ``floor`` (negative ones included) show at the bottom of the colour
    map. Returns ``(rgb (n_h, n_d, 3), (lo, hi))``: the log10 range mapped.
    """
    from matplotlib import colormaps

    v = np.log10(np.maximum(slice_rgb.mean(axis=0), floor))
    lo, hi = float(np.log10(floor)), float(max(v.max(), np.log10(floor) + 1.0))
    rgba = colormaps[cmap]((v - lo) / (hi - lo), bytes=True)
    return np.ascontiguousarray(rgba[::-1, :, :3]), (lo, hi)

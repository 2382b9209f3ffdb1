"""Pruning benchmark: what the kept materials change in the table, its albedo and the image.

The previous release's rule (``raw-l2``: the raw table within 1% of its L2 norm) against the
new default (``image``: each albedo channel within 0.5%, the cosine-weighted and the raw
table within 1%) and the levers behind the choice (other budgets; the albedo bound alone;
the cosine-weighted bound alone; both without the raw bound), on two sets of 200 latent
points of the manifold:

* ``tune`` (seed 0), the set the default was chosen on: the midpoint of each material and
  its nearest latent neighbour (100) and 100 uniform points of the latent box (10% margin);
* ``held_out`` (seed 1), never tuned on: the midpoint of each material and a neighbour drawn
  among its 3 nearest, and 100 other uniform points of the box.

Per configuration and set: the relative change of the albedo (the largest of the three
channels per point: median, 90th percentile, max), the relative cosine-weighted and raw L2
changes of the table, the materials kept, and with a basis (``--basis``) the relative MSE
(:func:`imaging.metrics.rel_mse`) of the blend of the pruned weights against the blend of
the unpruned ones on the same basis (so the basis's noise cancels to first order). The
time of one ``Manifold.prune`` call is the mean over the 400 points, median of 3 repeats.
"""

import time

import numpy as np

from mitsuba_manifold.basis.blend import blend
from mitsuba_manifold.basis.folder import Basis
from mitsuba_manifold.imaging.metrics import rel_mse
from mitsuba_manifold.manifold import pruning, space
from mitsuba_manifold.manifold.model import DEFAULT_PRUNE, Manifold

from .common import peak_rss_gib

#: What the default must reach at every point of both sets (and the median kept).
TARGETS = {"albedo_change": 5e-3, "image_rel_mse": 1e-4, "median_kept": 10}
#: Configurations: the library's two rules at their defaults (timed through ``Manifold.prune``)
#: and the levers (``pruning`` called directly: rule, budget, albedo and raw shares of the budget).
_SHARES = (pruning.ALBEDO_SHARE, pruning.RAW_SHARE)
CONFIGS = {
    "raw-l2 (previous default)": ("raw-l2", 1e-2, None, None),
    "image (default)": ("image", DEFAULT_PRUNE) + _SHARES,
    "image, budget 0.5%": ("image", 5e-3) + _SHARES,
    "image, budget 2%": ("image", 2e-2) + _SHARES,
    "image, budget 5%": ("image", 5e-2) + _SHARES,
    "albedo 0.5% + cosine-weighted 1%, no raw bound": ("image", 1e-2, pruning.ALBEDO_SHARE, np.inf),
    "albedo 0.5% only": ("image", 1e6, 5e-3 / 1e6, np.inf),
    "cosine-weighted 1% only": ("image", 1e-2, np.inf, np.inf),
    "raw-l2 0.1%": ("raw-l2", 1e-3, None, None),
}
MAIN = ("raw-l2 (previous default)", "image (default)")


def point_sets(latent, n_box=100):
    """``{"tune": (2N', q), "held_out": ...}``: neighbour midpoints and box points (module docstring)."""
    d2 = ((latent[:, None] - latent[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    near = np.argsort(d2, axis=1)[:, :3]
    lo, hi = space.latent_box(latent)
    out = {}
    for name, seed in (("tune", 0), ("held_out", 1)):
        rng = np.random.default_rng(seed)
        j = (
            near[:, 0]
            if seed == 0
            else near[np.arange(len(latent)), rng.integers(0, 3, len(latent))]
        )
        box = lo + rng.random((n_box, latent.shape[1])) * (hi - lo)
        out[name] = np.r_[0.5 * (latent + latent[j]), box]
    return out


def _stats(v):
    v = np.asarray(v, dtype=np.float64)
    return {
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "max": float(v.max()),
    }


def _keep(cfg, w, G, C, A):
    rule, budget, share, raw = cfg
    if rule == "raw-l2":
        return pruning.prune(w, G, budget)[0]
    return pruning.prune_image(w, C, A, budget, share, G=G, raw_share=raw)[0]


def _measure(m, W, cfg, grams, basis):
    G, C, A = grams
    rows = {"albedo": [], "cos": [], "raw": [], "kept": [], "image": []}
    for w in W:
        keep = _keep(cfg, w, G, C, A)
        r = pruning.report(w, keep, cfg[0], cfg[1], G=G, C=C, albedos=A)
        rows["albedo"].append(max(r.albedo_change))
        rows["cos"].append(r.cos_error)
        rows["raw"].append(r.raw_error)
        rows["kept"].append(r.kept)
        if basis is not None:
            wp = np.zeros_like(w)
            wp[keep] = w[keep] * (w.sum() / w[keep].sum())
            full = blend(basis, m, w=w, prune=0.0, l2="raw")[
                0
            ]  # linear: what pruning changes, not OIDN
            rows["image"].append(rel_mse(blend(basis, m, w=wp, prune=0.0, l2="raw")[0], full))
    out = {
        "albedo_change": _stats(rows["albedo"]),
        "cos_error": _stats(rows["cos"]),
        "raw_error": _stats(rows["raw"]),
        "kept": {"median": float(np.median(rows["kept"])), "max": int(max(rows["kept"]))},
    }
    if rows["image"]:
        out["image_rel_mse"] = _stats(rows["image"])
    out["meets"] = {
        "albedo_change": out["albedo_change"]["max"] <= TARGETS["albedo_change"],
        "median_kept": out["kept"]["median"] <= TARGETS["median_kept"],
    }
    if rows["image"]:
        out["meets"]["image_rel_mse"] = out["image_rel_mse"]["max"] <= TARGETS["image_rel_mse"]
    return out


def _time_prune(m, W, rule, budget, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for w in W:
            m.prune(w, budget, rule=rule)
        times.append((time.perf_counter() - t0) / len(W))
    return 1e3 * float(np.median(times))


def run(folder, manifold=None, basis=None, repeats=3, configs=None, progress=True):
    """Measure every configuration of :data:`CONFIGS` (or those named in ``configs``) on both point
    sets; see the module docstring. ``folder``: the database (the manifold's, when ``manifold``
    is None a default fit on it); ``basis``: a one-target basis folder of the manifold, for the
    image changes (skipped without one).
    """
    t0 = time.perf_counter()
    m = Manifold.load(manifold) if manifold else Manifold.fit(folder)
    database = folder if manifold else None
    m.tables(database)
    t_tables = time.perf_counter() - t0
    t0 = time.perf_counter()
    store = m._store
    grams = (store.raw_gram(m.database), store.cosine_gram(m.database), store.albedo(m.database))
    t_grams = time.perf_counter() - t0
    b = None
    if basis:
        b = Basis.load(basis, manifold=m)
        b.read(b.keys + ["base"])
    sets = point_sets(m.latent)
    weights = {name: m.weights(X).w for name, X in sets.items()}
    every = np.concatenate(list(weights.values()))
    result = {
        "n_materials": m.n,
        "dims": list(m.dims or ()),
        "preset": m.info.get("preset"),
        "interpolant": m.interpolant.params(),
        "basis": None if b is None else repr(b),
        "points": {k: len(v) for k, v in sets.items()},
        "targets": TARGETS,
        "load_s": t_tables,
        "grams_s": t_grams,
        "configs": {},
    }
    for name in configs or CONFIGS:
        cfg = CONFIGS[name]
        finite = [
            None if v is None or not np.isfinite(v) else v for v in cfg[2:]
        ]  # None: unbounded
        row = {"rule": cfg[0], "budget": cfg[1], "albedo_share": finite[0], "raw_share": finite[1]}
        for set_name, W in weights.items():
            row[set_name] = _measure(m, W, cfg, grams, b)
        if name in MAIN:
            row["ms_per_prune_call"] = _time_prune(m, every, cfg[0], cfg[1], repeats)
        result["configs"][name] = row
        if progress:
            t, h = row["tune"], row["held_out"]
            img = (
                ""
                if b is None
                else (
                    f", image rel. MSE max {t['image_rel_mse']['max']:.2g} / "
                    f"{h['image_rel_mse']['max']:.2g}"
                )
            )
            print(
                f"  {name}: albedo max {t['albedo_change']['max']:.2%} / {h['albedo_change']['max']:.2%}, "
                f"kept median {t['kept']['median']:g} / {h['kept']['median']:g}{img}",
                flush=True,
            )
    result["peak_rss_gib"] = peak_rss_gib()
    return result

"""``tools/bench.py match``: speed and accuracy of :func:`mitsuba_manifold.basis.inverse.match.match`.

- ``speed``: match time for a full basis (default: N = 100, 256x256) held in memory, per
  setting (relative MSE, exposure-free, masked, log luminance, starts from the nearest
  training points only), for targets that are blends at points between neighbouring
  training points (their L1- blends, which :func:`~mitsuba_manifold.basis.inverse.match.match` fits,
  also on a full-GI basis; ``recovered``: error < 1e-6), and the time to read the basis; target:
  at most 2 s.
- ``scenes`` (``table.xml``, ``sphere.xml``, small renders), per scene:
  1. ``random_points``: targets rendered with Mitsuba's ``path`` at random latent points in
     the data's region (between neighbouring training points, GP variance < 0.5, at most
     0.1% clamped table values): the recovered point's image error against the blend's own
     error at the true point (``ratio``, target <= 1.5), and the log-RMS table error of the
     recovered material (``log1p`` of the tables, as the ``log`` features);
  2. ``held_out``: a manifold fit on the other materials (the saved Gram matrix, centred
     again), its basis, and targets rendered from the held-out materials' own tables: the
     match's error against the best single training material's (target: better on >= 8 of 10);
  3. ``masked`` (object-only mask, the rest of the target altered) and ``exposure``
     (target scaled, matched exposure-free).
"""

import os
import time

import numpy as np

from mitsuba_manifold.basis.blend import blend
from mitsuba_manifold.basis.folder import BASE, Basis
from mitsuba_manifold.basis.inverse import match as mt
from mitsuba_manifold.basis.inverse.objectives import masked_rel_mse
from mitsuba_manifold.data.database import database_cache
from mitsuba_manifold.imaging.metrics import rel_mse
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.render.jobs.render_basis import render_basis
from mitsuba_manifold.render.scene.scenes import (
    load_scene,
    render_reference,
    scene_path,
    use_variant,
)

from .common import work_manifold

SPEED_TARGET_S = 2.0
RATIO_TARGET = 1.5


def _median(fn, repeats):
    """Median and max wall time of ``repeats`` calls of ``fn()``, the median CPU time of this
    process (all its threads), and the last result.
    """
    times, cpus, out = [], [], None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return float(np.median(times)), float(np.max(times)), float(np.median(cpus)), out


def bench_speed(basis_folder, manifold=None, n_targets=5, repeats=3, seed=0):
    """Match times on a basis already in memory (median over targets and repeats)."""
    t0 = time.perf_counter()
    basis = Basis.load(basis_folder, manifold=manifold)
    m = basis.check_manifold(manifold)
    basis.read([BASE] + m.names)
    t_read = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    pts = _interior_points(m, n_targets, rng, clamp=None)
    w, h = basis.resolution
    mask = np.zeros((h, w))
    mask[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4] = 1.0
    settings = {
        "rel_mse": {},
        "exposure_free": {"exposure_free": True},
        "masked": {"mask": mask},
        "log": {"loss": "log"},
        "nearest_starts_only": {"scan": 0},
    }
    out = {
        "basis": os.path.abspath(basis_folder),
        "n_materials": m.n,
        "resolution": [w, h],
        "read_basis_s": t_read,
        "target_s": SPEED_TARGET_S,
        "settings": {},
        "load_average": os.getloadavg(),
    }
    for name, kw in settings.items():
        meds, maxes, cpus, errs = [], [], [], []
        for x in pts:
            # the match fits the L1- blend (Eq. 13): so is the target, whatever the basis holds
            target = blend(basis, m, x=x, prune=0.0, component="l1")[0]
            target = target * (1.7 if kw.get("exposure_free") else 1.0)
            med, mx, cpu, r = _median(lambda: mt.match(basis, target, manifold=m, **kw), repeats)
            meds.append(med)
            maxes.append(mx)
            cpus.append(cpu)
            errs.append(r.error)
        out["settings"][name] = {
            "median_s": float(np.median(meds)),
            "max_s": float(np.max(maxes)),
            "cpu_median_s": float(np.median(cpus)),
            "max_error": float(np.max(errs)),
            "errors": errs,
            "recovered": int(np.sum(np.array(errs) < 1e-6)),
            "of": len(errs),
            "meets_target": bool(np.median(meds) <= SPEED_TARGET_S),
        }
    return out


# ------------------------------------------------------------------ targets


def _interior_points(m, n, rng, clamp=1e-3, max_tries=400):
    """``n`` latent points between a training point and one of its 3 nearest neighbours
    (``t`` in [0.25, 0.75]), with GP variance < 0.5 and (``clamp``) at most that fraction of
    negative table values.
    """
    d = np.linalg.norm(m.latent[:, None] - m.latent[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    pts = []
    for _ in range(max_tries):
        i = rng.integers(m.n)
        j = rng.choice(np.argsort(d[i])[:3])
        if d[i, j] < 1e-3:
            continue
        t = rng.uniform(0.25, 0.75)
        x = (1 - t) * m.latent[i] + t * m.latent[j]
        if m.variance(x) >= 0.5 or (clamp is not None and m.negative_fraction(x) > clamp):
            continue
        pts.append(x)
        if len(pts) == n:
            return pts
    raise RuntimeError(f"found only {len(pts)} of {n} latent points in the data's region")


def _log_rms(a, b):
    """RMS of ``log1p(max(a, 0)) - log1p(max(b, 0))`` over the bins valid in ``b``."""
    ok = b >= 0
    return float(np.sqrt(np.mean(np.square(np.log1p(np.maximum(a[ok], 0)) - np.log1p(b[ok])))))


def _render_material(scene_xml, manifold_path, name, spp, res, seed):
    """Full-GI render (``path``) of training material ``name`` from its own table."""
    import mitsuba as mi

    scene, targets, max_depth = load_scene(scene_xml, manifold_path, spp, (res, res))
    for bsdf in targets:
        bsdf.set_material(name)
    integrator = mi.load_dict({"type": "path", "max_depth": int(max_depth)})
    return np.array(
        mi.render(scene, integrator=integrator, spp=int(spp), seed=int(seed)), dtype=np.float32
    )[..., :3]


def _object_mask(scene_xml, manifold_path, res):
    """Pixels whose camera ray first hits the manifold material (the object), as (H, W) 0/1."""
    import drjit as dr
    import mitsuba as mi

    scene, targets, _ = load_scene(scene_xml, manifold_path, 1, (res, res))
    idx = dr.arange(mi.UInt32, res * res)
    pos = mi.Point2f((mi.Float(idx % res) + 0.5) / res, (mi.Float(idx // res) + 0.5) / res)
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.0, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    hit = si.is_valid() & (si.bsdf() == mi.BSDFPtr(targets[0]))
    return np.array(hit, dtype=np.float64).reshape(res, res)


def _saved(m, path):
    """``m`` saved to ``path`` and read back (a manifold that knows its file)."""
    m.save(path)
    return Manifold.load(path)


# ------------------------------------------------------------------- scenes


def _basis(scene_xml, m, folder, res, spp, seed):
    """Render (or resume) the basis of ``scene_xml`` with manifold ``m`` (loaded from a file)."""
    t0 = time.perf_counter()
    render_basis(scene_xml, m.file, folder, spp=spp, mode="onepass", resolution=res, seed=seed)
    b = Basis.load(folder, manifold=m)
    b.read([BASE] + m.names)
    return b, time.perf_counter() - t0


def _random_points(scene_xml, b, m, manifold_path, res, spp, n, rng, seed):
    rows = []
    for k, x in enumerate(_interior_points(m, n, rng)):
        target = render_reference(
            scene_xml, manifold_path, x, spp, seed=seed + 101 + k, resolution=(res, res)
        )
        r = mt.match(b, target, manifold=m)
        own = rel_mse(blend(b, m, x=x, prune=0.0)[0], target)
        t_true, _, _ = m.combine(m.weights(x)[1], prune=0.0)
        t_rec, _, _ = m.combine(r.weights, prune=0.0)
        rows.append(
            {
                "x_true": x.tolist(),
                "x": r.x.tolist(),
                "latent_distance": float(np.linalg.norm(r.x - x)),
                "rel_mse": r.rel_mse,
                "blend_at_true_x_rel_mse": own,
                "ratio": r.rel_mse / own,
                "log_rms_table_error": _log_rms(t_rec, t_true),
                "time_s": r.time_s,
                "best_single": r.single.name,
                "best_single_rel_mse": r.single.error,
            }
        )
    ratios = [row["ratio"] for row in rows]
    return {
        "points": rows,
        "max_ratio": float(np.max(ratios)),
        "median_ratio": float(np.median(ratios)),
        "within_target": int(np.sum(np.array(ratios) <= RATIO_TARGET)),
        "ratio_target": RATIO_TARGET,
        "median_log_rms_table_error": float(np.median([r["log_rms_table_error"] for r in rows])),
    }


def _held_out(scene_xml, m100, manifold_path, out, res, basis_spp, spp, n, seed):
    rng = np.random.default_rng(seed + 1)
    held = sorted(rng.choice(m100.n, size=n, replace=False).tolist())
    keep = [i for i in range(m100.n) if i not in held]
    sub_path = os.path.join(out, f"manifold_without_{'_'.join(map(str, held))}.npz")
    m = (
        Manifold.load(sub_path)
        if os.path.isfile(sub_path)
        else _saved(m100.subset([m100.names[i] for i in keep]), sub_path)
    )
    name = os.path.splitext(os.path.basename(scene_xml))[0]
    b, t_basis = _basis(
        scene_xml, m, os.path.join(out, f"basis_{name}_held_out_{n}"), res, basis_spp, seed
    )
    rows = []
    for k, i in enumerate(held):
        target = _render_material(scene_xml, manifold_path, m100.names[i], spp, res, seed + 211 + k)
        r = mt.match(b, target, manifold=m)
        errs, _ = mt.single_material_errors(b, target, manifold=m)
        j = int(np.argmin(errs))
        rows.append(
            {
                "material": m100.names[i],
                "x": r.x.tolist(),
                "rel_mse": r.rel_mse,
                "best_single": m.names[j],
                "best_single_rel_mse": float(errs[j]),
                "better": bool(r.rel_mse < errs[j]),
                "top_weights": r.top_weights(4),
                "time_s": r.time_s,
            }
        )
    better = sum(row["better"] for row in rows)
    return {
        "materials": rows,
        "better": int(better),
        "of": len(rows),
        "target": "better on >= 8 of 10",
        "meets_target": bool(better >= 0.8 * len(rows)),
        "basis_time_s": t_basis,
        "manifold": sub_path,
    }


def _masked_and_exposure(scene_xml, b, m, manifold_path, res, spp, rng, seed, scale=2.5):
    x = _interior_points(m, 1, rng)[0]
    target = render_reference(
        scene_xml, manifold_path, x, spp, seed=seed + 307, resolution=(res, res)
    )
    mask = _object_mask(scene_xml, manifold_path, res)
    altered = target.copy()
    altered[mask == 0] *= np.array(
        [0.3, 0.5, 1.4], dtype=np.float32
    )  # another background / lighting
    masked = mt.match(b, altered, mask=mask, manifold=m)
    unmasked = mt.match(b, altered, manifold=m)
    inside = mt.match(b, target, mask=mask, manifold=m)
    bright = target * scale
    free = mt.match(b, bright, manifold=m, exposure_free=True)
    fixed = mt.match(b, bright, manifold=m)
    plain = mt.match(b, target, manifold=m)
    return {
        "x_true": x.tolist(),
        "mask_fraction": float(mask.mean()),
        "masked": {
            "x": masked.x.tolist(),
            "rel_mse_in_mask": masked.rel_mse,
            "latent_distance": float(np.linalg.norm(masked.x - x)),
            "same_target_unaltered_rel_mse_in_mask": inside.rel_mse,
            "unmasked_match_rel_mse_in_mask": masked_rel_mse(unmasked.image, altered, mask),
            "unmasked_latent_distance": float(np.linalg.norm(unmasked.x - x)),
        },
        "exposure": {
            "scale": scale,
            "fitted_exposure": free.exposure,
            "rel_mse": free.rel_mse,
            "latent_distance": float(np.linalg.norm(free.x - x)),
            "rel_mse_scaled_back": rel_mse(free.image * (free.exposure / scale), target),
            "unscaled_target_rel_mse": plain.rel_mse,
            "without_exposure_free_rel_mse": fixed.rel_mse,
        },
    }


def run(  # noqa: PLR0913  tools/bench.py's options, as keywords
    folder,
    manifold=None,
    basis=None,
    scenes=("table", "sphere"),
    res=128,
    basis_spp=64,
    target_spp=256,
    n_points=10,
    n_held_out=10,
    out=None,
    seed=0,
    progress=True,
):
    """The whole match benchmark (see the module docstring); ``folder``: the database."""

    def say(text):
        if progress:
            print(text, flush=True)

    from mitsuba_manifold._util.checks import positive_int

    res = positive_int("`res`", res, 128)
    manifold = manifold or work_manifold(folder, "q2_log")
    if not os.path.isfile(manifold):
        Manifold.fit(folder, q=2, features="log").save(manifold)
    m100 = Manifold.load(manifold)
    m100.tables()  # all tables in memory: clamping checks and table errors are matrix products
    out = out or os.path.join(database_cache(folder), "bench_match")
    os.makedirs(out, exist_ok=True)
    report = {
        "manifold": os.path.abspath(manifold),
        "resolution": res,
        "basis_spp": basis_spp,
        "target_spp": target_spp,
        "scenes": {},
    }
    if basis is not None:
        say(f"speed on {basis} ...")
        report["speed"] = bench_speed(basis, manifold)
        say(f"  {report['speed']['settings']}")
    mi = use_variant()
    report["variant"] = mi.variant()
    for name in scenes:
        scene_xml = scene_path(name)
        rng = np.random.default_rng(seed)
        say(f"{name}: basis of {m100.n} materials ({res}x{res}, {basis_spp} spp) ...")
        b, t_basis = _basis(
            scene_xml, m100, os.path.join(out, f"basis_{name}"), res, basis_spp, seed
        )
        sc = {"basis_time_s": t_basis}
        say(f"{name}: {n_points} random points ...")
        sc["random_points"] = _random_points(
            scene_xml, b, m100, manifold, res, target_spp, n_points, rng, seed
        )
        say(f"  max ratio {sc['random_points']['max_ratio']:.3g}")
        say(f"{name}: masked and exposure ...")
        sc.update(_masked_and_exposure(scene_xml, b, m100, manifold, res, target_spp, rng, seed))
        say(f"{name}: {n_held_out} held-out materials ...")
        sc["held_out"] = _held_out(
            scene_xml, m100, manifold, out, res, basis_spp, target_spp, n_held_out, seed
        )
        say(f"  better on {sc['held_out']['better']} of {sc['held_out']['of']}")
        report["scenes"][name] = sc
    return report

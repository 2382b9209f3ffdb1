"""``tools/bench.py match-render``: inverse rendering through the differentiable ``x`` (no basis).

Targets are rendered with Mitsuba's ``path`` at ``target_spp`` from 3 views of ``cbox`` (a scene
no basis is made for), and matched with :func:`mitsuba_manifold.render.match_render.match_render`
(``prb``, ``mi.ad.Adam``):

1. ``random_points``: latent points between neighbouring training points; the recovered image
   error against the noise floor (the error of a render at the true point, same spp and seed as
   the match's final renders); target ``ratio <= 1.5``;
2. ``held_out``: a manifold fit on the other materials, targets rendered from the held-out
   materials' own tables; the match's error against the best single training material's.

Images are compared over the pixels where the camera sees the material (object masks), where the
image depends on it directly. Timings: seconds per Adam iteration (all views, forward + backward)
and per match, against a primal ``path`` render of the same views and spp; peak RSS. By default a
reduced setting that fits a shared 2-core machine: a surrogate database of ``n_materials`` at 32x32x64 bins (made in
``out``) unless ``folder`` holds one, 32x32 images, few points (the issue's full setting is
``res=64, n_points=10, n_held_out=10`` on the 100 materials).
"""

import os
import time

import numpy as np

from ...manifold.model import Manifold
from ...render import match_render as mr
from ...render.scenes import load_scene, scene_path, use_variant
from .common import peak_rss_gib
from .match import _interior_points

RATIO_TARGET = 1.5
#: Camera origins of the 3 views of cbox (looking at its centre).
VIEWS = ((0.0, 0.0, 3.9), (0.9, 0.35, 3.6), (-0.9, -0.3, 3.6))
SMALL_DIMS = (32, 32, 64)
SMALL_MATERIALS = ("white-diffuse-bball", "gold-paint", "blue-acrylic", "chrome", "steel",
                   "color-changing-paint3", "pink-fabric", "black-obsidian", "red-fabric", "green-plastic")


def _sensors(res):
    import mitsuba as mi
    return [mi.load_dict({"type": "perspective", "fov": 39.3077, "fov_axis": "smaller",
                          "to_world": mi.ScalarTransform4f().look_at(origin=list(o), target=[0, 0, 0], up=[0, 1, 0]),
                          "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                                   "pixel_format": "rgb"}}) for o in VIEWS]


def _render(scene_xml, manifold_path, set_material, sensors, spp, seed, max_depth):
    """Renders (``path``) of every view, the scene's manifold materials set by ``set_material(bsdf)``."""
    import mitsuba as mi
    res = int(sensors[0].film().size()[0])
    scene, targets, _ = load_scene(scene_xml, manifold_path, spp, (res, res), max_depth)
    for b in targets:
        set_material(b)
    integ = mi.load_dict({"type": "path", "max_depth": max_depth})
    t0 = time.perf_counter()
    imgs = [np.array(mi.render(scene, sensor=s, integrator=integ, spp=spp, seed=seed + k), dtype=np.float32)
            for k, s in enumerate(sensors)]
    return imgs, time.perf_counter() - t0


def _object_masks(scene_xml, manifold_path, sensors):
    """Per view, the pixels whose camera ray first hits the manifold material (H, W) 0/1: the
    matched pixels (elsewhere the image does not depend on the material but through its light)."""
    import drjit as dr
    import mitsuba as mi
    res = int(sensors[0].film().size()[0])
    scene, targets, _ = load_scene(scene_xml, manifold_path, 1, (res, res))
    idx = dr.arange(mi.UInt32, res * res)
    pos = mi.Point2f((mi.Float(idx % res) + 0.5) / res, (mi.Float(idx // res) + 0.5) / res)
    masks = []
    for sensor in sensors:
        ray, _ = sensor.sample_ray(0.0, 0.0, pos, mi.Point2f(0.5, 0.5))
        si = scene.ray_intersect(ray)
        hit = si.is_valid() & (si.bsdf() == mi.BSDFPtr(targets[0]))
        masks.append(np.array(hit, dtype=np.float64).reshape(res, res))
    return masks


def _views(scene_xml, targets, sensors, masks):
    return [mr.View(scene_xml, t, mk, s) for t, s, mk in zip(targets, sensors, masks)]


def _floor(scene_xml, manifold_path, x, views, opts):
    """Error at the true point: :meth:`_Problem.evaluate` as the match's final renders."""
    return mr._Problem(views, manifold_path, opts).evaluate(x, 1.0, opts.eval_spp, opts.seed + 55)[0]


def _ad_render_time(views, manifold_path, x, opts):
    """Seconds of one forward + backward render of every view (prb, warm), without the
    optimiser's bookkeeping (scan, proxies, final renders)."""
    import drjit as dr
    import mitsuba as mi
    problem = mr._Problem(views, manifold_path, opts)
    times = []
    for k in range(2):   # the first compiles
        xv = mi.Float(np.asarray(x, dtype=np.float32))
        dr.enable_grad(xv)
        t0 = time.perf_counter()
        problem.set_x(xv)
        loss, _, _ = problem.loss(mi.Float(1.0), opts.spp, opts.seed + k)
        dr.backward(loss)
        dr.eval(dr.grad(xv))
        times.append(time.perf_counter() - t0)
    return times[-1]


def _summary(r):
    return {"error": r.error, "errors": r.errors, "x": r.x.tolist(), "single": r.single,
            "top_weights": r.top_weights(4), "time_s": r.time_s, "time_per_iteration_s": r.time_per_iteration_s}


def _database(folder, out, n_materials):
    from ...data import database
    if folder and os.path.isdir(folder) and any(f.endswith(".binary") for f in os.listdir(folder)):
        return folder
    db = os.path.join(out, "database")
    database.make_database(db, SMALL_DIMS, list(SMALL_MATERIALS[:n_materials]))
    return db


def run(folder, manifold=None, res=32, target_spp=256, n_points=3, n_held_out=3, n_materials=10, iterations=15,
        spp=4, eval_spp=256, scan_spp=16, starts=2, max_depth=4, out=None, seed=0):
    """Measurements of the differentiable match; see the module docstring."""
    use_variant()
    out = out or os.path.join("out", "bench_match_render")
    os.makedirs(out, exist_ok=True)
    db = _database(folder, out, n_materials)
    if manifold is None:
        manifold = os.path.join(out, "manifold.npz")
        Manifold.fit(db, q=2).save(manifold)
    m = Manifold.load(manifold)
    cbox = scene_path("cbox")
    sensors = _sensors(res)
    opts = mr.MatchRenderOptions(iterations=iterations, spp=spp, eval_spp=eval_spp, scan_spp=scan_spp, starts=starts,
                                 max_depth=max_depth, seed=seed, progress=False)
    rng = np.random.default_rng(seed)
    masks = _object_masks(cbox, manifold, sensors)
    report = {"settings": {"res": res, "views": len(sensors), "target_spp": target_spp, "spp": spp,
                           "eval_spp": eval_spp, "scan_spp": scan_spp, "iterations": iterations, "starts": starts,
                           "max_depth": max_depth,
                           "materials": m.n, "table_dims": list(m.dims), "database": os.path.abspath(db),
                           "masked_pixels": [int(mk.sum()) for mk in masks]},
              "random_points": [], "held_out": []}
    for x in _interior_points(m, n_points, rng, clamp=None):
        targets, _ = _render(cbox, manifold, lambda b: b.set_latent(x), sensors, target_spp, seed + 100, max_depth)
        views = _views(cbox, targets, sensors, masks)
        r = mr.match_render(views, manifold, opts)
        floor = _floor(cbox, manifold, x, views, opts)
        w_true = m.weights(x)[1]
        top = np.argsort(-np.abs(w_true))[:4]
        report["random_points"].append({**_summary(r), "x_true": x.tolist(), "floor": floor,
                                        "true_top_weights": [(m.names[k], float(w_true[k])) for k in top],
                                        "ratio": r.error / floor, "single_ratio": r.single["error"] / floor,
                                        "meets_ratio": r.error <= RATIO_TARGET * floor})
    for i in sorted(rng.choice(m.n, size=n_held_out, replace=False).tolist()):
        name = m.names[i]
        sub = os.path.join(out, f"manifold_without_{name}.npz")
        Manifold.fit(db, q=2, names=[n for n in m.names if n != name]).save(sub)
        targets, _ = _render(cbox, manifold, lambda b: b.set_material(name), sensors, target_spp, seed + 200,
                             max_depth)
        r = mr.match_render(_views(cbox, targets, sensors, masks), sub, opts)
        report["held_out"].append({**_summary(r), "material": name, "better_than_single": r.error < r.single["error"]})
    _, t_primal = _render(cbox, manifold, lambda b: None, sensors, spp, seed, max_depth)
    _, t_primal = _render(cbox, manifold, lambda b: None, sensors, spp, seed, max_depth)   # compiled: timed
    t_ad = _ad_render_time(_views(cbox, targets, sensors, masks), manifold, m.latent[0] * 0.5 + m.latent[1] * 0.5,
                           opts)
    per_it = [e["time_per_iteration_s"] for e in report["random_points"] + report["held_out"]]
    report["timing"] = {"primal_path_render_s": t_primal, "forward_backward_render_s": t_ad,
                        "forward_backward_over_primal": t_ad / t_primal, "iteration_s_median": float(np.median(per_it)),
                        "iteration_over_primal": float(np.median(per_it)) / t_primal,
                        "match_s_median": float(np.median([e["time_s"] for e in report["random_points"]
                                                           + report["held_out"]]))}
    ratios = [e["ratio"] for e in report["random_points"]]
    report["summary"] = {"ratio_median": float(np.median(ratios)) if ratios else None,
                         "ratio_target": RATIO_TARGET,
                         "meets_ratio": sum(e["meets_ratio"] for e in report["random_points"]),
                         "held_out_better": sum(e["better_than_single"] for e in report["held_out"]),
                         "held_out_of": len(report["held_out"]), "peak_rss_gib": peak_rss_gib()}
    return report

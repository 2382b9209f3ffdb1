"""``tools/bench.py match-render``: inverse rendering through the differentiable ``x`` (no basis).

Targets are rendered with Mitsuba's ``path`` at ``target_spp`` from 3 views of ``cbox`` (a scene
no basis is made for; view 0 is the scene's own camera), and matched with
:func:`mitsuba_manifold.render.inverse.match_render.match_render` (``prb``, ``mi.ad.Adam``) on all 3 views:

1. ``random_points``: latent points between neighbouring training points; the recovered image
   error against the noise floor (the error of a render at the true point, same spp and seed as
   the match's final renders); target ``ratio <= 1.5``;
2. ``held_out``: a manifold fit on the other materials, targets rendered from the held-out
   materials' own tables; the match's error against the best single training material's (target:
   better on >= 8 of 10), and against the basis match (:func:`basis.match.match`) on a basis of the
   same manifold rendered from view 0 only: the basis match sees view 0, ``match_render`` all views;
   both points rendered with ``path`` on views 1 and 2 (``uncovered``), where the basis has no image;
   the error there also free of the render noise (``uncovered_noise_free``: two independent renders
   of each point, :func:`scan.cross_error`): one render's error adds its own variance, which
   penalises a glossy point against a matte one.

Images are compared over the pixels where the camera sees the material (object masks), where the
image depends on it directly. Timings: seconds per Adam iteration (all views, forward + backward)
and per match, against a primal ``path`` render of the same views and spp; peak RSS. The database:
``n_materials`` surrogate materials (all 100 by default) at 32x32x64 bins, made in ``out`` unless
``folder`` holds one. ``part`` runs the random points or the held-out materials alone (each fits
about 10 minutes on a shared 2-core machine), :func:`merge` joins the parts' reports and
:func:`plot` draws the convergence of every match (loss over iterations, in units of its floor).
"""

import os
import time

import numpy as np

from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.render.inverse import match_render as mr
from mitsuba_manifold.render.inverse import scan
from mitsuba_manifold.render.scene.scenes import load_scene, scene_path, use_variant

from .common import peak_rss_gib
from .match import _interior_points

RATIO_TARGET = 1.5
#: Camera origins of the 3 views of cbox (looking at its centre).
VIEWS = ((0.0, 0.0, 3.9), (0.9, 0.35, 3.6), (-0.9, -0.3, 3.6))
SMALL_DIMS = (32, 32, 64)
SMALL_MATERIALS = (
    "white-diffuse-bball",
    "gold-paint",
    "blue-acrylic",
    "chrome",
    "steel",
    "color-changing-paint3",
    "pink-fabric",
    "black-obsidian",
    "red-fabric",
    "green-plastic",
)


def _sensors(res):
    import mitsuba as mi

    return [
        mi.load_dict(
            {
                "type": "perspective",
                "fov": 39.3077,
                "fov_axis": "smaller",
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=list(o), target=[0, 0, 0], up=[0, 1, 0]
                ),
                "film": {
                    "type": "hdrfilm",
                    "width": res,
                    "height": res,
                    "rfilter": {"type": "box"},
                    "pixel_format": "rgb",
                },
            }
        )
        for o in VIEWS
    ]


def _views_scene(out):
    """``cbox.xml`` with a sensor per view of :data:`VIEWS` (sensor ``k`` looks from ``VIEWS[k]``;
    sensor 0 is the scene's own camera), written in ``out``: :class:`match_render.View` names its
    camera by the index of a sensor in the scene.
    """
    import re

    from mitsuba_manifold._util.atomic import write_bytes

    with open(scene_path("cbox")) as f:
        text = f.read()
    block = re.search(r"\s*<sensor .*?</sensor>", text, flags=re.S).group(0)
    extra = "".join(
        re.sub(r'origin="[^"]*"', f'origin="{x}, {y}, {z}"', block) for x, y, z in VIEWS[1:]
    )
    end = text.index(block) + len(block)
    path = os.path.join(out, "cbox_views.xml")
    write_bytes(path, text[:end] + extra + text[end:])
    return path


def _render(scene_xml, manifold_path, set_material, sensors, spp, seed, max_depth):
    """Renders (``path``) of every view, the scene's manifold materials set by ``set_material(bsdf)``."""
    import mitsuba as mi

    res = int(sensors[0].film().size()[0])
    scene, targets, _ = load_scene(scene_xml, manifold_path, spp, (res, res), max_depth)
    for b in targets:
        set_material(b)
    integ = mi.load_dict({"type": "path", "max_depth": max_depth})
    t0 = time.perf_counter()
    imgs = [
        np.array(
            mi.render(scene, sensor=s, integrator=integ, spp=spp, seed=seed + k), dtype=np.float32
        )
        for k, s in enumerate(sensors)
    ]
    return imgs, time.perf_counter() - t0


def _object_masks(scene_xml, manifold_path, sensors):
    """Per view, the pixels whose camera ray first hits the manifold material (H, W) 0/1: the
    matched pixels (elsewhere the image does not depend on the material but through its light).
    """
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
    return [mr.View(scene_xml, t, mk, k) for k, (t, mk) in enumerate(zip(targets, masks))]


def _floor(scene_xml, manifold_path, x, views, opts):
    """Error at the true point: :meth:`_Problem.evaluate` as the match's final renders."""
    return mr._Problem(views, manifold_path, opts).evaluate(x, 1.0, opts.eval_spp, opts.seed + 55)[
        0
    ]


def _ad_render_time(views, manifold_path, x, opts):
    """Seconds of one forward + backward render of every view (prb, warm), without the
    optimiser's bookkeeping (scan, proxies, final renders).
    """
    import drjit as dr
    import mitsuba as mi

    problem = mr._Problem(views, manifold_path, opts)
    times = []
    for k in range(2):  # the first compiles
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
    return {
        "error": r.error,
        "errors": r.errors,
        "x": r.x.tolist(),
        "single": r.single,
        "top_weights": r.top_weights(4),
        "time_s": r.time_s,
        "time_per_iteration_s": r.time_per_iteration_s,
        "history": r.history,
        "scan_s": r.extra["scan"]["time_s"],
        "from_start": r.extra["from_start"],
        "from_iterate": r.extra["from_iterate"],
    }


def _database(folder, out, n_materials):
    """The database spec or folder the benchmark fits on: a built-in set at ``SMALL_DIMS`` (or
    the resolution its spec gives), a folder of tables as given, else the surrogate materials
    written in ``out``.
    """
    from mitsuba_manifold.data import database
    from mitsuba_manifold.data.sources import SET_NAMES

    base, dims = database.split_spec(folder) if folder else (None, None)
    if base in SET_NAMES:
        return f"{base}@{'x'.join(map(str, dims or SMALL_DIMS))}"
    if folder and os.path.isdir(folder) and any(f.endswith(".binary") for f in os.listdir(folder)):
        return folder
    db = os.path.join(out, "database")
    names = list(SMALL_MATERIALS[:n_materials]) if n_materials <= len(SMALL_MATERIALS) else None
    made = os.path.isdir(db) and len([f for f in os.listdir(db) if f.endswith(".binary")]) >= min(
        n_materials, 100
    )
    if not made:  # (not even opened when made: parts run side by side, and writing locks it)
        database.make_database(db, SMALL_DIMS, names)
    if names is None and n_materials < 100:  # the first n of the built-in ones (sorted names)
        keep = sorted(f for f in os.listdir(db) if f.endswith(".binary"))[:n_materials]
        db_sub = os.path.join(out, f"database_{n_materials}")
        os.makedirs(db_sub, exist_ok=True)
        for f in keep:
            if not os.path.exists(os.path.join(db_sub, f)):
                os.link(os.path.join(db, f), os.path.join(db_sub, f))
        return db_sub
    return db


def _subset(db, n_materials):
    """The materials of a built-in set's spec ``db`` the benchmark keeps (None: all of them; a
    folder holds only its chosen ones).
    """
    from mitsuba_manifold.data.database import Database

    if os.path.exists(db) or n_materials >= 100:
        return None
    if n_materials <= len(SMALL_MATERIALS):
        return list(SMALL_MATERIALS[:n_materials])
    return sorted(Database(db).names)[:n_materials]


def _train_floor(problem, x, opts, seeds=3):
    """The training loss's level at ``x`` (mean over ``seeds`` primal renders at the training spp):
    the unit of the convergence plot.
    """
    return float(
        np.mean([problem.evaluate(x, 1.0, opts.spp, opts.seed + 31 * k)[0] for k in range(seeds)])
    )


def _random_point(cbox, manifold, m, x, ctx):
    sensors, masks, opts = ctx["sensors"], ctx["masks"], ctx["opts"]
    targets, _ = _render(
        cbox,
        manifold,
        lambda b: b.set_latent(x),
        sensors,
        ctx["target_spp"],
        ctx["seed"] + 100,
        opts.max_depth,
    )
    views = _views(cbox, targets, sensors, masks)
    r = mr.match_render(views, manifold, opts)
    problem = mr._Problem(views, manifold, opts)
    floor = problem.evaluate(x, 1.0, opts.eval_spp, opts.seed + 55)[0]
    w_true = m.weights(x)[1]
    top = np.argsort(-np.abs(w_true))[:4]
    return {
        **_summary(r),
        "x_true": x.tolist(),
        "floor": floor,
        "train_floor": _train_floor(problem, x, opts),
        "true_top_weights": [(m.names[k], float(w_true[k])) for k in top],
        "ratio": r.error / floor,
        "single_ratio": r.single["error"] / floor,
        "meets_ratio": bool(r.error <= RATIO_TARGET * floor),
    }


def _held_out(cbox, manifold, db, m, name, ctx):
    """One held-out material: the match on the manifold of the others, against the best single
    material and the basis match (a basis of view 0 only).
    """
    from mitsuba_manifold.basis.folder import Basis
    from mitsuba_manifold.basis.inverse import match as mt
    from mitsuba_manifold.render.jobs.render_basis import render_basis

    sensors, masks, opts, out = ctx["sensors"], ctx["masks"], ctx["opts"], ctx["out"]
    sub = os.path.join(out, f"manifold_without_{name}.npz")
    Manifold.fit(db, q=2, names=[n for n in m.names if n != name]).save(sub)
    targets, _ = _render(
        cbox,
        manifold,
        lambda b: b.set_material(name),
        sensors,
        ctx["target_spp"],
        ctx["seed"] + 200,
        opts.max_depth,
    )
    views = _views(cbox, targets, sensors, masks)
    r = mr.match_render(views, sub, opts)
    problem = mr._Problem(views, sub, opts)
    t0 = time.perf_counter()
    folder = os.path.join(out, f"basis_without_{name}")
    render_basis(
        cbox,
        sub,
        folder,
        spp=ctx["basis_spp"],
        resolution=ctx["res"],
        mode="onepass",
        max_depth=opts.max_depth,
        seed=ctx["seed"] + 300,
        progress=False,
    )
    sub_m = Manifold.load(sub)
    b = mt.match(Basis.load(folder, manifold=sub_m), targets[0], mask=masks[0], manifold=sub_m)
    t_basis = time.perf_counter() - t0
    _, images, _ = problem.evaluate(np.asarray(b.x), 1.0, opts.eval_spp, opts.seed + 55)
    basis_errors = mr._per_view_errors(images, problem.data, 1.0)
    uncovered, basis_uncovered = float(np.mean(r.errors[1:])), float(np.mean(basis_errors[1:]))
    unc = mr._Problem(views[1:], sub, opts)  # the same, free of the render noise (two renders each)
    nf, nf_basis = (
        scan.cross_error(unc, x, max(1, opts.eval_spp // 4), opts.seed + 77) for x in (r.x, b.x)
    )
    return {
        **_summary(r),
        "material": name,
        "better_than_single": bool(r.error < r.single["error"]),
        "train_floor": _train_floor(problem, sub_m.latent[sub_m.index(r.single["name"])], opts),
        "basis_match": {
            "x": np.asarray(b.x).tolist(),
            "errors": basis_errors,
            "blend_error_view0": float(b.error),
            "time_s": t_basis,
        },
        "uncovered_error": uncovered,
        "basis_uncovered_error": basis_uncovered,
        "better_than_basis_uncovered": bool(uncovered < basis_uncovered),
        "uncovered_noise_free": nf,
        "basis_uncovered_noise_free": nf_basis,
        "better_than_basis_uncovered_noise_free": bool(nf < nf_basis),
    }


def _timing(cbox, manifold, m, ctx, report):
    sensors, opts = ctx["sensors"], ctx["opts"]
    _, t_primal = _render(
        cbox, manifold, lambda b: None, sensors, opts.spp, ctx["seed"], opts.max_depth
    )
    _, t_primal = _render(
        cbox, manifold, lambda b: None, sensors, opts.spp, ctx["seed"], opts.max_depth
    )  # compiled
    targets, _ = _render(
        cbox, manifold, lambda b: None, sensors, opts.spp, ctx["seed"], opts.max_depth
    )
    t_ad = _ad_render_time(
        _views(cbox, targets, sensors, ctx["masks"]),
        manifold,
        m.latent[0] * 0.5 + m.latent[1] * 0.5,
        opts,
    )
    runs = report["random_points"] + report["held_out"]
    per_it = [e["time_per_iteration_s"] for e in runs]
    return {
        "primal_path_render_s": t_primal,
        "forward_backward_render_s": t_ad,
        "forward_backward_over_primal": t_ad / t_primal,
        "iteration_s_median": float(np.median(per_it)),
        "iteration_over_primal": float(np.median(per_it)) / t_primal,
        "match_s_median": float(np.median([e["time_s"] for e in runs])),
        "scan_s_median": float(np.median([e["scan_s"] for e in runs])),
        "load_average": os.getloadavg(),
    }


def run(  # noqa: PLR0913  tools/bench.py's options, as keywords
    folder,
    manifold=None,
    res=32,
    target_spp=256,
    n_points=10,
    n_held_out=10,
    n_materials=100,
    iterations=12,
    spp=12,
    eval_spp=256,
    scan_spp=64,
    starts=2,
    max_depth=4,
    out=None,
    seed=0,
    part="all",
    held_out_range=None,
    basis_spp=64,
    on_result=None,
):
    """Measurements of the differentiable match; see the module docstring. ``part``: ``"all"``,
    ``"random"`` or ``"held-out"`` (``held_out_range=(a, b)``: only those of the held-out list);
    ``on_result(report)`` is called after every match (to keep partial results).
    """
    use_variant()
    out = out or os.path.join("out", "bench_match_render")
    os.makedirs(out, exist_ok=True)
    db = _database(folder, out, n_materials)
    if manifold is None:
        manifold = os.path.join(out, "manifold.npz")
        if not os.path.isfile(manifold):
            Manifold.fit(db, q=2, names=_subset(db, n_materials)).save(manifold)
    m = Manifold.load(manifold)
    cbox = _views_scene(out)
    sensors = _sensors(res)
    opts = mr.MatchRenderOptions(
        iterations=iterations,
        spp=spp,
        eval_spp=eval_spp,
        scan_spp=scan_spp,
        starts=starts,
        max_depth=max_depth,
        seed=seed,
        progress=False,
    )
    masks = _object_masks(cbox, manifold, sensors)
    ctx = {
        "sensors": sensors,
        "masks": masks,
        "opts": opts,
        "out": out,
        "seed": seed,
        "res": res,
        "target_spp": target_spp,
        "basis_spp": basis_spp,
    }
    report = {
        "settings": {
            "res": res,
            "views": len(sensors),
            "target_spp": target_spp,
            "spp": spp,
            "eval_spp": eval_spp,
            "scan_spp": scan_spp,
            "iterations": iterations,
            "starts": starts,
            "max_depth": max_depth,
            "basis_spp": basis_spp,
            "part": part,
            "materials": m.n,
            "table_dims": list(m.dims),
            "database": db if not os.path.exists(db) else os.path.abspath(db),
            "masked_pixels": [int(mk.sum()) for mk in masks],
        },
        "random_points": [],
        "held_out": [],
    }
    if part in ("all", "random"):
        for x in _interior_points(m, n_points, np.random.default_rng(seed), clamp=None):
            report["random_points"].append(_random_point(cbox, manifold, m, x, ctx))
            if on_result is not None:
                on_result(report)
    if part in ("all", "held-out"):
        chosen = sorted(
            np.random.default_rng(seed + 1).choice(m.n, size=n_held_out, replace=False).tolist()
        )
        a, b = held_out_range or (0, len(chosen))
        for i in chosen[a:b]:
            report["held_out"].append(_held_out(cbox, manifold, db, m, m.names[i], ctx))
            if on_result is not None:
                on_result(report)
    report["timing"] = _timing(cbox, manifold, m, ctx, report)
    report["summary"] = summary(report)
    return report


def summary(report):
    """Counts against the issue's targets (of the random points and held-out materials in ``report``)."""
    rp, ho = report["random_points"], report["held_out"]
    ratios = [e["ratio"] for e in rp]
    return {
        "ratio_median": float(np.median(ratios)) if ratios else None,
        "ratio_max": max(ratios, default=None),
        "ratio_target": RATIO_TARGET,
        "meets_ratio": sum(e["meets_ratio"] for e in rp),
        "random_of": len(rp),
        "held_out_better": sum(e["better_than_single"] for e in ho),
        "held_out_of": len(ho),
        "held_out_better_than_basis_uncovered": sum(e["better_than_basis_uncovered"] for e in ho),
        "held_out_better_than_basis_uncovered_noise_free": (
            None
            if any("better_than_basis_uncovered_noise_free" not in e for e in ho)
            else sum(e["better_than_basis_uncovered_noise_free"] for e in ho)
        ),
        "peak_rss_gib": max([peak_rss_gib()] + [report.get("timing", {}).get("peak_rss_gib", 0)]),
    }


def merge(reports):
    """One report from the parts' reports (settings of the first; timings of the first part that has
    them; a part cut short has no timing nor summary and is listed as partial).
    """
    out = {
        "settings": dict(reports[0]["settings"], part="merged"),
        "random_points": [],
        "held_out": [],
        "parts": [],
    }
    for r in reports:
        out["random_points"] += r["random_points"]
        out["held_out"] += r["held_out"]
        out["parts"].append(
            {
                "part": r["settings"]["part"],
                "timing": r.get("timing"),
                "summary": r.get("summary"),
                "partial": "timing" not in r,
            }
        )
    runs = out["random_points"] + out["held_out"]
    per_it = [e["time_per_iteration_s"] for e in runs]
    t = next(r["timing"] for r in reports if "timing" in r)
    out["timing"] = dict(
        t,
        iteration_s_median=float(np.median(per_it)),
        iteration_over_primal=float(np.median(per_it)) / t["primal_path_render_s"],
        match_s_median=float(np.median([e["time_s"] for e in runs])),
        scan_s_median=float(np.median([e["scan_s"] for e in runs])),
    )
    out["summary"] = dict(
        summary(out),
        peak_rss_gib=max(r["summary"]["peak_rss_gib"] for r in reports if "summary" in r),
    )
    return out


def plot(report, path):
    """Convergence of every match: the training loss of the start that reached the lowest loss, over
    Adam iterations, in units of the loss at the true point (random points) or of the best single
    training material (held-out), both at the training spp.
    """
    from mitsuba_manifold.imaging.plots import finish, subplots

    fig, axes = subplots(1, 2, figsize=(11, 4))
    for ax, key, what in (
        (axes[0], "random_points", "true point"),
        (axes[1], "held_out", "best single material"),
    ):
        for k, e in enumerate(report[key]):
            h = min(e["history"], key=lambda h: min(h))
            label = e.get("material", f"point {k}")
            ax.semilogy(
                np.arange(1, len(h) + 1),
                np.asarray(h) / e["train_floor"],
                marker=".",
                lw=1,
                label=label,
            )
        ax.axhline(1.0, color="k", lw=1, ls="--")
        ax.set_xlabel("Adam iteration")
        ax.set_ylabel(f"training loss / loss at the {what}")
        ax.set_title(f"{key.replace('_', ' ')}: {len(report[key])} matches")
    return finish(fig, axes, path)


def main(argv=None):
    """``python3 -m benchmarks.match_render --part random --json A.json`` (one part),
    ``--merge A.json B.json --json OUT.json`` (joined, with the convergence plot beside OUT).
    """
    import argparse
    import json

    from mitsuba_manifold._util.atomic import write_bytes

    from .common import machine

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("--json", required=True)
    p.add_argument("--part", default="all", choices=("all", "random", "held-out"))
    p.add_argument("--held-out-range", type=int, nargs=2, default=None)
    p.add_argument("--out", default=None)
    p.add_argument("--merge", nargs="+", default=None)
    args = p.parse_args(argv)
    t0 = time.perf_counter()

    def write(result, partial=False):
        report = {
            "benchmark": "match-render",
            "machine": machine(),
            "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "wall_s": time.perf_counter() - t0,
            "partial": partial,
            "result": result,
        }
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        write_bytes(args.json, json.dumps(report, indent=1, default=float))

    if args.merge:
        result = merge([json.load(open(f))["result"] for f in args.merge])
    else:
        result = run(
            None,
            out=args.out,
            part=args.part,
            on_result=lambda r: write(r, partial=True),
            held_out_range=tuple(args.held_out_range) if args.held_out_range else None,
        )
    result["plot"] = plot(result, os.path.splitext(args.json)[0] + ".png")
    write(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

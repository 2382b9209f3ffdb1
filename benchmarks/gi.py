"""GI benchmark: the blend against re-rendering the interpolated material, error against run
time on the shipped sphere and table scenes (:func:`gi_comparison.gi_report`), and the targets
of full-GI bases (:func:`targets`): bias and relative MSE of the L1- and full-GI
blends against full-GI references at training, midpoint and extrapolated points, beside a
direct render; basis render time and size, L1- against full GI; blend time.
"""

import os
import shutil
import time

import numpy as np

from mitsuba_manifold._util.timing import median_time
from mitsuba_manifold.apps.gi_comparison import (
    gi_pair,
    gi_points,
    gi_report,
    refined_row,
    relative_bias,
)
from mitsuba_manifold.basis.blend import blend
from mitsuba_manifold.basis.folder import Basis
from mitsuba_manifold.data.database import database_cache
from mitsuba_manifold.imaging import metrics
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.render.jobs.render_basis import render_basis
from mitsuba_manifold.render.scene import scenes as _scenes

from .common import work_manifold

#: The scene made for this bench (not shipped): a sphere on a floor before a wall, all of the material.
FACING = os.path.join(
    os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    "tests",
    "render",
    "data",
    "facing.xml",
)


def run(folder, manifold=None, scenes=("sphere", "table"), out=None, plot=None, **settings):
    """Error against run time of blends and direct renders, without saving images; ``settings``:
    fields of :class:`~mitsuba_manifold.apps.gi_comparison.GISettings` (``res``, ``basis_spp``,
    ``ref_spp``, ``direct_spp``, ``mode``, ``seed``, ``progress``); see :func:`comparison.gi_report`.
    ``settings["targets"]`` (a dict of :func:`targets`'s keywords, or True) adds the issue-21 targets.
    """
    more = settings.pop("targets", None)
    report = gi_report(
        folder, manifold, scenes=scenes, out=out, plot=plot, **{"save_images": False, **settings}
    )
    if more:
        report["targets"] = targets(folder, manifold, **(more if isinstance(more, dict) else {}))
    return report


def _size(folder):
    return sum(
        os.path.getsize(os.path.join(folder, f))
        for f in os.listdir(folder)
        if os.path.isfile(os.path.join(folder, f))
    )


def _basis(scene, manifold, out, warm=True, **kw):
    """Render a basis from scratch (timed; after a 1-spp warm-up that compiles the kernels)."""
    if warm:
        _basis(scene, manifold, out, warm=False, **{**kw, "spp": 1})
    if os.path.isdir(out):
        shutil.rmtree(out)
    t0 = time.perf_counter()
    manifest = render_basis(scene, manifold, out, mode="onepass", **kw)
    return manifest, time.perf_counter() - t0, _size(out)


def targets(  # noqa: PLR0913  tools/bench.py's options, as keywords
    folder,
    manifold=None,
    scenes=("table", "sphere", "cbox", FACING),
    res=64,
    basis_spp=256,
    ref_spp=4096,
    direct_spp=256,
    levels=None,
    out=None,
    seed=0,
    log=print,
    both_ends=False,
    gi_options=None,
):
    """The full-GI targets per scene: L1- and full-GI bases (time, size, what they hold), and at
    the points of :func:`gi_points` the bias and relative MSE of both blends and of a
    ``direct_spp`` render against a ``ref_spp`` reference (Mitsuba's ``path``); ``both_ends``:
    also at the pair's second material (with convex weights the extrapolated point is close to it);
    ``gi_options``: more :class:`~mitsuba_manifold.render.jobs.render_basis.BasisOptions` fields of the
    full-GI basis (e.g. ``cross_fraction``).
    """
    manifold = manifold or work_manifold(folder)
    if not os.path.isfile(manifold):
        Manifold.fit(folder, q=2).save(manifold)
    m = Manifold.load(manifold)
    out = out or os.path.join(database_cache(folder), "bench_gi_targets")
    os.makedirs(out, exist_ok=True)
    pair = gi_pair(m)
    report = {
        "resolution": res,
        "basis_spp": basis_spp,
        "reference_spp": ref_spp,
        "direct_spp": direct_spp,
        "levels": levels,
        "pair": list(pair),
        "materials": m.n,
        "scenes": {},
    }
    for scene in scenes:
        name = os.path.splitext(os.path.basename(scene))[0]
        path = _scenes.scene_path(scene)
        kw = dict(spp=basis_spp, resolution=res, seed=seed)
        l1, t_l1, s_l1 = _basis(
            path, manifold, os.path.join(out, f"{name}_l1"), components="l1", **kw
        )
        gi, t_gi, s_gi = _basis(
            path,
            manifold,
            os.path.join(out, f"{name}_gi"),
            components="full",
            levels=levels,
            **kw,
            **(gi_options or {}),
        )
        b_l1, b_gi = (
            Basis.load(os.path.join(out, f"{name}_l1"), manifold=m),
            Basis.load(os.path.join(out, f"{name}_gi"), manifold=m),
        )
        rows = []
        ends = [("training", pair[1], m.latent[m.index(pair[1])])] if both_ends else []
        for kind, label, x in gi_points(m, *pair) + ends:
            ref = _scenes.render_reference(
                path, manifold, x, ref_spp, seed=seed + 7919, resolution=(res, res)
            )
            t0 = time.perf_counter()
            direct = _scenes.render_reference(
                path, manifold, x, direct_spp, seed=seed + 31, resolution=(res, res)
            )
            row = {
                "point": kind,
                "x_is": label,
                "direct": {
                    "time_s": time.perf_counter() - t0,
                    "rel_mse": metrics.compare(direct, ref).rel_mse,
                    "relative_bias": relative_bias(direct, ref)[0],
                },
            }
            for comp, b, l2 in (
                ("l1", b_l1, "raw"),
                ("full", b_gi, "denoised"),
                ("full_summed", b_gi, "raw"),
            ):
                img, info = blend(b, m, x=x, component=comp.split("_")[0], l2=l2)
                bias, se = relative_bias(img, ref)
                row[comp] = {
                    "relative_bias": bias,
                    "relative_bias_se": se,
                    "rel_mse": metrics.compare(img, ref).rel_mse,
                    "component": info.component,
                    "images": info.n_images,
                    "cross_terms": len(info.plan.cross[0]) if info.plan.cross else 0,
                }
            # the default refinement of the full-GI basis (the control variate; it costs about twice a
            # direct render per sample, so an eighth of the samples is about a quarter of the time)
            row["refined"] = refined_row(
                b_gi, m, x, ref, max(1, direct_spp // 8), seed + 101, warm=True
            )
            rows.append(row)
            if log:
                log(
                    f"{name} {kind} ({label}): bias L1- {100 * row['l1']['relative_bias']:+.2f}%, full "
                    f"{100 * row['full']['relative_bias']:+.2f}% (se {100 * row['full']['relative_bias_se']:.2f}%); "
                    f"rel. MSE L1- {row['l1']['rel_mse']:.3g}, full {row['full']['rel_mse']:.3g}, "
                    f"direct {direct_spp} spp {row['direct']['rel_mse']:.3g} ({row['direct']['time_s']:.2f} s); "
                    f"refined {row['refined']['spp']} spp {row['refined']['rel_mse']:.3g} "
                    f"({row['refined']['time_s']:.2f} s, {row['refined']['time_cold_s']:.2f} s from nothing, "
                    f"bias {100 * row['refined']['relative_bias']:+.2f}%)"
                )
        report["scenes"][name] = {
            "basis_l1": {"time_s": t_l1, "bytes": s_l1},
            "basis_gi": {
                "time_s": t_gi,
                "bytes": s_gi,
                "components": gi.components,
                "left_out": gi.left_out or {},
                "gi_stats": gi.gi_stats,
            },
            "render_ratio": t_gi / t_l1,
            "points": rows,
        }
        if log:
            log(
                f"{name}: basis L1- {t_l1:.1f} s {s_l1 / 1e6:.2f} MB, full GI {t_gi:.1f} s {s_gi / 1e6:.2f} MB "
                f"({t_gi / t_l1:.2f}x), holds {gi.components}, left out {gi.left_out or {}}"
            )
    return report


def blend_time(manifold, out, res=256, scene="table", spp=1, points=20, log=print):
    """Median blend time (ms) at ``res`` for the default (full-GI, its L2+ part denoised), the
    summed full-GI (``l2="raw"``) and the L1- blends at ``points`` explored points of a full-GI
    basis of all the manifold's materials (``spp`` per pixel).
    """
    from mitsuba_manifold.basis.crossterms import explored_points

    m = Manifold.load(manifold)
    folder = os.path.join(out, f"blend_time_{scene}_{res}")
    manifest, t, size = _basis(
        _scenes.scene_path(scene), manifold, folder, spp=spp, resolution=res, components="full"
    )
    b = Basis.load(folder, manifold=m)
    pts = explored_points(m)[m.n : m.n + points]
    res_ms = {}
    for mode in ("full", "full_summed", "l1"):
        kw = {"component": mode.split("_")[0], "l2": "denoised" if mode == "full" else "raw"}
        for x in pts:
            blend(b, m, x=x, **kw)  # reads the images once
        res_ms[mode] = float(
            np.median([median_time(lambda: blend(b, m, x=x, **kw), 3)[0] * 1e3 for x in pts])
        )
    mem = b._store.nbytes + b.cross_terms()[1].nbytes  # images float32, cross terms float16
    out = {
        "resolution": res,
        "materials": m.n,
        "blend_ms": res_ms,
        "basis_bytes": size,
        "memory_bytes": int(mem),
        "components": manifest.components,
        "pairs": manifest.cross.pairs if manifest.cross else 0,
    }
    if log:
        log(
            f"blend at {res}x{res}, N = {m.n}: full {res_ms['full']:.2f} ms (summed "
            f"{res_ms['full_summed']:.2f} ms), L1- {res_ms['l1']:.2f} ms; "
            f"basis {size / 1e6:.1f} MB on disk, {mem / 1e6:.1f} MB in memory, {out['pairs']} cross terms"
        )
    return out

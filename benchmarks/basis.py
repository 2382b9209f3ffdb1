"""Basis benchmark: one-pass against per-material basis rendering, and the blends' error."""

import os
import time

import numpy as np

from mitsuba_manifold.apps import gi_comparison as comparison
from mitsuba_manifold.basis.blend import blend
from mitsuba_manifold.basis.folder import Basis
from mitsuba_manifold.data.database import database_cache
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.render.scene import scenes
from mitsuba_manifold.render.scene.scenes import use_variant

from .common import peak_rss_gib, work_manifold


def basis_run(scene_path, manifold, folder, spp, mode, res, seed):
    """One basis rendered from scratch by the real tool (``render_basis``).

    Returns the wall time (scene loading, rendering, writing every EXR and the manifest)
    and the render time (the sum of the manifest's per-image times: the renders only).
    """
    import shutil

    from mitsuba_manifold.render.jobs import render_basis as basis_mod

    shutil.rmtree(folder, ignore_errors=True)
    t0 = time.perf_counter()
    manifest = basis_mod.render_basis(
        scene_path, manifold, folder, spp=spp, mode=mode, resolution=res, seed=seed
    )
    wall = time.perf_counter() - t0
    return {
        "spp": int(spp),
        "wall_s": wall,
        "render_s": float(sum(e.time_s for e in manifest.images.values())),
        "images": len(manifest.images),
    }


def l1_reference(scene_path, manifold, x, spp, seed, res):
    """The L1- image of latent point ``x`` (what a blend estimates), rendered directly."""
    import mitsuba as mi

    scene, _, max_depth = scenes.load_scene(scene_path, manifold, spp, (res, res), x=x)
    integ = mi.load_dict({"type": "manifold_path", "component": "l1", "max_depth": int(max_depth)})
    return np.array(
        mi.render(scene, integrator=integ, spp=int(spp), seed=int(seed)), dtype=np.float32
    )[..., :3]


def run(
    folder, manifold=None, scene="table", res=256, spp=64, ref_spp=4096, repeats=3, out=None, seed=0
):
    """One-pass basis rendering against one render per material, and the blends' error.

    Both modes run through :func:`render_basis.render_basis` on the scene ``scene`` with every
    material of the manifold, at ``res`` x ``res`` and ``spp`` samples per pixel; one-pass
    runs are interleaved with single-material renders (``touch`` and ``path``) and
    repeated (minimum reported); the per-material mode runs once. Targets: one-pass at
    least 10x faster than per-material, and under 3x one single-material render.

    Then, at equal total basis time: the one-pass mode gets the spp that makes its wall
    time that of the per-material mode (fitted from its times at ``spp`` and ``4 spp``,
    rounded down to whole passes of ``spp``), and both blends at the midpoint of
    :func:`gi_comparison.gi_pair` are compared with a full-GI reference (``path``, ``ref_spp``) and with
    the L1- reference (``manifold_path``, ``component=l1``, ``ref_spp``), which is what a
    blend estimates without bias.
    """
    import drjit as dr

    from mitsuba_manifold.render.integrators.onepass import PACKET

    mi = use_variant()
    if manifold is None:
        manifold = work_manifold(folder)
        Manifold.fit(folder, q=2).save(manifold)
    m = Manifold.load(manifold)
    scene_path = scenes.scene_path(scene)
    out = out or os.path.join(database_cache(folder), "bench_basis")
    os.makedirs(out, exist_ok=True)
    report = {
        "scene": scene + ".xml",
        "resolution": res,
        "spp": spp,
        "n_materials": m.n,
        "variant": mi.variant(),
        "threads": dr.thread_count(),
    }

    # The interleaved tables one-pass rendering reads (built once per set of materials).
    db = m.open_database()
    t0 = time.perf_counter()
    rows = db.material_rows(m.names, pad=PACKET)
    report["tables_cache"] = {
        "s": time.perf_counter() - t0,
        "bytes": int(rows.nbytes),
        "note": "Database.material_rows: built on first use, then read from the cache",
    }
    del rows

    # Timings: one-pass runs interleaved with single-material renders, per-material once.
    sc, targets, max_depth = scenes.load_scene(scene_path, manifold, spp, (res, res))
    targets[0].set_material(m.names[0])
    single = {
        "touch": mi.load_dict(
            {"type": "manifold_path", "component": "touch", "max_depth": max_depth}
        ),
        "path": mi.load_dict({"type": "path", "max_depth": max_depth}),
    }
    t_single = {k: [] for k in single}

    def render_single(kind, s):
        t0 = time.perf_counter()
        dr.eval(mi.render(sc, integrator=single[kind], spp=spp, seed=s))
        dr.sync_thread()
        return time.perf_counter() - t0

    one_dir = os.path.join(out, f"onepass_{spp}")
    for kind in single:  # warm-up (kernel compilation)
        render_single(kind, 1000)
    first = basis_run(scene_path, manifold, one_dir, spp, "onepass", res, seed)
    runs = []
    for rep in range(repeats):
        runs.append(basis_run(scene_path, manifold, one_dir, spp, "onepass", res, seed))
        for kind in single:
            t_single[kind].append(render_single(kind, rep))
    per = basis_run(
        scene_path,
        manifold,
        os.path.join(out, f"per_material_{spp}"),
        spp,
        "per-material",
        res,
        seed,
    )
    runs.append(
        basis_run(scene_path, manifold, one_dir, spp, "onepass", res, seed)
    )  # and once after it
    for kind in single:
        t_single[kind].append(render_single(kind, repeats))
    wall = [r["wall_s"] for r in runs]
    render = [r["render_s"] for r in runs]
    touch, path = min(t_single["touch"]), min(t_single["path"])
    report["onepass"] = {
        "images": runs[0]["images"],
        "first_wall_s": first["wall_s"],
        "first_render_s": first["render_s"],
        "wall_s": wall,
        "render_s": render,
        "min_wall_s": min(wall),
        "min_render_s": min(render),
    }
    report["per_material"] = per
    report["single_render"] = {
        k: {"min_s": float(np.min(v)), "median_s": float(np.median(v)), "times_s": v}
        for k, v in t_single.items()
    }
    speedup = per["wall_s"] / min(wall)
    ratio_render = min(render) / touch
    ratio_wall = min(wall) / touch
    report["targets"] = {
        "speedup_wall": speedup,
        "speedup_render": per["render_s"] / min(render),
        "speedup_target": 10.0,
        "meets_speedup_target": speedup >= 10.0,
        "onepass_render_over_touch_render": ratio_render,
        "onepass_render_over_path_render": min(render) / path,
        "onepass_wall_over_touch_render": ratio_wall,
        "single_render_ratio_target": 3.0,
        "meets_single_render_target": ratio_render < 3.0,
        "meets_single_render_target_wall": ratio_wall < 3.0,
        "note": (
            "speedup_wall: render_basis wall times (scene loading, rendering, writing 101 EXRs and the "
            "manifest) of the two modes; *_render: the rendering alone (manifest per-image times: "
            "render_onepass, or the sum of the per-material mi.render calls); single renders: one "
            "mi.render of one material (component touch, and full-GI path) at the same spp"
        ),
    }

    report["equal_time"] = equal_time(scene_path, manifold, out, spp, res, seed, min(wall), per)
    report["blend"] = blend_errors(
        scene_path, manifold, m, out, spp, report["equal_time"]["onepass_spp"], res, ref_spp, seed
    )
    report["peak_rss_gib"] = peak_rss_gib()
    return report


def equal_time(scene_path, manifold, out, spp, res, seed, onepass_wall, per):
    """The one-pass spp whose basis takes as long as the per-material basis ``per`` (fitted from
    its wall times at ``spp`` and ``4 spp``, rounded down to whole passes of ``spp``).
    """
    import shutil

    four = basis_run(
        scene_path, manifold, os.path.join(out, f"onepass_{4 * spp}"), 4 * spp, "onepass", res, seed
    )
    slope = max((four["wall_s"] - onepass_wall) / (3 * spp), 1e-9)
    fixed = onepass_wall - slope * spp
    spp_eq = max(spp, int((per["wall_s"] - fixed) / slope) // spp * spp)
    eq = basis_run(
        scene_path, manifold, os.path.join(out, f"onepass_{spp_eq}"), spp_eq, "onepass", res, seed
    )
    tries = [(spp_eq, eq["wall_s"])]
    if abs(eq["wall_s"] / per["wall_s"] - 1.0) > 0.1:  # one secant step from the two largest runs
        slope = max((eq["wall_s"] - four["wall_s"]) / max(spp_eq - 4 * spp, 1), 1e-9)
        spp_eq = max(spp, int(4 * spp + (per["wall_s"] - four["wall_s"]) / slope) // spp * spp)
        shutil.rmtree(os.path.join(out, f"onepass_{tries[0][0]}"), ignore_errors=True)
        eq = basis_run(
            scene_path,
            manifold,
            os.path.join(out, f"onepass_{spp_eq}"),
            spp_eq,
            "onepass",
            res,
            seed,
        )
        tries.append((spp_eq, eq["wall_s"]))
    return {
        "onepass_spp": spp_eq,
        "onepass_wall_s": eq["wall_s"],
        "per_material_spp": spp,
        "per_material_wall_s": per["wall_s"],
        "time_ratio_onepass_over_per_material": eq["wall_s"] / per["wall_s"],
        "fit": {
            "fixed_s": fixed,
            "s_per_spp": slope,
            "onepass_wall_s_at_4spp": four["wall_s"],
            "tries_spp_wall_s": tries,
        },
        "how": (
            f"the per-material basis at {spp} spp sets the time; the one-pass basis gets the spp that "
            f"makes its render_basis wall time equal (wall = fixed + slope * spp fitted from its runs at "
            f"{spp} and {4 * spp} spp, rounded down to a multiple of {spp}; refitted once from the two "
            f"largest runs when 10% off)"
        ),
    }


def blend_errors(scene_path, manifold, m, out, spp, spp_eq, res, ref_spp, seed):
    """Each basis's blend at the midpoint of :func:`gi_comparison.gi_pair` against the full-GI and L1- references."""
    from mitsuba_manifold.imaging import metrics

    a, b = comparison.gi_pair(m)
    x = 0.5 * (m.latent[m.index(a)] + m.latent[m.index(b)])
    ref = scenes.render_reference(
        scene_path, manifold, x, ref_spp, seed=seed + 7919, resolution=(res, res)
    )
    ref_l1 = l1_reference(scene_path, manifold, x, ref_spp, seed + 7919, res)
    blends = {}
    for key, where, s in (
        ("per_material", f"per_material_{spp}", spp),
        ("onepass", f"onepass_{spp}", spp),
        ("onepass_equal_time", f"onepass_{spp_eq}", spp_eq),
    ):
        img, _ = blend(Basis.load(os.path.join(out, where), manifold=m), m, x=x)
        bias, bias_se = comparison.relative_bias(img, ref)
        blends[key] = {
            "spp": s,
            "vs_full_gi": {
                **metrics.compare(img, ref),
                "relative_bias": bias,
                "relative_bias_se": bias_se,
            },
            "vs_l1": metrics.compare(img, ref_l1),
        }
    return {
        "x": x.tolist(),
        "x_is": f"midpoint {a}-{b}",
        "reference_spp": ref_spp,
        "clamped_fraction": m.negative_fraction(x),
        "bases": blends,
        "equal_time_rel_mse_ratio_vs_full_gi": (
            blends["per_material"]["vs_full_gi"]["rel_mse"]
            / blends["onepass_equal_time"]["vs_full_gi"]["rel_mse"]
        ),
        "equal_time_rel_mse_ratio_vs_l1": (
            blends["per_material"]["vs_l1"]["rel_mse"]
            / blends["onepass_equal_time"]["vs_l1"]["rel_mse"]
        ),
        "note": (
            "vs_full_gi includes the L2+ light a blend leaves out (table.xml is concave), the same for "
            "every basis; vs_l1 is the blend's own error (noise)"
        ),
    }

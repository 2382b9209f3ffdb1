"""What the main job does, end to end (``tools/main.py``); the GI benchmark runs the same steps.

1. the MERL-format database (SGD surrogates of the 100 MERL materials),
2. the latent manifold (GPLVM fit, paper Sec. 3) with its summary and plots,
3. the L1- basis of a scene (paper Sec. 5.2, one image per material),
4. blends at a training point, a midpoint and an extrapolated point (Eq. 13), their errors
   against full-GI references, and the error-against-time plot of blending vs re-rendering;
   with ``denoise``, also the blends and the highest-spp direct renders denoised (OIDN guided
   by albedo and normal AOVs that blend like the images, :mod:`denoise`), raw errors kept.

:func:`run_main_job` does all four; :func:`gi_report` steps 3 and 4 (also behind
``tools/bench.py gi``).
"""

import json
import os
import shutil
import time

import numpy as np

from ..data import database
from ..basis import denoise as denoise_mod
from ..imaging import io as imageio, metrics, plots
from ..render import scenes as _scenes  # (gi_report has a parameter named scenes)
from .._util.atomic import write_bytes
from ..basis.folder import Basis
from ..basis.blend import blend, blend_path, path_labels
from ..manifold import paths
from ..manifold.model import Manifold
from ..render.render_basis import render_basis
from .._util.timing import median_time


def gi_pair(m, max_clamped=1e-3, min_share=0.6):
    """Two latent neighbours to interpolate between, for the GI comparison and the path sheet.

    Among the pairs (material, its nearest latent neighbour) whose midpoint is a genuine
    interpolation of the two (their weights there sum to at least ``min_share``) and whose
    midpoint table needs (almost) no clamping, the one whose albedos differ most, so that
    the interpolation is visible. Far-apart pairs cross other materials' regions, where an
    affine combination with large weights of both signs goes negative in many bins; the
    plugin clamps those but a blend cannot, so such a midpoint measures clamping rather
    than Eq. 13.
    """
    d2 = ((m.latent[:, None] - m.latent[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    pairs = sorted({tuple(sorted((i, int(j)))) for i, j in enumerate(d2.argmin(axis=1))})
    alb = m.albedos.mean(axis=1) if m.albedos is not None else np.zeros(m.n)
    best = pairs[0]
    for i, j in sorted(pairs, key=lambda p: -abs(alb[p[0]] - alb[p[1]])):
        x = 0.5 * (m.latent[i] + m.latent[j])
        _, w = m.weights(x)
        if w[i] + w[j] >= min_share and m.negative_fraction(x) <= max_clamped:
            best = (i, j)
            break
    i, j = best
    return m.names[i], m.names[j]


def gi_points(m, a, b):
    """Training point, midpoint and extrapolated point on the latent segment from a to b."""
    xa, xb = m.latent[m.index(a)], m.latent[m.index(b)]
    return [("training", f"{a}", xa), ("midpoint", f"midpoint {a}-{b}", 0.5 * (xa + xb)),
            ("extrapolated", f"{a} + 1.5 ({b} - {a})", xa + 1.5 * (xb - xa))]


def relative_bias(a, ref):
    """Mean relative difference of two images and its standard error (pixels independent)."""
    d = (a - ref).reshape(-1, 3).astype(np.float64).mean(axis=1)
    scale = float(np.mean(ref))
    return float(d.mean() / scale), float(d.std() / np.sqrt(d.size) / scale)


def gi_report(folder, manifold=None, scenes=("sphere", "table"), res=128, basis_spp=64, ref_spp=4096,
              direct_spp=(1, 4, 16, 64, 256, 1024), mode="onepass", out=None, seed=0, save_images=False,
              progress=False, plot=None, denoise=False):
    """Error against run time: the blend (Eq. 13) beside re-rendering the interpolated material.

    For each scene (a shipped scene's name or a path) and latent point (training, midpoint,
    extrapolated, :func:`gi_points` of :func:`gi_pair`): the blend's time and error against
    a high-spp full-GI reference (``path``), and the error and time of direct renders at
    increasing spp. On a convex scene L2+ is zero and the blend is unbiased; on a concave
    one the bias (L2+) is measured. Writes a log-log plot (``plot``, default in ``out``);
    with ``save_images`` also the blends, references and error images (EXR and PNG) and the
    contact sheet of the latent path between the two materials (paper Fig. 12; the path of
    :data:`paths.DEFAULT_KIND`).
    """
    mi = _scenes.use_variant()
    if manifold is None:
        manifold = os.path.join(folder, ".manifold-cache", "bench_q2.npz")
        Manifold.fit(folder, q=2).save(manifold)
    m = Manifold.load(manifold)
    out = out or os.path.join(folder, ".manifold-cache", "bench_gi")
    os.makedirs(out, exist_ok=True)
    pair = gi_pair(m)
    report = {"resolution": res, "basis_spp": basis_spp, "reference_spp": ref_spp, "mode": mode,
              "variant": mi.variant(), "pair": list(pair), "denoise": bool(denoise), "scenes": {}}
    for name in scenes:
        label = os.path.splitext(os.path.basename(name))[0]  # a shipped scene's name, or a file's stem
        report["scenes"][name] = gi_scene(_scenes.scene_path(name), manifold, m, pair, os.path.join(out, label),
                                          res, basis_spp, ref_spp, direct_spp, mode, seed, save_images, progress,
                                          denoise)
    report["plot"] = plots.gi_error_vs_time(report, plot or os.path.join(out, "gi_error_vs_time.png"))
    return report


def gi_scene(scene_path, manifold_path, m, pair, stem, res, basis_spp, ref_spp, direct_spp, mode, seed,
             save_images, progress, denoise=False):
    """:func:`gi_report` for one scene: render its basis (timed, from scratch; with its AOVs
    when ``denoise``), then each point's blend, reference and direct renders; files are
    named ``<stem>_...``."""
    out, name = os.path.dirname(stem), os.path.basename(stem)
    folder_b = os.path.join(out, f"basis_{name}_{res}_{basis_spp}_{mode}")
    if os.path.isdir(folder_b):  # time a whole basis, not a resumed one
        shutil.rmtree(folder_b)
    t0 = time.perf_counter()
    render_basis(scene_path, manifold_path, folder_b, spp=basis_spp, mode=mode, resolution=res, seed=seed,
                 progress=progress, aovs=denoise)
    t_basis = time.perf_counter() - t0
    b = Basis.load(folder_b, manifold=m)
    aovs = denoise_mod.BasisAOVs.load(folder_b, b.manifest) if denoise else None
    rows = []
    for kind, label, x in gi_points(m, *pair):
        t0 = time.perf_counter()
        ref = _scenes.render_reference(scene_path, manifold_path, x, ref_spp, seed=seed + 7919, resolution=(res, res))
        t_ref = time.perf_counter() - t0
        img, info = blend(b, m, x=x)
        t_blend = median_time(lambda: blend(b, m, x=x), 5)[0]
        bias, bias_se = relative_bias(img, ref)
        row = {"point": kind, "x_is": label, "x": np.asarray(x).tolist(), "reference_time_s": t_ref,
               "clamped_fraction": m.negative_fraction(x),
               "blend": {"time_s": t_blend, **metrics.compare(img, ref), "relative_bias": bias,
                         "relative_bias_se": bias_se, "materials_used": int(info["n_images"])},
               "direct": []}
        guides = None
        if aovs is not None:
            guides = (aovs.albedo_of_blend(info, b.manifest["version"]), aovs.normal)
            den, t_den = _denoised(img, guides)
            row["blend"]["denoised"] = {"time_s": t_blend + t_den, "denoise_s": t_den, **metrics.compare(den, ref)}
        for spp in direct_spp:
            t0 = time.perf_counter()
            direct = _scenes.render_reference(scene_path, manifold_path, x, spp, seed=seed + spp, resolution=(res, res))
            entry = {"spp": spp, "time_s": time.perf_counter() - t0, **metrics.compare(direct, ref)}
            if guides is not None and spp == max(direct_spp):  # the same denoiser, for a fair comparison
                d_den, t_den = _denoised(direct, guides)
                entry["denoised"] = {"time_s": entry["time_s"] + t_den, "denoise_s": t_den,
                                     **metrics.compare(d_den, ref)}
            row["direct"].append(entry)
        rows.append(row)
        if save_images:
            _save_point_images(f"{stem}_{kind}", img, ref, den if aovs is not None else None)
        if progress:
            print(f"  {name}: {kind} done (blend rel. MSE {row['blend']['rel_mse']:.3g})", flush=True)
    if save_images:
        images, _, _ = blend_path(b, m, *pair, steps=20, kind=paths.DEFAULT_KIND)
        imageio.write_contact_sheet(f"{stem}_path_sheet.png", images, labels=path_labels(pair, len(images)),
                                    title=f"{pair[0]} (t = 0) to {pair[1]} (t = 1) along a {paths.DEFAULT_KIND} "
                                          "latent path (paths.py)")
        extrapolation_sheet(b, m, pair, f"{stem}_extrapolation_sheet", log=print if progress else None)
    out = {"basis_time_s": t_basis, "basis_images": len(b.keys) + 1, "points": rows,
           "basis_folder": os.path.abspath(folder_b)}
    if aovs is not None:
        out["aovs_time_s"] = aovs.time_s
    return out


def extrapolation_sheet(basis, m, pair, stem, steps=12, reach=3.0, log=None):
    """Contact sheet along the ray from ``pair[0]`` through ``pair[1]`` and on out of the data.

    ``x(t) = x_a + t (x_b - x_a)``, ``t`` from 0 to ``reach``: beyond ``t = 1`` the path leaves
    the data. Each frame is labelled with its plausibility figures (albedo, fraction of the
    table below 0, largest weight); they are also written to ``<stem>.json``. Returns the rows.
    """
    xa, xb = m.latent[m.index(pair[0])], m.latent[m.index(pair[1])]
    ts = np.linspace(0.0, reach, steps)
    rows, images = [], []
    for t in ts:
        x = xa + t * (xb - xa)
        img, _ = blend(basis, m, x=x)
        w = m.weights(x).w
        a = m.albedo(x)
        rows.append({"t": float(t), "x": x.tolist(), "albedo": a.tolist(), "negative_fraction": m.negative_fraction(x),
                     "largest_weight": [m.names[int(np.argmax(w))], float(w.max())]})
        images.append(img)
    labels = extrapolation_labels(rows)
    title = (f"{pair[0]} (t = 0) through {pair[1]} (t = 1) and on out of the data; under each frame: t, "
             f"albedo (mean RGB), neg.: share of the table's bins below 0")
    imageio.write_contact_sheet(stem + ".png", np.stack(images), labels=labels, columns=6, title=title)
    write_bytes(stem + ".json", json.dumps({"from": pair[0], "through": pair[1], "rows": rows}, indent=1))
    if log:
        for r, lab in zip(rows, labels):
            rgb = ", ".join(f"{v:.3f}" for v in r["albedo"])
            log(f"  extrapolation {lab.replace(chr(10), ', ')}, albedo RGB {rgb}, "
                f"largest weight {r['largest_weight'][0]} {r['largest_weight'][1]:.2f}")
    return rows


def extrapolation_labels(rows):
    """One label per frame of :func:`extrapolation_sheet`, a field per line (they read on 64 px
    tiles): ``t``, the albedo (mean RGB), the share of the table's bins below 0."""
    return [f"t = {r['t']:.2f}\nalbedo {np.mean(r['albedo']):.2f}\nneg. {100 * r['negative_fraction']:.1f}%"
            for r in rows]


def _denoised(image, guides):
    """OIDN on ``image`` with (albedo, normal) guides; returns the image and the seconds it took."""
    out = denoise_mod.denoise(image, *guides)
    return out, median_time(lambda: denoise_mod.denoise(image, *guides), 3)[0]


def _save_point_images(stem, img, ref, denoised=None):
    pairs = (("blend", img), ("reference", ref)) + ((("blend_denoised", denoised),) if denoised is not None else ())
    for suffix, image in pairs:
        imageio.write_exr(f"{stem}_{suffix}.exr", image)
        imageio.write_png(f"{stem}_{suffix}.png", image)
    vmax = metrics.write_error_png(f"{stem}_error.png", img, ref)
    if denoised is not None:   # on the raw error's scale, so that the two compare by eye
        metrics.write_error_png(f"{stem}_denoised_error.png", denoised, ref, vmax=vmax,
                                scale_note="the raw blend's error scale")


def versus_direct(row, spp):
    """Issue 13's targets for one point of :func:`gi_report`: the blend against the direct render
    at ``spp`` (lower relative MSE, at least 100x faster per image)."""
    b, d = row["blend"], next(r for r in row["direct"] if r["spp"] == spp)
    speedup = d["time_s"] / b["time_s"]
    return {"direct_spp": int(spp), "speedup": speedup, "meets_speed_target": bool(speedup >= 100),
            "meets_error_target": bool(b["rel_mse"] < d["rel_mse"])}


def check_main_job(out, resolution, q, scene, res, spp, ref_spp, direct_spp=(1,), mode="onepass"):
    """Check the main job's settings before anything is computed or written; raises
    :class:`~mitsuba_manifold.errors.InputError` naming the option (as ``tools/main.py``
    spells it), the value and the fix. Returns the scene's path."""
    from .._util import checks as validate
    from ..data import merl
    from ..gp.kernel import MAX_LATENT_DIM

    validate.output_folder("--out", out)
    merl.table_resolution(resolution, "--resolution")
    if q is not None:
        validate.positive_int("--q", q, "3", hi=MAX_LATENT_DIM)
    path = _scenes.check_scene("--scene", scene)
    validate.positive_int("--res", res, "256")
    held = len(database.load_sgd_fits()) + 2 if mode == "onepass" else 6   # as render_basis holds them
    validate.fits_in_memory("--res", 2 * held * res * res * 3 * 4, f"{mode} basis images of {res}x{res}")
    validate.positive_int("--spp", spp, "1024")
    validate.positive_int("--ref-spp", ref_spp, "2048")
    for s in direct_spp:
        validate.positive_int("direct_spp", s, "64")
    return path


def run_main_job(out, resolution=(90, 90, 180), q=None, features=None, scene="table", res=256, spp=1024,
                 ref_spp=2048, mode="onepass", direct_spp=(1, 4, 16, 64, 256), denoise=True, log=print,
                 preset="default"):
    """The main job: database, manifold, plots, basis and blends of ``scene``, ``gi/report.json``.

    ``log(text)`` reports progress (stages and results). Returns the GI report (with
    ``report_path`` and ``stages``: the measured seconds of each stage).
    """
    check_main_job(out, resolution, q, scene, res, spp, ref_spp, direct_spp, mode)
    t_start = time.perf_counter()
    stages = {}
    db_dir = os.path.join(out, "database")
    manifold_path = os.path.join(out, "manifold.npz")
    log(f"\n== database: {db_dir}")
    t0 = time.perf_counter()
    database.make_database(db_dir, resolution, progress=True)
    stages["tabulate_s"] = time.perf_counter() - t0
    log(f"100 tables ready ({stages['tabulate_s']:.1f} s)")

    log(f"\n== manifold: preset {preset}" + (f", q={q}" if q else "") + (f", features={features}" if features else ""))
    m = Manifold.fit(db_dir, q=q, features=features, preset=preset, progress=True)
    m.save(manifold_path)
    stages.update(load_s=m.info["time_load_s"], gram_s=m.info["time_gram_s"], fit_s=m.info["time_fit_s"])
    log(m.summary())
    log(f"load {m.info['time_load_s']:.1f} s, Gram {m.info['time_gram_s']:.1f} s, "
        f"optimisation {m.info['time_fit_s']:.1f} s; saved {manifold_path}")
    t0 = time.perf_counter()
    for path in plots.write_fit_plots(m, os.path.join(out, "plots")):
        log(f"plot: {path}")
    stages["plots_s"] = time.perf_counter() - t0

    log(f"\n== basis of {scene} and blends ({res}x{res}, {spp} spp basis, {ref_spp} spp references)")
    t0 = time.perf_counter()
    report = gi_report(db_dir, manifold=manifold_path, scenes=(scene,), res=res, basis_spp=spp,
                       ref_spp=ref_spp, mode=mode, direct_spp=direct_spp, out=os.path.join(out, "gi"),
                       save_images=True, progress=True, denoise=denoise)
    t_gi = time.perf_counter() - t0
    sc = report["scenes"][scene]
    stages["basis_s"] = sc["basis_time_s"]
    stages["references_s"] = sum(r["reference_time_s"] for r in sc["points"])
    stages["direct_renders_s"] = sum(d["time_s"] for r in sc["points"] for d in r["direct"])
    stages["blends_images_plot_s"] = t_gi - stages["basis_s"] - stages["references_s"] - stages["direct_renders_s"]
    log(f"basis: {sc['basis_images']} images in {sc['basis_time_s']:.1f} s"
        + (f" (AOVs {sc['aovs_time_s']:.1f} s)" if "aovs_time_s" in sc else ""))
    top = max(direct_spp)
    for row in sc["points"]:
        b = row["blend"]
        d = next(r for r in row["direct"] if r["spp"] == top)
        v = row["versus_direct"] = versus_direct(row, top)
        log(f"{row['point']:>12s} ({row['x_is']}): blend {1e3 * b['time_s']:.1f} ms, rel. MSE {b['rel_mse']:.3g}, "
            f"PSNR {b['psnr']:.1f} dB, bias {100 * b['relative_bias']:+.2f}% | direct {top} spp "
            f"{d['time_s']:.2f} s, rel. MSE {d['rel_mse']:.3g} | blend {v['speedup']:.0f}x faster, "
            f"{'lower' if v['meets_error_target'] else 'HIGHER'} error")
        if "denoised" in b:
            log(f"{'':>12s} denoised (OIDN, albedo+normal): blend {1e3 * b['denoised']['time_s']:.0f} ms, "
                f"rel. MSE {b['denoised']['rel_mse']:.3g} (raw {b['rel_mse']:.3g}) | direct {top} spp "
                f"rel. MSE {d['denoised']['rel_mse']:.3g} (raw {d['rel_mse']:.3g})")
    report_path = os.path.join(out, "gi", "report.json")
    stages["total_s"] = time.perf_counter() - t_start
    report["stages"] = stages
    write_bytes(report_path, json.dumps(report, indent=1))
    log(f"plot: {report['plot']}\nreport: {report_path}\nimages: {os.path.join(out, 'gi')}")
    log("stages: " + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in stages.items() if k != "total_s"))
    from .cli.explore import command
    log(f"\nexplore the manifold in the browser:\n  {command(sc['basis_folder'], manifold_path)}")
    log(f"\nmain job done in {time.perf_counter() - t_start:.0f} s")
    report["report_path"] = report_path
    return report

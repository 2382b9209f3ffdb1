"""The GI comparison (steps 3 and 4 of the main job, :mod:`mitsuba_manifold.apps.pipeline`;
also ``tools/bench.py gi``): the blend (paper Eq. 13) beside re-rendering the interpolated
material, error against run time.

A basis of the scene is rendered (timed, from scratch; a one-pass basis holds full-GI images
where the scene needs them, and the report gives its default full-GI blend and, beside it,
its L1- blend); at a training point, a midpoint and
an extrapolated point on the segment between two latent neighbours (:func:`gi_pair`) the
blend is compared with a high-spp full-GI reference, beside direct renders at increasing
spp; with ``denoise`` the blends and the highest-spp direct render are also denoised (OIDN
guided by albedo and normal AOVs that blend like the images, :mod:`~mitsuba_manifold.basis.denoise`),
raw errors kept. :func:`gi_report` writes the log-log plot and, with ``save_images``, the
images and the contact sheets of the latent path (paper Fig. 12) and of the extrapolation.
"""

import json
import os
import time
from dataclasses import dataclass, replace

import numpy as np

from .._util.atomic import write_bytes
from .._util.memory import peak_rss
from .._util.timing import median_time
from ..basis import denoise as denoise_mod
from ..basis.blend import BlendSettings, blend, blend_path, path_labels
from ..basis.folder import Basis
from ..basis.folder.owned_files import remove_basis
from ..data.database import database_cache
from ..imaging import io as imageio
from ..imaging import metrics, plots
from ..manifold import paths
from ..manifold.appearance import lab
from ..manifold.model import Manifold
from ..render.jobs.refine import forget_kept, refine
from ..render.jobs.render_basis import render_basis
from ..render.scene import scenes as _scenes  # (gi_report has a parameter named scenes)


def gi_pair(m, max_clamped=1e-3, min_share=0.6):
    """Two latent neighbours to interpolate between, for the GI comparison and the path sheet.

    The rule: among the pairs (material, its nearest latent neighbour) whose midpoint is a
    genuine interpolation of the two (their weights there sum to at least ``min_share``) and
    whose midpoint table needs (almost) no clamping, the one whose ends differ most in colour,
    the CIELAB distance (``Delta E*ab``, D65; :func:`..manifold.appearance.lab`) of their
    albedos, so that the path visibly changes (in hue, not only in lightness). Far-apart pairs
    cross other materials' regions, where an affine combination with large weights of both
    signs goes negative in many bins; the plugin clamps those but a blend cannot, so such a
    midpoint measures clamping rather than Eq. 13.
    """
    d2 = ((m.latent[:, None] - m.latent[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    pairs = sorted({tuple(sorted((i, int(j)))) for i, j in enumerate(d2.argmin(axis=1))})
    colour = lab(m.albedos) if m.albedos is not None else np.zeros((m.n, 3))
    best = pairs[0]
    for i, j in sorted(pairs, key=lambda p: -float(np.linalg.norm(colour[p[0]] - colour[p[1]]))):
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
    return [
        ("training", f"{a}", xa),
        ("midpoint", f"midpoint {a}-{b}", 0.5 * (xa + xb)),
        ("extrapolated", f"{a} + 1.5 ({b} - {a})", xa + 1.5 * (xb - xa)),
    ]


def relative_bias(a, ref):
    """Mean relative difference of two images and its standard error (pixels independent)."""
    d = (a - ref).reshape(-1, 3).astype(np.float64).mean(axis=1)
    scale = float(np.mean(ref))
    return float(d.mean() / scale), float(d.std() / np.sqrt(d.size) / scale)


@dataclass(frozen=True)
class GISettings:
    """What :func:`gi_report` renders and measures (every field is also a keyword of it).

    Attributes
    ----------
    res : int
        Square image size.
    basis_spp, ref_spp : int
        Samples per pixel of the basis and of the full-GI references (``path``).
    direct_spp : tuple of int
        Samples per pixel of the direct renders the blend is compared with.
    mode : {"onepass", "per-material"}
        How the basis is rendered (:func:`~mitsuba_manifold.render.jobs.render_basis.render_basis`).
    seed : int
    save_images : bool
        Also write the blends, references and error images (EXR and PNG) and the contact
        sheets of the latent path (paper Fig. 12) and of the extrapolation.
    progress : bool
        Print a line per point.
    denoise : bool
        Also denoise the blends and the highest-spp direct render (OIDN, AOV guides).
    refine_spp : int
        Samples per pixel of the refined blend (``blend.py --refine``) at each point (0: none), in
        two passes (the fewest that estimate its noise).
    """

    res: int = 128
    basis_spp: int = 64
    ref_spp: int = 4096
    direct_spp: tuple = (1, 4, 16, 64, 256, 1024)
    mode: str = "onepass"
    seed: int = 0
    save_images: bool = False
    progress: bool = False
    denoise: bool = False
    refine_spp: int = 0


def gi_report(
    folder,
    manifold=None,
    scenes=("sphere", "table"),
    out=None,
    plot=None,
    settings=None,
    **overrides,
):
    """Error against run time: the blend (Eq. 13) beside re-rendering the interpolated material.

    For each scene (a shipped scene's name or a path) and latent point (training, midpoint,
    extrapolated, :func:`gi_points` of :func:`gi_pair`): the blend's time and error against
    a high-spp full-GI reference (``path``), and the error and time of direct renders at
    increasing spp. On a convex scene L2+ is zero and the blend is unbiased; on a concave
    one the bias (L2+) is measured. Writes a log-log plot (``plot``, default in ``out``).
    ``settings`` (:class:`GISettings`, with ``overrides`` of its fields) says what is
    rendered and written.
    """
    opts = replace(settings or GISettings(), **overrides)
    mi = _scenes.use_variant()
    if manifold is None:
        manifold = os.path.join(database_cache(folder), "bench_q2.npz")
        Manifold.fit(folder, q=2).save(manifold)
    m = Manifold.load(manifold)
    out = out or os.path.join(database_cache(folder), "bench_gi")
    os.makedirs(out, exist_ok=True)
    pair = gi_pair(m)
    report = {
        "resolution": opts.res,
        "basis_spp": opts.basis_spp,
        "reference_spp": opts.ref_spp,
        "mode": opts.mode,
        "variant": mi.variant(),
        "pair": list(pair),
        "denoise": bool(opts.denoise),
        "scenes": {},
    }
    for name in scenes:
        label = os.path.splitext(os.path.basename(name))[
            0
        ]  # a shipped scene's name, or a file's stem
        report["scenes"][name] = gi_scene(
            _scenes.scene_path(name), manifold, m, pair, os.path.join(out, label), opts
        )
    report["plot"] = plots.gi_error_vs_time(
        report, plot or os.path.join(out, "gi_error_vs_time.png")
    )
    return report


def gi_scene(scene_path, manifold_path, m, pair, stem, settings):
    """:func:`gi_report` for one scene: render its basis (timed, from scratch; with its AOVs
    when ``settings.denoise``), then each point's blend, reference and direct renders; files
    are named ``<stem>_...``. ``peak_rss_after`` gives the process's peak memory (bytes,
    :func:`~mitsuba_manifold._util.memory.peak_rss`) at the end of the basis, of each point and
    of the contact sheets: the step where it grows holds the new peak.
    """
    opts = settings
    out, name = os.path.dirname(stem), os.path.basename(stem)
    folder_b = os.path.join(out, f"basis_{name}_{opts.res}_{opts.basis_spp}_{opts.mode}")
    remove_basis(folder_b)  # time a whole basis, not a resumed one (only a basis of its own)
    t0 = time.perf_counter()
    render_basis(
        scene_path,
        manifold_path,
        folder_b,
        spp=opts.basis_spp,
        mode=opts.mode,
        resolution=opts.res,
        seed=opts.seed,
        progress=opts.progress,
        aovs=opts.denoise,
        components="full" if opts.mode == "onepass" else "l1",
    )
    t_basis = time.perf_counter() - t0
    peak = {"basis": peak_rss()}  # the process's peak memory at the end of each step
    b = Basis.load(folder_b, manifold=m)
    aovs = denoise_mod.BasisAOVs.load(folder_b, b.manifest) if opts.denoise else None
    rows = []
    for kind, label, x in gi_points(m, *pair):
        row, images = _gi_point(scene_path, manifold_path, b, m, x, aovs, opts)
        rows.append({"point": kind, "x_is": label, **row})
        if opts.save_images:
            _save_point_images(f"{stem}_{kind}", *images)
        peak[kind] = peak_rss()
        if opts.progress:
            print(
                f"  {name}: {kind} done (blend rel. MSE {row['blend']['rel_mse']:.3g})", flush=True
            )
    if opts.save_images:
        l2 = "denoised" if opts.denoise else "raw"
        images, _, _ = blend_path(
            b, m, *pair, steps=20, kind=paths.DEFAULT_KIND, settings=BlendSettings(l2=l2)
        )
        imageio.write_contact_sheet(
            f"{stem}_path_sheet.png",
            images,
            labels=path_labels(pair, len(images)),
            title=f"{pair[0]} (t = 0) to {pair[1]} (t = 1) along a {paths.DEFAULT_KIND} "
            "latent path",
        )
        extrapolation_sheet(
            b, m, pair, f"{stem}_extrapolation_sheet", log=print if opts.progress else None, l2=l2
        )
    peak["sheets"] = peak_rss()
    out = {
        "basis_time_s": t_basis,
        "basis_images": len(b.keys) + 1,
        "points": rows,
        "basis_folder": os.path.abspath(folder_b),
        "peak_rss_after": peak,
    }
    if aovs is not None:
        out["aovs_time_s"] = aovs.time_s
    return out


#: Direct renders of at most this many spp are timed after an untimed one of the same spp: their
#: time is the render's, not compiling's (which would put a 1-spp render after a 4-spp one).
WARM_SPP = 64


def timed_render(render, spp, seed):
    """``(image, seconds)`` of ``render(spp, seed)``; at most :data:`WARM_SPP` spp, an untimed
    ``render(spp, seed + 1)`` first compiles its kernels (the sample count is in them).
    """
    if spp <= WARM_SPP:
        render(spp, seed + 1)
    t0 = time.perf_counter()
    image = render(spp, seed)
    return image, time.perf_counter() - t0


def _gi_point(scene_path, manifold_path, b, m, x, aovs, opts):
    """One latent point of :func:`gi_scene`: the blend (and its denoised image) against the
    reference, beside the direct renders. Returns the report row and the images
    ``(blend, reference, denoised blend or None)``.
    """
    res = (opts.res, opts.res)
    t0 = time.perf_counter()
    ref = _scenes.render_reference(
        scene_path, manifold_path, x, opts.ref_spp, seed=opts.seed + 7919, resolution=res
    )
    t_ref = time.perf_counter() - t0
    l2 = "denoised" if opts.denoise else "raw"  # without the denoiser, the blends as summed
    img, info = blend(b, m, x=x, l2=l2)
    t_blend = median_time(lambda: blend(b, m, x=x, l2=l2), 5)[0]
    bias, bias_se = relative_bias(img, ref)
    row = {
        "x": np.asarray(x).tolist(),
        "reference_time_s": t_ref,
        "clamped_fraction": m.negative_fraction(x),
        "blend": {
            "time_s": t_blend,
            **metrics.compare(img, ref),
            "relative_bias": bias,
            "relative_bias_se": bias_se,
            "materials_used": int(info.n_images),
            "component": info.component,
        },
        "direct": [],
    }
    if info.l2 == "denoised":  # the same blend as summed (the explorer while dragging)
        raw, _ = blend(b, m, x=x, l2="raw")
        raw_bias, raw_se = relative_bias(raw, ref)
        row["blend_summed"] = {
            "time_s": median_time(lambda: blend(b, m, x=x, l2="raw"), 5)[0],
            **metrics.compare(raw, ref),
            "relative_bias": raw_bias,
            "relative_bias_se": raw_se,
        }
    if info.component == "full":  # the L1- blend of the same basis beside it
        l1, _ = blend(b, m, x=x, component="l1")
        l1_bias, l1_se = relative_bias(l1, ref)
        row["blend_l1"] = {
            **metrics.compare(l1, ref),
            "relative_bias": l1_bias,
            "relative_bias_se": l1_se,
        }
    if opts.refine_spp:
        row["refined"] = refined_row(
            b, m, x, ref, opts.refine_spp, opts.seed + 104729, warm=True, l2=l2
        )  # warm: as the direct renders
    guides = den = None
    if aovs is not None:
        guides = (aovs.albedo_of_blend(info.plan, b.manifest.version), aovs.normal)
        den, t_den = _denoised(img, guides)
        row["blend"]["denoised"] = {
            "time_s": t_blend + t_den,
            "denoise_s": t_den,
            **metrics.compare(den, ref),
        }
    for spp in opts.direct_spp:
        direct, t_direct = timed_render(
            lambda n, seed: _scenes.render_reference(
                scene_path, manifold_path, x, n, seed=seed, resolution=res
            ),
            spp,
            opts.seed + spp,
        )
        entry = {"spp": spp, "time_s": t_direct, **metrics.compare(direct, ref)}
        if guides is not None and spp == max(
            opts.direct_spp
        ):  # the same denoiser, for a fair comparison
            d_den, t_den = _denoised(direct, guides)
            entry["denoised"] = {
                "time_s": entry["time_s"] + t_den,
                "denoise_s": t_den,
                **metrics.compare(d_den, ref),
            }
        row["direct"].append(entry)
    return row, (img, ref, den)


def refined_row(b, m, x, ref, spp, seed, warm=False, l2="denoised"):
    """``blend.py --refine spp`` at ``x`` (:func:`~mitsuba_manifold.render.jobs.refine.refine`) against
    ``ref``: error, bias, the noise it estimates, and its time as the explorer has it at a newly
    chosen point (``time_s``: the scene kept from the last refinement, the point's tables built)
    and from nothing (``time_cold_s``: the scene loaded, as a new ``blend.py`` process does);
    ``l2``: the full-GI blend's light beyond L1- as :func:`blend` takes it; ``warm``: its kernels
    compiled first, as the direct renders' are (by a refinement of the same
    samples and passes: the sample count is in the kernels, so a warm-up of other samples
    leaves compiling in the timed refinement).
    """
    passes = min(2, spp)
    if warm:
        refine(b, m, x=x, spp=spp, passes=passes, seed=seed + 1, l2=l2)
    forget_kept(scene=False)
    t0 = time.perf_counter()
    r = refine(b, m, x=x, spp=spp, passes=passes, seed=seed, l2=l2)
    t_new = time.perf_counter() - t0
    forget_kept()
    t0 = time.perf_counter()
    refine(b, m, x=x, spp=spp, passes=passes, seed=seed, l2=l2)
    t_cold = time.perf_counter() - t0
    forget_kept()  # the scene and the point's tables are not needed by what follows
    bias, se = relative_bias(r.image, ref)
    return {
        "spp": spp,
        "time_s": t_new,
        "time_cold_s": t_cold,
        **metrics.compare(r.image, ref),
        "relative_bias": bias,
        "relative_bias_se": se,
        "noise_rel_mse": r.noise_rel_mse,
    }


def extrapolation_sheet(basis, m, pair, stem, steps=12, reach=3.0, log=None, l2="denoised"):
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
        img, _ = blend(basis, m, x=x, l2=l2)
        w = m.weights(x).w
        a = m.albedo(x)
        rows.append(
            {
                "t": float(t),
                "x": x.tolist(),
                "albedo": a.tolist(),
                "negative_fraction": m.negative_fraction(x),
                "largest_weight": [m.names[int(np.argmax(w))], float(w.max())],
            }
        )
        images.append(img)
    labels = extrapolation_labels(rows)
    title = (
        f"{pair[0]} (t = 0) through {pair[1]} (t = 1) and on out of the data; under each frame: t, "
        f"albedo (mean RGB), neg.: share of the table's bins below 0"
    )
    imageio.write_contact_sheet(
        stem + ".png", np.stack(images), labels=labels, columns=6, title=title
    )
    write_bytes(
        stem + ".json", json.dumps({"from": pair[0], "through": pair[1], "rows": rows}, indent=1)
    )
    if log:
        for r, lab in zip(rows, labels):
            rgb = ", ".join(f"{v:.3f}" for v in r["albedo"])
            log(
                f"  extrapolation {lab.replace(chr(10), ', ')}, albedo RGB {rgb}, "
                f"largest weight {r['largest_weight'][0]} {r['largest_weight'][1]:.2f}"
            )
    return rows


def extrapolation_labels(rows):
    """One label per frame of :func:`extrapolation_sheet`, a field per line (they read on 64 px
    tiles): ``t``, the albedo (mean RGB), the share of the table's bins below 0.
    """
    return [
        f"t = {r['t']:.2f}\nalbedo {np.mean(r['albedo']):.2f}\nneg. {100 * r['negative_fraction']:.1f}%"
        for r in rows
    ]


def _denoised(image, guides):
    """OIDN on ``image`` with (albedo, normal) guides; returns the image and the seconds it took."""
    out = denoise_mod.denoise(image, *guides)
    return out, median_time(lambda: denoise_mod.denoise(image, *guides), 3)[0]


def _save_point_images(stem, img, ref, denoised=None):
    pairs = (("blend", img), ("reference", ref)) + (
        (("blend_denoised", denoised),) if denoised is not None else ()
    )
    for suffix, image in pairs:
        imageio.write_exr(f"{stem}_{suffix}.exr", image)
        imageio.write_png(f"{stem}_{suffix}.png", image)
    vmax = metrics.write_error_png(f"{stem}_error.png", img, ref)
    if denoised is not None:  # on the raw error's scale, so that the two compare by eye
        metrics.write_error_png(
            f"{stem}_denoised_error.png",
            denoised,
            ref,
            vmax=vmax,
            scale_note="the raw blend's error scale",
        )


def versus_direct(row, spp):
    """The targets for one point of :func:`gi_report`: the blend against the direct render
    at ``spp`` (lower relative MSE, at least 100x faster per image).
    """
    b, d = row["blend"], next(r for r in row["direct"] if r["spp"] == spp)
    speedup = d["time_s"] / b["time_s"]
    return {
        "direct_spp": int(spp),
        "speedup": speedup,
        "meets_speed_target": bool(speedup >= 100),
        "meets_error_target": bool(b["rel_mse"] < d["rel_mse"]),
    }

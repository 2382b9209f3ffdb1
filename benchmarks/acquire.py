"""``tools/bench.py acquire``: a material acquired from one photo, judged in a new view and light.

Photos: the sphere of :mod:`.acquire_scenes` (the shipped ``sphere.xml`` set-up: sky map and a
point light), 64x64, of materials that are not in the manifold: the built-in ``rgl`` (51) and
``nielsen`` (8) networks (rendered through their tables: a manifold of each set, every material's
image in one pass, 512 spp) and the real RGL-EPFL files of ``measured_dir`` (Mitsuba's
``measured`` plugin, ``path``, 1024 spp). Each photo is acquired with
:func:`mitsuba_manifold.render.inverse.acquire.acquire` on a manifold of ``merl`` only (default options;
the training images kept in a cache per scene, so the first photo's time includes their render
and the others' do not; ``cold`` photos are also acquired without the cache).

The judge: the judging scene (another camera, the sky map turned and dimmed, another point light
and a spherical area light); the acquired weights' image there is ``base + sum_i w_i J_i`` from
the training materials' images ``J_i`` rendered in it once at ``judge_spp`` (exact for the convex
sphere alone: no light scatters twice off it); the reference is the measured material rendered
there (the networks: one pass at ``judge_spp``; the files: ``measured`` at 8192 spp), twice with
independent seeds (``noise``: the relative RMSE between the two).

relative RMSE = sqrt(mean over the sphere's pixels and RGB of (a - r)^2 / (r^2 + 0.01))
(:func:`mitsuba_manifold.imaging.metrics.rel_mse` over the pixels the sphere covers entirely).

Compared: the acquisition, the best single training material (the acquisition's ``single``),
and a plain non-negative least-squares fit (SciPy's ``nnls``) of the same training images to the
photo in linear RGB. Split: ``tune`` (every other rgl network, sorted by name, without the three
that have real files) is what the method's choices were made on; ``held-out`` (the other rgl
networks, the 8 nielsen networks, the networks and the files of the three real measurements)
was never looked at while tuning.
"""

import os
import time

import numpy as np
import scipy.optimize

from . import acquire_scenes as S

RES = 64
PHOTO_SPP = 512
FILE_PHOTO_SPP = 1024
JUDGE_SPP = 4096
FILE_JUDGE_SPP = 8192
REL_EPS = 0.01
TARGET_MEDIAN = 0.12
REAL = ("ilm_l3_37_metallic", "paper_blue", "vch_golden_yellow")
#: Photos acquired without the training images' cache (the time of a first photo).
COLD = 3


def _rrmse(a, r):
    return float(np.sqrt(np.mean((a - r) ** 2 / (r * r + REL_EPS))))


def _fit(setname, out):
    from mitsuba_manifold.apps.cli import fit_manifold

    path = os.path.join(out, f"{setname}.npz")
    if not os.path.exists(path):
        fit_manifold.main([setname, "--out", path])
    return path


def _onepass(scene, manifold, spp, seed):
    from mitsuba_manifold.render.jobs.render_basis import _integrator
    from mitsuba_manifold.render.scene import scenes

    ls = scenes.load_scene(scene, manifold, spp, RES, None)
    base, images = _integrator("l1", ls.integrator).render_onepass(ls.scene, spp=spp, seed=seed)
    names = list(images)
    stack = np.stack([np.asarray(images[n], dtype=np.float32)[..., :3] for n in names])
    return np.asarray(base, dtype=np.float32)[..., :3], stack, names


def _cached(path, make):
    if os.path.exists(path):
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    value = make()
    np.savez(path, **value)
    return value


def _data(out, manifold, measured_dir):
    """Photos and references of every material, and the judging scene's training images."""
    import mitsuba as mi

    photo = S.write_scene(os.path.join(out, "photo.xml"), "photo")
    judge = S.write_scene(os.path.join(out, "judge.xml"), "judge")

    def merl_judge():
        base, images, names = _onepass(judge, manifold, JUDGE_SPP, 4101)
        return {"base": base, "images": images, "names": np.array(names)}

    mj = _cached(os.path.join(out, "merl_judge.npz"), merl_judge)
    materials = []
    for setname in ("rgl", "nielsen"):

        def make(setname=setname):
            m = _fit(setname, out)
            bp, P, names = _onepass(photo, m, PHOTO_SPP, 1001)
            b1, J1, _ = _onepass(judge, m, JUDGE_SPP, 2101)
            b2, J2, _ = _onepass(judge, m, JUDGE_SPP, 3101)
            return {"names": np.array(names), "photo": P + bp, "judge": J1 + b1, "judge2": J2 + b2}

        d = _cached(os.path.join(out, f"{setname}_data.npz"), make)
        for i, n in enumerate(d["names"].tolist()):
            materials.append((f"{setname}:{n}", d["photo"][i], d["judge"][i], d["judge2"][i]))
    if measured_dir and os.path.isdir(measured_dir):
        for f in sorted(os.listdir(measured_dir)):
            if not f.endswith(".bsdf"):
                continue
            src = os.path.join(measured_dir, f)

            def make(src=src, f=f):
                images = {}
                for kind, spps in (("photo", (FILE_PHOTO_SPP,)), ("judge", (FILE_JUDGE_SPP,) * 2)):
                    xml = S.write_scene(
                        os.path.join(out, f"{kind}_{f}.xml"), kind, S.measured_bsdf(src)
                    )
                    sc = mi.load_file(xml, res=RES)
                    images[kind] = np.stack(
                        [
                            np.asarray(mi.render(sc, spp=s, seed=5000 + k), dtype=np.float32)[
                                ..., :3
                            ]
                            for k, s in enumerate(spps)
                        ]
                    )
                return images

            d = _cached(os.path.join(out, f"file_{f[:-5]}.npz"), make)
            name = f[:-5].removesuffix("_rgb")
            materials.append((f"file:{name}", d["photo"][0], d["judge"][0], d["judge"][1]))
    return photo, mj, materials


#: The tuning set: every other rgl network in the set's order, leaving out the three that have
#: real files (the method's choices were made on these only).
TUNE = (
    "acrylic_felt_green acrylic_felt_pink acrylic_felt_white aurora_white cc_amber_citrine "
    "cc_green_malachite cc_iris_purple_gem cg_sunflower chm_mint cm_military_green cm_white "
    "colodur_connemara_4c colodur_napoli_4f ilm_l3_37_matte ilm_solo_millennium_falcon "
    "irid_flake_paint1 laika_ceiling_paint_18_gray paper_green paper_white satin_blue satin_purple "
    "satin_white vch_dragon_eye_red vch_silk_blue"
).split()


def split(materials):
    """``(tune, held_out)`` names: :data:`TUNE`, and every other material."""
    tune = [n for n, *_ in materials if n.startswith("rgl:") and n[4:] in TUNE]
    held = [n for n, *_ in materials if n not in tune]
    return tune, held


def run(
    folder=None,
    manifold=None,
    out=None,
    part="all",
    measured_dir=None,
    limit=None,
    shard=(0, 1),
    on_row=None,
):
    """Acquire every photo of ``part`` (``tune``, ``held-out`` or ``all``; ``shard`` ``(i, n)``:
    every n-th from the i-th) and judge it.
    """
    from mitsuba_manifold.basis.inverse.acquisition import AcquireOptions
    from mitsuba_manifold.render.inverse.acquire import Photo, acquire
    from mitsuba_manifold.render.scene import scenes

    out = os.path.abspath(out or "bench_acquire_work")
    os.makedirs(out, exist_ok=True)
    scenes.use_variant(jit=True)
    manifold = manifold or _fit("merl", out)
    if measured_dir is None:
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        measured_dir = os.path.join(root, "..", "shared", "data", "rgl")
    photo_xml, mj, materials = _data(out, manifold, measured_dir)
    tune, held = split(materials)
    chosen = {"tune": tune, "held-out": held, "all": held + tune}[part]
    by_name = {m[0]: m for m in materials}
    materials = [by_name[n] for n in chosen][shard[0] :: shard[1]][:limit]
    jbase, jimg = mj["base"].astype(np.float64), mj["images"].astype(np.float64)
    jmask = (jbase.sum(-1) == 0) & (jimg.sum((0, 3)) > 0)
    n = len(jimg)
    Aj, bj = jimg[:, jmask].reshape(n, -1).T, jbase[jmask].reshape(-1)
    cache = os.path.join(out, "training_images")
    rows = []
    for k, (name, P, J, J2) in enumerate(materials):
        cold = k < COLD and shard[0] == 0
        opts = (
            AcquireOptions(progress=False)  # everything a user runs, nothing cached
            if cold
            else AcquireOptions(progress=False, basis_cache=cache, bootstrap=0, render_spp=0)
        )
        t0 = time.perf_counter()
        got = acquire([Photo(photo_xml, P.astype(np.float64))], manifold, opts)
        seconds = time.perf_counter() - t0
        r = got.result
        ref = J[jmask].reshape(-1).astype(np.float64)
        w = np.asarray(r.w)
        single = np.eye(n)[r.names.index(r.single["name"])]
        # the plain fit: the acquisition's own training images (the cached ones), linear RGB
        from mitsuba_manifold.render.inverse.acquire import render_training_images

        tr = render_training_images(
            photo_xml, manifold, (RES, RES), AcquireOptions(basis_cache=cache), 0
        )
        mask = got.masks[0] > 0
        A = tr.images[:, mask].reshape(n, -1).T.astype(np.float64)
        w_nnls, _ = scipy.optimize.nnls(A, (P[mask] - tr.base[mask]).reshape(-1))
        row = {
            "material": name,
            "split": "tune" if name in tune else "held-out",
            "acquired": _rrmse(Aj @ w + bj, ref),
            "single": _rrmse(Aj @ single + bj, ref),
            "single_name": r.single["name"],
            "nnls": _rrmse(Aj @ w_nnls + bj, ref),
            "noise": _rrmse(J2[jmask].reshape(-1).astype(np.float64), ref),
            "photo_error": r.error,
            "regularisation": r.regularisation,
            "seconds": seconds,
            "cold": cold,
            "timings": r.timings,
            "warnings": r.warnings,
            "spread": r.spread,
            "load": os.getloadavg()[0],
        }
        rows.append(row)
        if on_row is not None:
            on_row(rows)
        print(
            f"{name:40s} acquired {row['acquired']:.3f} single {row['single']:.3f} "
            f"nnls {row['nnls']:.3f} noise {row['noise']:.3f} {seconds:.1f} s",
            flush=True,
        )
    return summarise(rows)


def summarise(rows):
    """Medians per split and over all, the targets and whether they are met."""

    def med(sel, key):
        vals = [r[key] for r in sel]
        return float(np.median(vals)) if vals else None

    out = {"materials": rows, "target_median": TARGET_MEDIAN}
    for name, sel in (
        ("all", rows),
        ("tune", [r for r in rows if r["split"] == "tune"]),
        ("held_out", [r for r in rows if r["split"] == "held-out"]),
    ):
        if not sel:
            continue
        out[name] = {
            "n": len(sel),
            "acquired": med(sel, "acquired"),
            "single": med(sel, "single"),
            "nnls": med(sel, "nnls"),
            "noise": med(sel, "noise"),
            "better_than_single": int(sum(r["acquired"] < r["single"] for r in sel)),
            "seconds_cold": med([r for r in sel if r["cold"]], "seconds"),
            "seconds_weights_cached": med([r for r in sel if not r["cold"]], "seconds"),
            "load_average": med(sel, "load"),
        }
        out[name]["meets_median"] = bool(out[name]["acquired"] <= TARGET_MEDIAN)
        out[name]["meets_single"] = out[name]["better_than_single"] == len(sel)
    return out


def report(result: dict) -> str:
    """Markdown section of ``docs/benchmarks.md``."""
    r = result.get("result", result)
    lines = [
        "### Acquisition from one photo",
        "",
        "Photo: sphere under the sky map and a point light, 64x64; judged in another view and "
        "light; manifold of `merl` only. Relative RMSE over the sphere (median). Seconds per "
        "photo: everything included with nothing cached / with the scene's training images "
        "cached, as measured while the benchmark shared the machine with other work.",
        "",
        "| set | n | acquired | best single | plain NNLS | reference noise | better than single "
        "| target (median <= 0.12, all better) | s/photo cold / cached |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key in ("held_out", "tune", "all"):
        s = r.get(key)
        if not s:
            continue
        met = "met" if s["meets_median"] and s["meets_single"] else "not met"
        cold = "-" if s["seconds_cold"] is None else f"{s['seconds_cold']:.0f}"
        cached = (
            "-" if s["seconds_weights_cached"] is None else f"{s['seconds_weights_cached']:.0f}"
        )
        lines.append(
            f"| {key.replace('_', '-')} | {s['n']} | {s['acquired']:.3f} | {s['single']:.3f} | "
            f"{s['nnls']:.3f} | {s['noise']:.3f} | {s['better_than_single']}/{s['n']} | {met} | "
            f"{cold} / {cached} |"
        )
    lines += [
        "",
        "Command: `python3 tools/bench.py acquire --manifold merl.npz --json "
        "benchmarks/results/acquire.json`",
        "",
    ]
    return "\n".join(lines)


def main(argv=None):
    """``python3 -m benchmarks.acquire --manifold M.npz --json OUT [--part tune|held-out|all]``."""
    import argparse
    import json

    from mitsuba_manifold._util.atomic import write_bytes

    from .common import machine

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("--json", required=True)
    p.add_argument("--manifold", default=None)
    p.add_argument("--part", default="all", choices=("all", "tune", "held-out"))
    p.add_argument("--out", default=None, help="work folder (default: beside --json)")
    p.add_argument("--measured-dir", default=None)
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--shard", type=int, nargs=2, default=(0, 1), metavar=("I", "N"))
    p.add_argument("--merge", nargs="+", default=None, help="join the JSON reports of shards")
    args = p.parse_args(argv)
    if args.merge:
        import json as json_

        rows = [r for f in args.merge for r in json_.load(open(f))["result"]["materials"]]
        for r in rows:  # the split as defined now (TUNE)
            r["split"] = (
                "tune"
                if r["material"][4:] in TUNE and r["material"].startswith("rgl:")
                else "held-out"
            )
        out = {"benchmark": "acquire", "machine": machine(), "result": summarise(rows)}
        write_bytes(args.json, json_.dumps(out, indent=1, default=float))
        print(report(out))
        return 0
    t0, load0 = time.perf_counter(), os.getloadavg()[0]

    def partial(rows):
        out = {"benchmark": "acquire", "partial": True, "result": summarise(rows)}
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        write_bytes(args.json, json.dumps(out, indent=1, default=float))

    result = run(
        manifold=args.manifold,
        out=args.out or os.path.splitext(args.json)[0] + "_work",
        part=args.part,
        measured_dir=args.measured_dir,
        limit=args.limit,
        shard=tuple(args.shard),
        on_row=partial,
    )
    report_ = {
        "benchmark": "acquire",
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "wall_s": time.perf_counter() - t0,
        "load_average": {"start": load0, "end": os.getloadavg()[0]},
        "result": result,
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    write_bytes(args.json, json.dumps(report_, indent=1, default=float))
    print(report(report_))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

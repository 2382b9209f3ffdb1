#!/usr/bin/env python3
"""The main job on the built-in default data, end to end:

1. the MERL-format database (SGD surrogates of the 100 MERL materials, 90x90x180 bins),
2. the latent manifold (GPLVM fit) with its summary and plots,
3. the L1- basis of scenes/table.xml (one image per material),
4. blends at a training point, a midpoint and an extrapolated point, their errors against
   full-GI references, and the error-against-time plot of blending vs re-rendering.
"""

import argparse
import json
import os
import sys
import time

from _cli import fail, parse_resolution

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def stage(text):
    print(f"\n== {text}", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=os.path.join(ROOT, "out"), help="output folder (default out/)")
    p.add_argument("--resolution", type=parse_resolution, default=(90, 90, 180), help="table bins (default MERL's)")
    p.add_argument("--q", type=int, default=2, help="latent dimension (default 2)")
    p.add_argument("--features", choices=["raw", "log"], default="log",
                   help="fit features (default log: on the built-in surrogate, whose bin-centre specular "
                        "peaks reach 1e8, raw features collapse most non-metallic materials onto one "
                        "latent point; see the README)")
    p.add_argument("--scene", default="table", help="scene of scenes/ for the GI part (default table)")
    p.add_argument("--res", type=int, default=256, help="image size (default 256)")
    p.add_argument("--spp", type=int, default=64, help="basis samples per pixel (default 64)")
    p.add_argument("--ref-spp", type=int, default=4096, help="reference samples per pixel (default 4096)")
    p.add_argument("--mode", choices=["onepass", "per-material"], default="onepass")
    args = p.parse_args(argv)

    from mitsuba_manifold import benchmarks, database, plots
    from mitsuba_manifold.manifold import Manifold
    t_start = time.perf_counter()
    db_dir = os.path.join(args.out, "database")
    manifold_path = os.path.join(args.out, "manifold.npz")
    try:
        stage(f"database: {db_dir}")
        t0 = time.perf_counter()
        database.make_database(db_dir, args.resolution, progress=True)
        print(f"100 tables ready ({time.perf_counter() - t0:.1f} s)")

        stage(f"manifold: q={args.q}, features={args.features}")
        m = Manifold.fit(db_dir, q=args.q, features=args.features, progress=True)
        m.save(manifold_path)
        print(m.summary())
        print(f"load {m.info['time_load_s']:.1f} s, Gram {m.info['time_gram_s']:.1f} s, "
              f"optimisation {m.info['time_fit_s']:.1f} s; saved {manifold_path}")
        for path in plots.write_fit_plots(m, os.path.join(args.out, "plots")):
            print(f"plot: {path}")

        stage(f"basis of scenes/{args.scene}.xml and blends ({args.res}x{args.res}, {args.spp} spp basis, "
              f"{args.ref_spp} spp references)")
        report = benchmarks.bench_gi(db_dir, manifold=manifold_path, scenes=(args.scene,), res=args.res,
                                     basis_spp=args.spp, ref_spp=args.ref_spp, mode=args.mode,
                                     direct_spp=(1, 4, 16, 64, 256), out=os.path.join(args.out, "gi"),
                                     save_images=True, progress=True)
    except (ValueError, KeyError, OSError, ArithmeticError) as e:
        fail(e)
    sc = report["scenes"][args.scene]
    print(f"basis: {sc['basis_images']} images in {sc['basis_time_s']:.1f} s")
    for row in sc["points"]:
        b = row["blend"]
        d64 = next(r for r in row["direct"] if r["spp"] == 64)
        print(f"{row['point']:>12s} ({row['x_is']}): blend {1e3 * b['time_s']:.1f} ms, rel. MSE {b['rel_mse']:.3g}, "
              f"PSNR {b['psnr']:.1f} dB, bias {100 * b['relative_bias']:+.2f}% | direct 64 spp "
              f"{d64['time_s']:.2f} s, rel. MSE {d64['rel_mse']:.3g}")
    report_path = os.path.join(args.out, "gi", "report.json")
    from mitsuba_manifold.merl import atomic_write
    atomic_write(report_path, lambda f: f.write(json.dumps(report, indent=1).encode()))
    print(f"plot: {report['plot']}\nreport: {report_path}\nimages: {os.path.join(args.out, 'gi')}")
    print(f"\nmain job done in {time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    sys.exit(main())

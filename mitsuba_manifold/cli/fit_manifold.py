"""Fit the latent manifold of a folder of MERL tables (paper Sec. 3) and save it."""

import argparse
import time

from .common import ERRORS, fail, parse_list


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("database", help="folder of <name>.binary MERL tables")
    p.add_argument("--q", type=int, default=2, help="latent dimension (1..8, default 2)")
    p.add_argument("--out", required=True, help="output manifold (.npz)")
    p.add_argument("--materials", type=parse_list, default=None, help="subset of materials (default: all)")
    p.add_argument("--method", choices=["hooke-jeeves", "lbfgs"], default="hooke-jeeves")
    p.add_argument("--features", choices=["raw", "log"], default="raw", help="fit features (default raw, as the paper)")
    p.add_argument("--length-scale", type=float, default=1.0, help="kernel length scale l (default 1)")
    p.add_argument("--noise", type=float, default=1e-4, help="kernel noise mu (default 1e-4)")
    p.add_argument("--plot", metavar="DIR", help="write latent map and convergence PNGs here")
    args = p.parse_args(argv)

    from .. import plots
    from ..manifold import Manifold
    t0 = time.perf_counter()
    try:
        m = Manifold.fit(args.database, q=args.q, names=args.materials, method=args.method,
                         length_scale=args.length_scale, noise=args.noise, features=args.features,
                         progress=True)
        m.save(args.out)
    except ERRORS as e:
        fail(e)
    print(m.summary())
    print(f"time: {time.perf_counter() - t0:.2f} s total (load {m.info['time_load_s']:.2f} s, "
          f"Gram {m.info['time_gram_s']:.2f} s, optimisation {m.info['time_fit_s']:.2f} s)")
    print(f"final L = {m.info['log_likelihood']:.8g}, cond(K) = {m.condition_number():.4g}")
    print(f"saved {args.out}")
    if args.plot:
        try:
            paths = plots.write_fit_plots(m, args.plot)
        except ERRORS as e:
            fail(e)
        for path in paths:
            print(f"plot: {path}")


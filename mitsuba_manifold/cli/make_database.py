"""Write the built-in MERL-format database (SGD surrogates of the 100 MERL materials)."""

import argparse
import time

from .common import ERRORS, parse_list, parse_resolution, fail


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", required=True, help="output folder (created or completed)")
    p.add_argument("--resolution", type=parse_resolution, default=(90, 90, 180),
                   help="theta_h,theta_d,phi_d bins (default 90,90,180 as MERL)")
    p.add_argument("--materials", type=parse_list, default=None, help="comma-separated names (default: all 100)")
    p.add_argument("--noise", type=float, default=0.0, help="multiplicative log-normal noise sigma (default 0)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    args = p.parse_args(argv)

    from .. import database
    t0 = time.perf_counter()
    try:
        paths = database.make_database(args.out, args.resolution, args.materials, args.noise,
                                       args.seed, progress=True)
    except ERRORS as e:
        fail(e)
    print(f"{len(paths)} tables in {args.out} ({time.perf_counter() - t0:.1f} s)")


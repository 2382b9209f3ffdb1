"""Write the built-in MERL-format database (SGD surrogates of the 100 MERL materials)."""

import os
import time

from .common import ArgumentParser, guarded, parse_list, parse_resolution


@guarded
def main(argv=None):
    p = ArgumentParser(description=__doc__)
    p.add_argument("--out", required=True, help="output folder (created or completed)")
    p.add_argument("--resolution", type=parse_resolution, default=(90, 90, 180),
                   help="theta_h,theta_d,phi_d bins (default 90,90,180 as MERL)")
    p.add_argument("--materials", type=parse_list, default=None, help="comma-separated names (default: all 100)")
    p.add_argument("--noise", type=float, default=0.0, help="multiplicative log-normal noise sigma (default 0)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--force", action="store_true", help="overwrite .binary files this tool did not make")
    args = p.parse_args(argv)

    from ...data import database
    from ..._util import checks as validate
    from ...data import merl
    t0 = time.perf_counter()
    if args.materials and len(set(args.materials)) < len(args.materials):
        repeated = sorted({n for n in args.materials if args.materials.count(n) > 1})
        print(f"note: {', '.join(repeated)} repeated in --materials; each table is made once")
        args.materials = list(dict.fromkeys(args.materials))
    n = len(args.materials) if args.materials else 100
    merl.table_resolution(args.resolution, "--resolution", workers=min(n, os.cpu_count() or 1))
    validate.finite("--noise", args.noise, 0.0, 10.0)
    validate.seed("--seed", args.seed)
    paths = database.make_database(args.out, args.resolution, args.materials, args.noise,
                                   args.seed, progress=True, force=args.force)
    print(f"{len(paths)} tables in {args.out} ({time.perf_counter() - t0:.1f} s)")

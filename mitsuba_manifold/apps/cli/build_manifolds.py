"""Refit and write the manifolds that ship with the package: the default fit of each built-in
set (merl, rgl, nielsen, all) at MERL's resolution, into mitsuba_manifold/manifold/shipped/.

Run it after a change to the default fit; the files are package data (in the wheel), loaded by
name: Manifold.load("merl"), <string name="manifold" value="merl"/>, --manifold merl.
"""

import os
import time

from .common import ArgumentParser, guarded, parse_list


@guarded
def main(argv=None):
    from ...errors import InputError
    from ...manifold.shipped import FOLDER, SHIPPED

    p = ArgumentParser(description=__doc__)
    p.add_argument(
        "--sets",
        type=parse_list,
        default=list(SHIPPED),
        help=f"the shipped manifolds to refit (default all: {','.join(SHIPPED)})",
    )
    p.add_argument("--out", default=FOLDER, help="folder to write <set>.npz into")
    args = p.parse_args(argv)
    unknown = [s for s in args.sets if s not in SHIPPED]
    if unknown:
        raise InputError(f"--sets {','.join(unknown)}: not shipped; one of {', '.join(SHIPPED)}")

    from ...manifold.model import Manifold

    os.makedirs(args.out, exist_ok=True)
    for name in args.sets:
        t0 = time.perf_counter()
        m = Manifold.fit(name, progress=True)  # the default preset, every material of the set
        path = os.path.join(args.out, name + ".npz")
        m.save(path)
        size = os.path.getsize(path) / 1024
        print(
            f"{name}: {m.n} materials, q={m.q}, {size:.0f} KiB, {time.perf_counter() - t0:.0f} s "
            f"-> {path}"
        )

"""Refit and write the manifolds that ship with the package: the default fit of each built-in
set (merl, rgl, nielsen, all) at MERL's resolution, into mitsuba_manifold/manifold/shipped/.

Run it after a change to the default fit; the files are package data (in the wheel), loaded by
name: Manifold.load("merl"), <string name="manifold" value="merl"/>, --manifold merl. What a
file holds depends on the fit alone: the fit's wall times are left out and the archive's entries
carry a fixed date, so the same fit gives the same bytes on every machine.
"""

import os
import time

from .common import ArgumentParser, guarded, parse_list


@guarded
def main(argv=None):
    from ...manifold.file.shipped import FOLDER, SHIPPED, check_sets, write
    from ...manifold.model import Manifold

    p = ArgumentParser(description=__doc__)
    p.add_argument(
        "--sets",
        type=parse_list,
        default=list(SHIPPED),
        help=f"the shipped manifolds to refit (default all: {','.join(SHIPPED)})",
    )
    p.add_argument("--out", default=FOLDER, help="folder to write <set>.npz into")
    args = p.parse_args(argv)
    check_sets(args.sets)
    for name in args.sets:
        t0 = time.perf_counter()
        m = Manifold.fit(name, progress=True)  # the default preset, every material of the set
        path, seconds = write(m, name, args.out)
        size = os.path.getsize(path) / 1024
        print(
            f"{name}: {m.n} materials, q={m.q}, L = {m.record.log_likelihood:.8g}, {size:.0f} KiB, "
            f"{time.perf_counter() - t0:.0f} s (fit {seconds.fit_s:.1f} s) -> {path}"
        )

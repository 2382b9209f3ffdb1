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
    from ...errors import InputError
    from ...manifold.file.shipped import FOLDER, SHIPPED

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

    from ...manifold.file.fit_record import Timings
    from ...manifold.model import Manifold

    os.makedirs(args.out, exist_ok=True)
    for name in args.sets:
        t0 = time.perf_counter()
        m = Manifold.fit(name, progress=True)  # the default preset, every material of the set
        seconds = m.record.timings
        m.record.timings = Timings()  # machine-dependent: not in the shipped file
        path = os.path.join(args.out, name + ".npz")
        m.save(path)
        _fixed_dates(path)
        size = os.path.getsize(path) / 1024
        print(
            f"{name}: {m.n} materials, q={m.q}, L = {m.record.log_likelihood:.8g}, {size:.0f} KiB, "
            f"{time.perf_counter() - t0:.0f} s (fit {seconds.fit_s:.1f} s) -> {path}"
        )


def _fixed_dates(path):
    """Rewrite the ``.npz`` archive ``path`` with every entry dated 1980-01-01 (atomically)."""
    import zipfile

    with zipfile.ZipFile(path) as z:
        entries = [(info.filename, z.read(info)) for info in z.infolist()]
    tmp = path + ".tmp"
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as z:
        for name, data in entries:
            z.writestr(zipfile.ZipInfo(name, (1980, 1, 1, 0, 0, 0)), data)
    os.replace(tmp, path)

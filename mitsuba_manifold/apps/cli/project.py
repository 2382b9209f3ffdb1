"""Project a measured material onto a manifold: the latent point whose material is closest.

The material: a MERL ``.binary`` file (of the manifold's resolution), a Mitsuba ``measured``
file (``.bsdf``), an NBRDF network (``.h5`` + ``.json``, ``.npz``) or ``SET:NAME`` of a built-in
database (``rgl:paper_white``), tabulated at the manifold's resolution.

Prints the latent point, its error (RMS of log(1 + rho) differences over all bins) beside the
nearest training material's, and the main weights; --json writes the same.
"""

import json

from .common import ArgumentParser, guarded


def check_json(args, guard=None):
    """Refuse a --json that is not a .json name, names an input, or would replace a file
    this tool did not write (``guard``, the run's :class:`ownership.Outputs`; never a
    read-only one).
    """
    from ..._util import ownership
    from ...errors import InputError

    if not args.json.lower().endswith(".json"):
        raise InputError(f"--json must name a .json file, got {args.json!r}")
    ownership.check_not_inputs(
        [args.json],
        (args.table, args.manifold),
        what="--json",
        reason="is an input of this run; choose another name",
    )
    (guard or ownership.Outputs("project.py", args.force)).check(args.json, "--json")


@guarded
def main(argv=None):
    p = ArgumentParser(description=__doc__)
    p.add_argument(
        "table",
        help="material: .binary, .bsdf, .h5 or .npz file, or SET:NAME of a built-in database "
        "(e.g. rgl:paper_white)",
    )
    p.add_argument(
        "--manifold",
        required=True,
        help="saved manifold (.npz), or a shipped one by name (merl, rgl, nielsen, all)",
    )
    p.add_argument(
        "--database",
        default=None,
        help="the manifold's tables: folder or built-in set name (default: as recorded)",
    )
    p.add_argument("--json", default=None, metavar="OUT", help="also write the result here (.json)")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --json this tool did not write (never a read-only one)",
    )
    args = p.parse_args(argv)

    from ..._util import ownership

    with ownership.Outputs("project.py", args.force) as guard:
        if args.json:
            check_json(args, guard)
        project(args)


def project(args):
    """Project ``args.table``, print the result and write ``--json``."""
    from ..._util.atomic import write_bytes
    from ...data.sources import material_source
    from ...manifold.model import Manifold

    material_source(args.table)  # a missing or malformed file is refused before the manifold loads
    m = Manifold.load(args.manifold)
    m.tables(args.database)
    r = m.project(args.table)
    result = r.to_json(args.table, m.names)
    if args.json:
        write_bytes(args.json, json.dumps(result, indent=1) + "\n")
    print(f"x = {', '.join(f'{v:.6g}' for v in r.x)}")
    print(
        f"error {r.error:.5g} (RMS of log(1 + rho) differences); nearest training material "
        f"{r.nearest}: {r.nearest_error:.5g}"
    )
    print("weights: " + ", ".join(f"{k}:{v:.4g}" for k, v in result["weights"].items()))
    if r.negative_fraction:
        print(f"negative bins: {100 * r.negative_fraction:.3g}% (clamped by the plugin)")

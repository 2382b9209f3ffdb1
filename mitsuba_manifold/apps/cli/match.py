"""Find the latent point whose blend best matches an image (inverse rendering on a basis).

  match.py --basis DIR --image photo.exr [--mask mask.png] [--exposure-free] [--starts K]
           [--out best.exr] [--png] [--json match.json] [--render-reference --spp 256]

Prints the best latent point, its nearest training materials and largest weights, the
image error (relative MSE over the mask; the fitted exposure with --exposure-free) and the
best single training material; writes the blend at the best point (--out), a contact sheet
image | match | best single material (--png), a full-GI render of the point (--render-
reference) and everything as JSON (--json). The image to match (--image; --target is its former
spelling): linear EXR, or PNG/JPEG (sRGB-decoded at its depth: 8 bits, or a 16-bit greyscale
PNG; clipped pixels left out). Nothing is written until the match has succeeded.
"""

import argparse
import json
import os
import sys
import time

from .common import ERRORS, ArgumentParser, fail, guarded


def _parser():
    p = ArgumentParser(
        prog="match.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        aliases={"manifold_path": "manifold", "image": "target"},
        renamed={"--target": "--image"},
    )
    p.add_argument(
        "--render",
        action="store_true",
        help="match full-GI renders of scenes instead of a basis (differentiable x; --render --help)",
    )
    p.add_argument(
        "--basis",
        required=True,
        help="basis folder written by render_basis.py (of one manifold material)",
    )
    p.add_argument(
        "--image",
        "--target",
        dest="target",
        required=True,
        help="the image to match: linear .exr, or .png/.jpg (sRGB; 8 bits, or 16-bit grey); "
        "--target is its former spelling",
    )
    p.add_argument(
        "--mask",
        help="mask image of the image's size: pixels > 0 are matched (grey = weight)",
    )
    p.add_argument(
        "--exposure-free", action="store_true", help="fit the blend's brightness scale too"
    )
    p.add_argument(
        "--log", action="store_true", help="match log luminance instead of relative MSE of RGB"
    )
    p.add_argument(
        "--prior",
        type=float,
        default=0.0,
        help="weight of the GP variance (paper Eq. 2) keeping the point near the data (default 0)",
    )
    p.add_argument("--starts", type=int, default=8, help="L-BFGS-B starts (default 8)")
    p.add_argument(
        "--scan",
        type=int,
        default=8192,
        help="random points near the data scored to choose the starts (default 8192; 0: start "
        "from the training points nearest to the best single material)",
    )
    p.add_argument(
        "--max-iter", type=int, default=100, help="L-BFGS-B iterations per start (default 100)"
    )
    p.add_argument(
        "--manifold", help="manifold (.npz); default: the one in the manifest (checked by hash)"
    )
    p.add_argument("--out", help="write the blend at the best point here (.exr)")
    p.add_argument(
        "--png",
        action="store_true",
        help="with --out: also a contact sheet image | match | best single",
    )
    p.add_argument("--json", metavar="OUT", help="write the result as JSON")
    p.add_argument(
        "--render-reference",
        action="store_true",
        help="with --out: also render the best point with manifold_brdf and Mitsuba's path",
    )
    p.add_argument(
        "--spp", type=int, default=256, help="samples per pixel of --render-reference (default 256)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of --render-reference (default 0)")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace existing output files this tool did not write (never read-only ones)",
    )
    return p


def _stem(path):
    return path[:-4] if path.lower().endswith(".exr") else path


def _check_args(args):
    if args.out is not None and not args.out.lower().endswith(".exr"):
        fail(f"--out must name an .exr file, got {args.out!r}")
    if (args.png or args.render_reference) and args.out is None:
        fail("--png and --render-reference write beside --out: give --out best.exr")
    for option, value, least in (
        ("--starts", args.starts, 1),
        ("--max-iter", args.max_iter, 1),
        ("--spp", args.spp, 1),
        ("--scan", args.scan, 0),
    ):
        if value < least:
            fail(f"{option} must be an integer >= {least}, got {value}")
    if args.json is not None and not args.json.lower().endswith(".json"):
        fail(f"--json must name a .json file, got {args.json!r}")
    from ..._util import checks as validate

    validate.seed("--seed", args.seed)


def _inputs(args):
    """Basis, manifold, target and mask weights, all checked."""
    from ...basis.folder import Basis
    from ...basis.inverse.targets import read_target_and_weight

    basis = Basis.load(args.basis, manifold=args.manifold)
    manifold = basis.check_manifold(args.manifold)
    target, weight, clipped = read_target_and_weight(args.target, args.mask, basis.resolution)
    if clipped:
        print(
            f"note: {clipped} clipped pixels of the target (a channel at its largest code) are left out"
        )
    return basis, manifold, target, weight


def _report(result, manifold, basis):
    print(basis)
    x = ", ".join(f"{v:.4f}" for v in result.x)
    print(
        f"best latent point: x = {x}  (GP variance {result.variance:.3g}; 0 at the data, "
        f"{1 + manifold.noise:.4g} far away)"
    )
    print(
        "nearest training materials: "
        + ", ".join(f"{n} ({d:.3f})" for n, d in result.nearest(manifold))
    )
    print("largest weights: " + ", ".join(f"{n} {w:+.4f}" for n, w in result.top_weights()))
    what = "log-luminance MSE" if result.loss == "log" else "relative MSE"
    print(
        f"image error: {what} {result.error:.4g}"
        + (f", relative MSE {result.rel_mse:.4g}" if result.loss == "log" else "")
        + f" over {result.n_pixels} pixels"
        + (f", fitted exposure x{result.exposure:.4g}" if result.exposure_free else "")
    )
    s = result.single
    print(
        f"best single training material: {s.name}, {what} {s.error:.4g}"
        + (f" (exposure x{s.exposure:.4g})" if result.exposure_free else "")
    )
    if result.from_start is None:
        print("the best single material itself is the best point")
    evals = sum(r["n_evaluations"] for r in result.starts)
    print(
        f"match time: {result.time_s:.3f} s ({len(result.starts)} starts, {evals} evaluations; "
        f"reading the basis: {result.time_read_s:.3f} s)"
    )


def _outputs(args, result, basis, manifold, target):
    """(kind, path, writer) of everything to write."""
    from ...basis.composition import single_image
    from ...imaging import io as imageio
    from ...render.scene.references import BasisView, render_reference_passes

    outputs, info = [], result.to_dict(manifold)
    if args.out:
        stem = _stem(args.out)
        outputs.append(
            ("blend at the best point", args.out, lambda: imageio.write_exr(args.out, result.image))
        )
        if args.png:
            single = single_image(basis, result.single.name)
            images = [target, result.exposure * result.image, result.single.exposure * single]
            labels = [
                "image to match",
                f"match ({result.error:.3g})",
                f"{result.single.name} ({result.single.error:.3g})",
            ]
            sheet = stem + "_sheet.png"
            outputs.append(
                (
                    "contact sheet",
                    sheet,
                    lambda: imageio.write_contact_sheet(sheet, images, labels, columns=3),
                )
            )
        if args.render_reference:
            m = basis.manifest
            print(
                f"rendering the best point: {m.scene}, with its integrator, {args.spp} spp ...",
                flush=True,
            )
            t0 = time.perf_counter()
            try:
                view = BasisView.of(basis, manifold=args.manifold, warn=print)
                ref = render_reference_passes(view, result.x, args.spp, seed=args.seed).image
            except (*ERRORS, RuntimeError) as e:  # RuntimeError: Mitsuba's
                fail(e)
            print(f"rendered in {time.perf_counter() - t0:.1f} s")
            path = stem + "_reference.exr"
            info["reference"] = path
            outputs.append(
                ("full-GI render of the best point", path, lambda: imageio.write_exr(path, ref))
            )
    if args.json:
        from ..._util.atomic import write_bytes

        info.update(
            basis=os.path.abspath(basis.folder),
            target=os.path.abspath(args.target),
            mask=None if args.mask is None else os.path.abspath(args.mask),
        )
        text = json.dumps(info, indent=1) + "\n"
        outputs.append(("JSON", args.json, lambda: write_bytes(args.json, text)))
    return outputs


def _planned(args):
    """Paths the tool will write."""
    out = [args.json] if args.json else []
    if args.out:
        out.append(args.out)
        out += [_stem(args.out) + "_sheet.png"] if args.png else []
        out += [_stem(args.out) + "_reference.exr"] if args.render_reference else []
    return out


def _refuse_inputs(args, guard):
    """Never overwrite an input (the target, the mask or an image of the basis), nor a file
    this tool did not make (``guard``: :class:`ownership.Outputs`, which allows those with
    ``--force``).
    """
    from ..._util import ownership
    from ...basis.folder import owned_files as basis_ownership

    for path in _planned(args):
        ownership.check_not_inputs(
            [path],
            (args.target, args.mask),
            folders=(args.basis,),
            named="an input (the target, the mask or the basis)",
        )
        basis_ownership.check_output_outside_basis(path)
        guard.check(path, "output")


@guarded
def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--render" in argv:  # differentiable rendering, no basis: its own tool
        from .match_render import main as match_render_main

        return match_render_main([a for a in argv if a != "--render"])
    args = _parser().parse_args(argv)
    _check_args(args)
    from ..._util import ownership
    from ...basis.inverse import match as mt

    settings = mt.MatchSettings(
        loss="log" if args.log else "rel_mse",
        exposure_free=args.exposure_free,
        prior=args.prior,
        starts=args.starts,
        max_iter=args.max_iter,
        scan=args.scan,
    )  # the tool's parameter object (checked by the match)
    with ownership.Outputs("match.py", args.force) as guard:
        _refuse_inputs(args, guard)
        basis, manifold, target, weight = _inputs(args)
        result = mt.match(basis, target, weight, manifold=manifold, settings=settings)
        _report(result, manifold, basis)
        outputs = _outputs(args, result, basis, manifold, target)
        for kind, path, _ in outputs:
            guard.check(path, kind)
        for kind, path, write in outputs:
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            write()
            print(f"wrote {kind}: {path}")
    return 0

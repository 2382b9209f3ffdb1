"""Blend a basis of per-material renders into the image of a latent point (paper Eq. 13).

  blend.py --basis DIR --x gold-paint --out img.exr [--png]
  blend.py --basis DIR --x 0.11,-0.29,0.49,0.68 --out img.exr --reference ref.exr
  blend.py --basis DIR --x 0.11,-0.29,0.49,0.68 --out img.exr --render-reference --spp 1024
  blend.py --basis DIR --path gold-paint chrome --steps 20 --out seq.exr [--path-kind straight]
  blend.py --basis DIR --x 0.11,-0.29,0.49,0.68 --out img.exr --component full

The default blends the full-GI images and cross terms of the basis (render_basis.py's default), its
light beyond L1- denoised (--l2 raw: summed, exact at the training materials but noisy where light runs
through narrow peaks); --component l1 blends the L1- images (paper Eq. 13). A basis without full-GI
images blends L1- and says so. --refine SPP makes the point's image unbiased: with a full-GI basis it
corrects the blend by what the same light paths say it misses (a control variate; nothing at a training
material), otherwise it adds the L2+ light rendered at the point.

With several manifold materials in the scene give one --x per target (in the manifest's
target order; --x A B is --x A --x B); with --path, --target names the one that moves and --x
gives the others. Nothing is written until every input has been read and checked.
"""

import argparse
import os
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Optional

from ...basis.outputs import (
    MAX_STEPS,
    Output,
    check_steps,
    companions,
    frame_names,
    planned_files,
)
from ...manifold.paths import DEFAULT_KIND as DEFAULT_PATH_KIND
from ...manifold.paths import KINDS as PATH_KINDS
from .common import (
    ERRORS,
    ArgumentParser,
    add_prune_argument,
    fail,
    guarded,
    one_line_warnings,
    parse_point,
    parse_points,
    write_outputs,
)

if TYPE_CHECKING:  # imported by parse() when it runs (the command line is checked first)
    from ...basis.blend import BlendSettings


def parser():
    p = ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        aliases={"manifold_path": "manifold"},
    )
    p.add_argument("--basis", required=True, help="basis folder written by render_basis.py")
    p.add_argument(
        "--x",
        nargs="+",
        action="append",
        metavar="X",
        help="latent point (q numbers) or a measured material's name; repeat once per target "
        "for a multilinear basis (with --path: once per target that stays fixed)",
    )
    p.add_argument(
        "--out",
        required=True,
        help="output EXR (with --path, OUT.exr names the frames OUT_0.exr, OUT_1.exr, ... and "
        "the contact sheet OUT_sheet.png)",
    )
    p.add_argument("--png", action="store_true", help="also write tonemapped sRGB PNGs")
    p.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops (default 0)")
    p.add_argument(
        "--manifold", help="manifold (.npz); default: the one in the manifest (checked by hash)"
    )
    p.add_argument(
        "--scene",
        help="scene XML to check the basis against (default: not checked; "
        "--render-reference uses the manifest's scene)",
    )
    add_prune_argument(p)
    p.add_argument(
        "--renormalise",
        action="store_true",
        help="if images with surviving weight are missing from the basis, rescale the "
        "weights of those present instead of failing (an approximation)",
    )
    ref = p.add_mutually_exclusive_group()
    ref.add_argument(
        "--reference", metavar="REF.exr", help="reference image to measure the error against"
    )
    ref.add_argument(
        "--render-reference",
        action="store_true",
        help="render the reference: Mitsuba's own render of the basis's scene with the point's "
        "manifold_brdf, with the scene's integrator as the basis was (its type, max_depth, "
        "rr_depth, hide_emitters; a basis made with --max-depth: that depth)",
    )
    p.add_argument(
        "--spp", type=int, default=256, help="samples per pixel of --render-reference (default 256)"
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed of --render-reference and --refine (default 0)"
    )
    p.add_argument(
        "--path",
        nargs=2,
        metavar=("A", "B"),
        help="images along a latent path (of --path-kind) between materials (or 'x0,x1' points) A "
        "and B",
    )
    p.add_argument(
        "--steps",
        type=int,
        default=20,
        help=f"images along --path (default 20, at most {MAX_STEPS})",
    )
    p.add_argument(
        "--path-kind",
        choices=PATH_KINDS,
        default=DEFAULT_PATH_KIND,
        help="the path of --path: straight (the latent segment at equal steps), uniform (the segment "
        "at equal perceptual steps), geodesic (a shortest path under the perceptual metric, at "
        "equal steps) or faithful (each image as far from the two ends as its place says, in even "
        f"steps); default {DEFAULT_PATH_KIND} (the paper's Fig. 9 measures: tools/bench.py fig9)",
    )
    p.add_argument(
        "--target",
        default=None,
        help="with --path and several targets: the BSDF id that moves (default: the first); "
        "--x gives the others",
    )
    p.add_argument(
        "--database",
        help="the manifold's tables (folder or built-in set name), if it moved "
        "(--render-reference)",
    )
    p.add_argument(
        "--refine",
        type=int,
        metavar="SPP",
        default=None,
        help="unbiased image of the point, SPP samples per pixel: the full-GI blend corrected by "
        "a control variate (or, with an L1- basis, the L1- blend plus the L2+ rendered there); "
        "reports the noise its passes estimate (too low where fireflies are rare)",
    )
    p.add_argument(
        "--refine-passes",
        type=int,
        default=None,
        help="independent passes of --refine, which estimate its noise "
        "(default 4, or --refine if fewer)",
    )
    p.add_argument(
        "--l2",
        choices=["denoised", "raw"],
        default="denoised",
        help="the full-GI blend's light beyond L1-: denoised by OIDN (default) or as summed",
    )
    p.add_argument(
        "--component",
        choices=["full", "l1"],
        default=None,
        help="full (default): the full-GI images and cross terms where the basis holds them "
        "(render_basis.py --components full); l1: the L1- images (Eq. 13)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace existing output files this tool did not write (never read-only ones)",
    )
    return p


@dataclass(frozen=True)
class PathRequest:
    """``--path A B``: ``steps`` images along a latent path of ``kind``; ``target`` (a BSDF id)
    the target that moves when the basis has several.
    """

    ends: tuple
    steps: int = 20
    kind: str = DEFAULT_PATH_KIND
    target: Optional[str] = None


@dataclass(frozen=True)
class ReferenceRequest:
    """What the blend is compared with: the image ``file`` (``--reference``), or a render
    (``--render-reference``, ``spp`` samples per pixel, ``seed``); neither: no comparison.
    """

    file: Optional[str] = None
    render: bool = False
    spp: int = 256
    seed: int = 0

    @property
    def wanted(self):
        """Whether the blend is compared with a reference."""
        return bool(self.file or self.render)


@dataclass(frozen=True)
class RefineChoice:
    """``--refine SPP``: ``spp`` samples per pixel in ``passes`` passes (None: no refinement),
    seeded with ``--seed``.
    """

    spp: Optional[int] = None
    passes: int = 4
    seed: int = 0


@dataclass(frozen=True)
class BlendRequest:
    """Everything ``blend.py`` was asked, checked: made once by :func:`parse` from the command line.

    Attributes
    ----------
    basis, manifold, scene, database : str or None
        ``--basis``, ``--manifold``, ``--scene``, ``--database``.
    x : list or None
        The latent points of ``--x`` (:func:`.common.parse_points`: each a list of numbers or
        a material's name), target after target; :func:`main` makes them one flat list of
        numbers (:func:`mitsuba_manifold.basis.points.target_points`).
    settings : BlendSettings
        ``--prune``, ``--renormalise``, ``--component``, ``--l2``.
    path : PathRequest or None
        ``--path`` (None: the image of one point).
    reference : ReferenceRequest
    refine : RefineChoice
    output : Output
    """

    basis: str
    manifold: Optional[str]
    scene: Optional[str]
    database: Optional[str]
    x: Optional[list]
    settings: "BlendSettings"
    path: Optional[PathRequest]
    reference: ReferenceRequest
    refine: RefineChoice
    output: Output


def parse(argv=None):
    """The checked :class:`BlendRequest` of the command line ``argv``."""
    args = parser().parse_args(argv)
    x = None
    if args.x:  # numbers, or measured materials' names, resolved with the manifold
        try:
            x = parse_points(args.x)
        except argparse.ArgumentTypeError as e:
            fail(f"--x: {e}")
    if args.path is None and x is None:
        fail("give --x (a latent point) or --path A B")
    if args.path is not None and (args.reference or args.render_reference):
        fail("--reference/--render-reference compare one image; not with --path")
    output = Output(args.out, args.png, args.exposure, args.force)
    output.check(path=args.path is not None)
    check_steps(args.steps)
    if args.refine is not None and args.path is not None:
        fail("--refine makes one point's image exact; not with --path")
    if args.refine is not None and args.refine < 1:
        fail(f"--refine must be >= 1 (samples per pixel), got {args.refine}")
    passes = args.refine_passes
    if passes is None:  # not given: 4 passes, fewer when --refine has fewer samples
        passes = min(4, args.refine) if args.refine is not None else 4
    if args.refine is not None and not 1 <= passes <= args.refine:
        fail(f"--refine-passes must be in 1..--refine ({args.refine}), got {passes}")
    if args.spp < 1:
        fail(f"--spp must be >= 1, got {args.spp}")
    from ..._util import checks as validate
    from ..._util import ownership
    from ...basis.blend import BlendSettings
    from ...basis.folder import owned_files as basis_ownership

    validate.exposure(args.exposure)
    validate.fraction("--prune", args.prune)
    validate.seed("--seed", args.seed)
    basis_ownership.check_output_outside_basis(args.out, args.basis)
    validate.output_folder(
        f"--out {args.out}: folder", os.path.dirname(os.path.abspath(args.out))
    )  # before work
    path = None
    if args.path is not None:
        path = PathRequest(tuple(args.path), args.steps, args.path_kind, args.target)
    request = BlendRequest(
        basis=args.basis,
        manifold=args.manifold,
        scene=args.scene,
        database=args.database,
        x=x,
        settings=BlendSettings(
            prune=args.prune, renormalise=args.renormalise, component=args.component, l2=args.l2
        ),
        path=path,
        reference=ReferenceRequest(args.reference, args.render_reference, args.spp, args.seed),
        refine=RefineChoice(args.refine, passes, args.seed),
        output=output,
    )
    reference = request.reference
    planned = planned_files(
        output, args.steps if path else None, reference.render, reference.wanted
    )  # names and kinds of targets (their owners: before writing)
    for kind, file in planned:
        ownership.check_replaceable(file, args.force, what=kind, owner=False)
    return request


def path_outputs(request, basis, manifold):
    """Blend the images along ``--path``; returns the outputs ``(kind, path, writer)`` to write."""
    from ...basis.blend import MovingTarget, blend_path, path_labels
    from ...basis.points import check_path_memory, path_end, target_index
    from ...imaging import io as imageio

    path, output = request.path, request.output
    check_path_memory(basis, path.steps)
    ends = [
        path_end(manifold, a if a in manifold.names else _point_or_name(a), a) for a in path.ends
    ]
    target = target_index(basis, path.target)
    with one_line_warnings():
        images, _, info = blend_path(
            basis,
            manifold,
            ends[0],
            ends[1],
            steps=path.steps,
            kind=path.kind,
            moving=MovingTarget(target, request.x),
            settings=request.settings,
        )
    _say_component(info)
    den = (
        f"; their L2+ light denoised in {info.denoise_ms:.0f} ms" if info.denoise_ms >= 0.5 else ""
    )
    print(
        f"path {path.ends[0]} -> {path.ends[1]}: {path.steps} images blended in "
        f"{info.time_ms:.2f} ms ({info.time_ms / path.steps:.3f} ms per image){den}"
    )
    outputs = []
    for name, img in zip(frame_names(output, path.steps), images):
        outputs.append(("image", name, lambda n=name, i=img: imageio.write_exr(n, i)))
        if output.png:
            png = name[:-4] + ".png"
            outputs.append(
                ("png", png, lambda n=png, i=img: imageio.write_png(n, i, output.exposure))
            )
    labels = path_labels(list(path.ends), path.steps)
    sheet = output.stem + "_sheet.png"
    title = f"{path.ends[0]} (t = 0) to {path.ends[1]} (t = 1) along a {path.kind} latent path"
    outputs.append(
        (
            "contact sheet",
            sheet,
            lambda: imageio.write_contact_sheet(
                sheet,
                images,
                labels,
                columns=min(path.steps, 10),
                exposure=output.exposure,
                title=title,
            ),
        )
    )
    return outputs


def _say_component(info):
    """One line: which blend was made (full GI or L1-) and, for L1-, why."""
    if info.component == "full":
        print(
            f"blend: full GI (full-GI images and cross terms; light beyond L1- {info.l2 or 'summed'})"
        )
    elif info.component == "l1" and not info.component_note:
        print("blend: L1- images only (paper Eq. 13; --component l1)")
    elif info.component_note and "predates" not in info.component_note:
        print(f"blend: {info.component_note}")


def _refined(request, basis, manifold):
    """The image of ``--refine`` (:func:`mitsuba_manifold.render.jobs.refine.refine`), its progress printed."""
    from ...render.jobs.refine import CONTROL_VARIATE, RefineRequest, refine_passes

    refine = RefineRequest(
        spp=request.refine.spp,
        passes=request.refine.passes,
        seed=request.refine.seed,
        database=request.database,
        prune=request.settings.prune,
        l2=request.settings.l2,
    )
    print(f"refining at the point, {refine.spp} spp in {refine.passes} passes ...", flush=True)
    last = None
    for last in refine_passes(basis, manifold, request.x, refine):
        if last.passes:
            print(
                f"  pass {last.passes}/{refine.passes}: {last.spp} spp, {last.seconds:.2f} s",
                flush=True,
            )
    written = (
        "the full-GI blend plus this correction"
        if last.method == CONTROL_VARIATE
        else "the L1- blend plus this L2+"
    )
    print(f"{last.summary()}; the image written is {written}")
    return last.image


def _point_or_name(a):  # a latent point "x0,x1", else a name blend_path reports as unknown
    try:
        return parse_point(a)
    except argparse.ArgumentTypeError:
        return a


def point_outputs(request, basis, manifold):
    """Blend the image of ``--x`` (and compare it with a reference); returns the outputs to write."""
    from ...basis.blend import blend
    from ...imaging import io as imageio
    from ...imaging import metrics

    settings, output = request.settings, request.output
    with one_line_warnings():
        image, info = blend(
            basis,
            manifold,
            x=request.x,
            settings=settings,
        )
    _say_component(info)
    for t, (weights, dropped) in enumerate(zip(info.weights, info.dropped_weight)):
        top = sorted(weights.items(), key=lambda kv: -abs(kv[1]))
        shown = ", ".join(f"{n} {v:.4g}" for n, v in top[:6]) + (" ..." if len(top) > 6 else "")
        print(
            f"target {basis.targets[t]}: {len(top)} material{'s' * (len(top) != 1)} kept "
            f"(dropped |w| {dropped:.3g}): {shown}"
        )
    if info.renormalised:
        print(
            f"warning: renormalised over the images present; missing: {', '.join(sorted(info.missing))}"
        )
    print(
        f"blend time: {info.time_ms:.3f} ms ({info.n_images} images; reading them: "
        f"{info.time_read_s:.3f} s)"
    )
    below = metrics.negative_pixels(image)
    if info.component == "full" and settings.l2 == "raw" and request.refine.spp is None and below:
        print(
            f"note: {below} pixels below 0 (the summed cross terms' noise; "
            "the default --l2 denoised has none)"
        )
    unrefined = image
    if request.refine.spp is not None:
        image = _refined(request, basis, manifold)
    stem = output.stem
    outputs = [("image", output.out, lambda: imageio.write_exr(output.out, image))]
    if output.png:
        outputs.append(
            ("png", stem + ".png", lambda: imageio.write_png(stem + ".png", image, output.exposure))
        )
    reference = reference_image(request, basis, manifold, outputs)
    if reference is not None:
        try:
            stats = metrics.compare(image, reference)
        except ValueError as e:
            fail(f"reference {request.reference.file or 'render'}: {e}")
        if request.refine.spp is not None:
            print(
                f"before refining: relative MSE {metrics.compare(unrefined, reference)['rel_mse']:.4g}"
            )
        print(
            f"relative MSE {stats['rel_mse']:.4g} (eps {stats['eps']:g}), PSNR {stats['psnr']:.2f} dB "
            f"(peak {stats['peak']:.4g}), max error {stats['max_abs']:.4g}, mean error {stats['mean_abs']:.4g}"
        )
        err = metrics.error_image(image, reference)
        outputs.append(
            (
                "error image",
                stem + "_error.exr",
                lambda: imageio.write_exr(stem + "_error.exr", err),
            )
        )
        outputs.append(
            (
                "error PNG (false colour, its scale drawn under it)",
                stem + "_error.png",
                lambda: metrics.write_error_png(stem + "_error.png", image, reference),
            )
        )
    return outputs


def reference_image(request, basis, manifold, outputs):
    """The reference of ``--reference`` (read) or ``--render-reference`` (rendered by
    :func:`mitsuba_manifold.render.scene.references.render_reference_passes`, and added to
    ``outputs``), or None.
    """
    from ...basis.blend import latent_points
    from ...imaging import io as imageio
    from ...render.scene.references import BasisView, render_reference_passes

    ref, output = request.reference, request.output
    if ref.file:
        return imageio.read_exr(ref.file)
    if not ref.render:
        return None
    m = basis.manifest
    scene = request.scene or m.scene
    paths = m.integrator
    how = (
        f"{paths['kind']}, max_depth {paths['max_depth']}"
        + (", hide_emitters" if paths["hide_emitters"] else "")
        if paths
        else f"max_depth {m.max_depth}"
    )
    print(f"rendering the reference: {scene}, {how} (as the basis), {ref.spp} spp ...", flush=True)
    t0 = time.perf_counter()
    points = latent_points(basis, manifold, request.x)
    view = BasisView.of(basis, scene, request.manifold, request.database, warn=print)
    reference = render_reference_passes(view, points, ref.spp, seed=ref.seed).image
    print(f"reference rendered in {time.perf_counter() - t0:.2f} s")
    if basis.p == 1:
        neg = manifold.negative_fraction(points[0], database=request.database)
        if neg > 1e-3:
            print(
                f"note: {100 * neg:.1f}% of the interpolated table's values are negative; "
                "manifold_brdf clamps them to 0, a blend keeps them, so the two differ beyond L2+"
            )
    ref_path = output.stem + "_reference.exr"
    outputs.append(("reference", ref_path, lambda: imageio.write_exr(ref_path, reference)))
    if output.png:
        ref_png = output.stem + "_reference.png"
        outputs.append(
            (
                "reference PNG",
                ref_png,
                lambda: imageio.write_png(ref_png, reference, output.exposure),
            )
        )
    return reference


def remove_stale_companions(out, outputs):
    """Remove the files an earlier blend to ``out`` wrote beside it that this run did not
    write again (e.g. the previous point's error image): only the tool's own, unchanged since
    (:func:`mitsuba_manifold._util.ownership.remove_owned`).
    """
    from ..._util import ownership

    written = [path for _, path, _ in outputs]
    for path in ownership.remove_owned(companions(out), keep=written):
        print(f"removed {path} (from an earlier blend to {out}; this one did not write it)")


@guarded
def main(argv=None):
    request = parse(argv)
    from ...basis.folder import Basis
    from ...basis.points import target_points

    try:
        basis = Basis.load(request.basis, manifold=request.manifold, scene=request.scene)
        manifold = basis.check_manifold(request.manifold)
        path = request.path
        x = target_points(
            basis, manifold, request.x, path is not None, path and path.target
        )  # one point per target, names resolved
        request = replace(request, x=x)
        print(basis)
        out, force = request.output.out, request.output.force
        if request.path is not None:
            outputs = path_outputs(request, basis, manifold)
            write_outputs("blend.py", out, outputs, force, group="path:" + os.path.abspath(out))
        else:
            outputs = point_outputs(request, basis, manifold)
            write_outputs("blend.py", out, outputs, force, group="point:" + os.path.abspath(out))
            remove_stale_companions(out, outputs)
    except (*ERRORS, RuntimeError) as e:  # RuntimeError: Mitsuba's, from a reference render
        fail(e)

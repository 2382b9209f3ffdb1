"""Tutorial 3: render a basis once, then any material of the manifold is a blend of its images.

    python3 docs/tutorials/basis_blend.py --out out/tutorials           # after tutorial 1
    python3 docs/tutorials/basis_blend.py --out /tmp/t --small

Reads OUT/manifold.npz (tutorial 1 makes it); writes the basis to OUT/basis and
OUT/basis_blend.png: blend | full-GI reference | difference x4, at a point between two materials,
and OUT/basis_parts.png: what the basis holds for one material (base, L1-, full GI, L2+).
"""

import argparse
import os
import sys

import numpy as np

from mitsuba_manifold import Manifold, blend
from mitsuba_manifold.errors import MitsubaManifoldError
from mitsuba_manifold.imaging.io import read_exr, write_contact_sheet
from mitsuba_manifold.imaging.metrics import rel_mse
from mitsuba_manifold.render.jobs.render_basis import render_basis
from mitsuba_manifold.render.scene.scenes import render_reference, scene_path


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/tutorials")
    ap.add_argument("--small", action="store_true", help="tiny images (for the tests)")
    args = ap.parse_args()
    res, spp, ref_spp = (24, 8, 16) if args.small else (128, 512, 1024)
    manifold = os.path.join(args.out, "manifold.npz")
    basis = os.path.join(args.out, "basis")
    if not os.path.isfile(manifold):  # tutorial 1 writes it
        sys.exit(
            f"error: {manifold} does not exist: run tutorial 1 first "
            f"(python3 docs/tutorials/manifold_tour.py --out {args.out})"
        )

    # 1. The basis of the shipped scene "table" (a bowl of the material on a table): one set of
    #    paths gives base.exr, every material's image (full global illumination), the cross terms.
    render_basis(
        scene_path("table"),
        manifold,
        basis,
        spp=spp,
        resolution=res,
        mode="onepass",
        components="full",
        progress=not args.small,
    )

    # 2. A blend: any latent point, in milliseconds. Here the latent midpoint of
    #    gold-metallic-paint and white-paint: a material of the manifold, not a mix of the two
    #    (in this manifold of eight a blue one, mostly blue-rubber and green-metallic-paint:
    #    the weights printed below say which materials it blends).
    m = Manifold.load(manifold)
    x = 0.5 * (m.latent[m.index("gold-metallic-paint")] + m.latent[m.index("white-paint")])
    image, info = blend(basis, x=x)  # the part beyond L1- is denoised by default (l2="raw": summed)
    print(
        f"blend: {info.time_ms:.1f} ms; weights:",
        {k: round(v, 3) for k, v in info.weights[0].items()},
    )

    # 3. What it approximates: a full-GI render of that material with Mitsuba's path tracer.
    reference = render_reference(
        scene_path("table"), manifold, x, spp=ref_spp, resolution=res, seed=7
    )
    print(f"relative MSE of the blend against the reference: {rel_mse(image, reference):.4f}")
    diff = np.abs(image - reference) * 4
    write_contact_sheet(
        os.path.join(args.out, "basis_blend.png"),
        np.stack([image, reference, diff]),
        ["blend", "reference (path tracer)", "|difference| x4"],
        columns=3,
    )
    print("wrote", os.path.join(args.out, "basis_blend.png"))

    # 4. What the basis holds for one material: base (paths that never meet the bowl), the
    #    material's touch image (paths meeting it once) and its full-GI image (touch + L2+).
    base = read_exr(os.path.join(basis, "base.exr"))
    touch = read_exr(os.path.join(basis, "pink-fabric.exr"))
    full = read_exr(os.path.join(basis, "pink-fabric.gi.exr"))
    write_contact_sheet(
        os.path.join(args.out, "basis_parts.png"),
        np.stack([base, base + touch, base + full, 4 * (full - touch)]),
        [
            "base: never on the bowl",
            "L1-: base + touch",
            "full GI: base + touch + L2+",
            "L2+ x4: twice or more",
        ],
        columns=4,
    )
    print("wrote", os.path.join(args.out, "basis_parts.png"))


if __name__ == "__main__":
    try:
        main()
    except MitsubaManifoldError as e:  # e.g. OUT/basis made from an earlier manifold: one line
        sys.exit(f"error: {e}")

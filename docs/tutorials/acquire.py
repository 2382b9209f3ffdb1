"""Tutorial 5: acquire a material from one photo of a known object under known light.

    python3 docs/tutorials/acquire.py --out out/tutorials              # after tutorial 1
    python3 docs/tutorials/acquire.py --out /tmp/t --small

Fits a manifold of all 100 MERL materials at the resolution of tutorial 1's tables, then acquires
the material of the shipped photo docs/tutorials/data/acquire_photo.exr (the sphere scene, a
glossy yellow vinyl film measured by RGL-EPFL, not one of the MERL materials). Writes
OUT/acquire.png (photo | acquired | best single MERL material), OUT/acquire.json (the result,
readable with Acquisition.read) and OUT/acquired.xml (a manifold_brdf with the weights).
"""

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/tutorials")
    ap.add_argument(
        "--small", action="store_true", help="a small photo, few samples (for the tests)"
    )
    args = ap.parse_args()
    first = os.path.join(args.out, "manifold.npz")
    if not os.path.isfile(first):  # tutorial 1 writes it (and the tables at its resolution)
        sys.exit(
            f"error: {first} does not exist: run tutorial 1 first "
            f"(python3 docs/tutorials/manifold_tour.py --out {args.out})"
        )
    from mitsuba_manifold import Manifold
    from mitsuba_manifold.basis.inverse.acquisition import AcquireOptions
    from mitsuba_manifold.imaging import io
    from mitsuba_manifold.render.inverse.acquire import Photo, acquire

    # 1. The library of materials to acquire with: all 100 MERL materials.
    merl = os.path.join(args.out, "merl.npz")
    if not os.path.isfile(merl):
        Manifold.fit("merl@{}x{}x{}".format(*Manifold.load(first).dims)).save(merl)

    # 2. The photo (linear RGB) of a known shape under known light: the shipped sphere scene.
    photo = io.read_exr(os.path.join(HERE, "data", "acquire_photo.exr"))
    if args.small:  # 2x2 pixels averaged: a 32x32 photo of the same scene
        photo = photo.reshape(32, 2, 32, 2, 3).mean(axis=(1, 3))
    opts = AcquireOptions(spp=16 if args.small else 64, render_spp=16 if args.small else 256)

    # 3. Acquire: every MERL material's image in the scene (one pass), then the weights.
    got = acquire([Photo("sphere", photo)], merl, opts)
    r = got.result
    print(f"acquired with weights {r.feasible}: relative RMSE {r.error:.3f} on the photo")
    print(f"best single MERL material: {r.single['name']} ({r.single['error']:.3f})")
    print("largest weights:", ", ".join(f"{n} {w:+.3f}" for n, w in r.top_weights(5)))
    for warning in r.warnings:
        print("warning:", warning)

    # 4. The outputs: the result file, a manifold_brdf for any scene, a contact sheet.
    r.write(os.path.join(args.out, "acquire.json"))
    with open(os.path.join(args.out, "acquired.xml"), "w") as f:
        f.write(r.snippet(os.path.abspath(merl)))
    sheet = os.path.join(args.out, "acquire.png")
    io.write_contact_sheet(
        sheet,
        np.stack([got.photos[0], got.renders[0], got.singles[0]]).astype(np.float32),
        ["photo", f"acquired\n{r.error:.3f}", f"{r.single['name']}\n{r.single['error']:.3f}"],
        columns=3,
    )
    print("wrote", sheet)


if __name__ == "__main__":  # the database is written by worker processes, which import this file
    main()

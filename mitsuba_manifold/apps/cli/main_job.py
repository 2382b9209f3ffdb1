"""The main job on the built-in default data, end to end (library: mitsuba_manifold.apps.pipeline.run_main_job):

1. the database (default: the built-in ``merl``, the 100 MERL measurements, 90x90x180 bins),
2. the latent manifold (GPLVM fit) with its summary and plots,
3. the full-GI basis of a shipped scene (default table.xml, one pass: base, every material's
   L1- and full-GI image, the cross terms),
4. blends at a training point, a midpoint and an extrapolated point, their errors against
   full-GI references (raw, and denoised with OIDN beside the raw ones), and the
   error-against-time plot of blending vs re-rendering.
"""

import argparse

from .common import ArgumentParser, guarded, parse_resolution


@guarded
def main(argv=None) -> None:
    p = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out", help="output folder (default out/)")
    p.add_argument(
        "--database",
        default="merl",
        help="built-in set (merl, rgl, nielsen, all, sgd) or folder of measured tables (default merl)",
    )
    p.add_argument(
        "--resolution",
        type=parse_resolution,
        default=(90, 90, 180),
        help="table bins (default MERL's)",
    )
    p.add_argument(
        "--preset",
        choices=["default", "paper"],
        default="default",
        help="manifold settings (default: the measured best; paper: the paper's exact "
        "formulation; see docs/concepts/latent-space.md)",
    )
    p.add_argument("--q", type=int, default=None, help="latent dimension (default: the preset's)")
    p.add_argument(
        "--features",
        choices=["raw", "log"],
        default=None,
        help="fit features (default: the preset's; on the built-in surrogate, whose bin-centre "
        "specular peaks reach 1e8, raw features collapse most non-metallic materials onto one "
        "latent point; see docs/concepts/latent-space.md)",
    )
    p.add_argument(
        "--scene",
        default="table",
        help="shipped scene name or scene XML for the GI part (default table)",
    )
    p.add_argument("--res", type=int, default=256, help="image size (default 256)")
    p.add_argument(
        "--spp",
        type=int,
        default=512,
        help="basis samples per pixel (default 512; the basis holds "
        "full-GI images, about 3x the cost of L1- ones)",
    )
    p.add_argument(
        "--ref-spp", type=int, default=2048, help="reference samples per pixel (default 2048)"
    )
    p.add_argument(
        "--no-denoise", action="store_true", help="skip the AOVs and the denoised figures"
    )
    p.add_argument("--mode", choices=["onepass", "per-material"], default="onepass")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace files in --out this job did not write (never read-only ones); without it "
        "they are refused before anything is computed",
    )
    args = p.parse_args(argv)

    from ..pipeline import MainJob, run_main_job

    job = MainJob(
        args.out,
        args.resolution,
        q=args.q,
        features=args.features,
        preset=args.preset,
        scene=args.scene,
        res=args.res,
        spp=args.spp,
        ref_spp=args.ref_spp,
        mode=args.mode,
        denoise=not args.no_denoise,
        force=args.force,
        database=args.database,
    )
    run_main_job(job, log=lambda text: print(text, flush=True))

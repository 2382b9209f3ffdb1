"""GI benchmark: the blend (Eq. 13) against re-rendering the interpolated material, error
against run time on the shipped sphere and table scenes (:func:`pipeline.gi_report`)."""

from .. import pipeline


def run(folder, manifold=None, scenes=("sphere", "table"), res=128, basis_spp=64, ref_spp=4096,
        direct_spp=(1, 4, 16, 64, 256, 1024), mode="onepass", out=None, seed=0, plot=None, progress=False):
    """Error against run time of blends and direct renders; see :func:`pipeline.gi_report`."""
    return pipeline.gi_report(folder, manifold, scenes=scenes, res=res, basis_spp=basis_spp, ref_spp=ref_spp,
                              direct_spp=direct_spp, mode=mode, out=out, seed=seed, save_images=False,
                              progress=progress, plot=plot)

"""GI benchmark: the blend (Eq. 13) against re-rendering the interpolated material, error
against run time on the shipped sphere and table scenes (:func:`comparison.gi_report`)."""

from ..comparison import gi_report


def run(folder, manifold=None, scenes=("sphere", "table"), out=None, plot=None, **settings):
    """Error against run time of blends and direct renders, without saving images; ``settings``:
    fields of :class:`~mitsuba_manifold.apps.comparison.GISettings` (``res``, ``basis_spp``,
    ``ref_spp``, ``direct_spp``, ``mode``, ``seed``, ``progress``); see :func:`comparison.gi_report`."""
    return gi_report(folder, manifold, scenes=scenes, out=out, plot=plot, **{"save_images": False, **settings})

"""The package's Mitsuba plugins are Mitsuba classes of the active variant, made again for each
variant as Mitsuba makes its own Python integrators (:mod:`mitsuba_manifold.render.plugin.plugins`)."""

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from mitsuba_manifold.render import integrators
from mitsuba_manifold.render.plugin import plugins  # noqa: E402
from mitsuba_manifold.render.scene.scenes import scene_path  # noqa: E402

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]


def _classes():
    """The plugin classes of the active variant, through their modules."""
    from mitsuba_manifold.render.integrators import aovs, path
    from mitsuba_manifold.render.plugin import bsdf

    return bsdf.ManifoldBRDF, path.ManifoldPathIntegrator, aovs.FirstHitAOVs


def test_the_plugins_are_classes_of_the_active_variant(small_manifold):
    brdf, path, aovs = _classes()
    assert issubclass(brdf, mi.BSDF) and issubclass(path, mi.SamplingIntegrator)
    assert issubclass(aovs, mi.SamplingIntegrator)
    assert [cls.__name__ for cls in _classes()] == [
        "ManifoldBRDF",
        "ManifoldPathIntegrator",
        "FirstHitAOVs",
    ]
    b = mi.load_dict(
        {
            "type": "manifold_brdf",
            "manifold": small_manifold,
            "material": "chrome",
            "interpolation": "linear",
            "sampling": "cosine",
        }
    )
    assert type(b) is brdf and isinstance(b, mi.BSDF)
    assert (b.interpolation, b.sampling, b.database, b.used_names) == (
        "linear",
        "cosine",
        None,
        ["chrome"],
    )
    with pytest.raises(AttributeError):
        b.interpolation = "nearest"  # read-only
    assert type(mi.load_dict({"type": "manifold_path"})) is path
    assert type(mi.load_dict({"type": "manifold_aovs"})) is aovs
    scene = mi.load_file(scene_path("sphere"), manifold=small_manifold, res="8")
    found = [s.bsdf() for s in scene.shapes() if isinstance(s.bsdf(), brdf)]
    assert len(found) == 1 and integrators.manifold_bsdfs(scene) == found
    assert not integrators.is_manifold_bsdf(mi.load_dict({"type": "diffuse"}))


def test_the_plugins_survive_a_variant_round_trip(small_manifold):
    """llvm_ad_rgb -> scalar_rgb -> llvm_ad_rgb: new classes on the scalar base, the first ones
    back on returning, so that a scene loaded before the round trip still renders its split."""
    llvm = _classes()
    scene = mi.load_file(scene_path("sphere"), manifold=small_manifold, res="8", spp="2")
    (target,) = integrators.manifold_bsdfs(scene)
    split = mi.load_dict({"type": "manifold_path", "component": "touch"})
    before = np.array(mi.render(scene, integrator=split, spp=2, seed=3))

    mi.set_variant("scalar_rgb")
    scalar = _classes()
    assert all(s is not c for s, c in zip(scalar, llvm)) and issubclass(scalar[0], mi.BSDF)
    b = mi.load_dict({"type": "manifold_brdf", "manifold": small_manifold, "material": "steel"})
    assert type(b) is scalar[0] and not isinstance(b, llvm[0])
    with pytest.raises(RuntimeError, match="not supported"):
        mi.load_dict({"type": "manifold_path"})

    mi.set_variant("llvm_ad_rgb")
    assert _classes() == llvm and isinstance(target, llvm[0])
    assert integrators.manifold_bsdfs(scene) == [target]
    assert type(mi.load_dict({"type": "manifold_path"})) is llvm[1]
    after = np.array(mi.render(scene, integrator=split, spp=2, seed=3))
    np.testing.assert_array_equal(after, before)


def test_register_without_a_variant_says_what_to_do(monkeypatch):
    monkeypatch.setattr(mi, "variant", lambda: None)
    with pytest.raises(RuntimeError, match=r"call mi.set_variant\(...\) first"):
        plugins.register()

"""Refining a blend (issue 21): the L1- blend plus the L2+ rendered at the point is the
full-GI render of that point, whatever the point, with its noise estimated honestly."""

import numpy as np
import pytest
from helpers import assert_same_mean  # noqa: E402

import mitsuba_manifold.render  # noqa: F401  (selects a working libLLVM before drjit loads; the plugins)
from mitsuba_manifold import errors  # noqa: E402
from mitsuba_manifold.basis import folder as bf  # noqa: E402
from mitsuba_manifold.basis.blend import blend  # noqa: E402
from mitsuba_manifold.errors import InputError  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.render.jobs import render_basis
from mitsuba_manifold.render.jobs.refine import refine, refine_passes  # noqa: E402
from mitsuba_manifold.render.scene import scenes  # noqa: E402

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]

RES = 16


@pytest.fixture(scope="module")
def basis(tmp_path_factory, small_manifold):
    out = tmp_path_factory.mktemp("refine") / "basis"
    render_basis.render_basis(
        "table", small_manifold, out, spp=4096, mode="onepass", resolution=RES, max_depth=8
    )
    m = Manifold.load(small_manifold)
    return bf.Basis.load(out, manifold=m), m


@pytest.fixture(scope="module")
def gi_basis(tmp_path_factory, small_manifold):
    out = tmp_path_factory.mktemp("refine_gi") / "basis"
    render_basis.render_basis(
        "table",
        small_manifold,
        out,
        spp=1024,
        mode="onepass",
        resolution=RES,
        max_depth=8,
        components="full",
    )
    m = Manifold.load(small_manifold)
    return bf.Basis.load(out, manifold=m), m


def _midpoint(m, a="gold-paint", b="white-diffuse-bball"):
    return 0.5 * (m.latent[m.index(a)] + m.latent[m.index(b)])


def test_refined_blend_is_the_full_gi_render_of_its_point(basis, small_manifold):
    """At a midpoint (where the L1- blend misses the bowl's interreflection, and no per-material
    image gives the L2+ of the blended material), refined blends over independent seeds and
    Mitsuba's ``path`` at the same point agree within noise (block and image z-tests); the
    L1- blend alone is darker."""
    b, m = basis
    x = _midpoint(m)
    refined = [refine(b, m, x=x, spp=32, passes=2, seed=100 + s) for s in range(8)]
    ref = np.stack(
        [
            scenes.render_reference(
                b.manifest.scene,
                small_manifold,
                x,
                256,
                seed=900 + s,
                resolution=b.resolution,
                max_depth=8,
            )
            for s in range(8)
        ]
    )
    img = np.stack([r.image for r in refined])
    assert np.stack([r.rest for r in refined]).mean() > 1e-3 * img.mean()  # the bowl sees itself
    # the L1- part is the basis's, the same in every estimate: its noise (4096 spp) is not in the
    # spread the z-test sees, so it is kept well below that of the references' mean (8 x 256 spp)
    assert_same_mean(img, ref, "refined blend vs path at a midpoint")
    assert refined[0].l1.mean() < ref.mean()


def test_control_variate_makes_a_full_gi_blend_the_render_of_its_point(gi_basis, small_manifold):
    """With a full-GI basis the refinement is the control variate (blend + R - Q from the same
    paths): over independent seeds it equals Mitsuba's ``path`` at a midpoint (z-tests, the
    summed blend so that nothing is denoised), its correction is far less noisy than the L2+
    it corrects, and at a training material it is exactly 0 (the model is exact there)."""
    pytest.importorskip("pyoidn")  # the default blend denoises (a GPU machine may lack OIDN)
    b, m = gi_basis
    x = _midpoint(m)
    refined = [
        refine(b, m, x=x, spp=16, passes=2, seed=100 + s, l2="raw", control_variate=True)
        for s in range(8)
    ]
    assert all(r.method == "control variate" for r in refined)
    assert "(control variate) with 16 spp in 2 passes" in refined[0].summary()
    ref = np.stack(
        [
            scenes.render_reference(
                b.manifest.scene,
                small_manifold,
                x,
                256,
                seed=900 + s,
                resolution=b.resolution,
                max_depth=8,
            )
            for s in range(8)
        ]
    )
    # the basis's blend is the same in every estimate: its noise (1024 spp) is not in the spread
    assert_same_mean(
        np.stack([r.image for r in refined]), ref, "control-variate refinement vs path"
    )
    l2 = refine(b, m, x=x, spp=16, passes=2, seed=3, l2="raw", control_variate=True)
    assert np.std(l2.rest) < 0.5 * np.std(
        b.image(b.gi_key(b.key(["gold-paint"]))) - b.image(b.key(["gold-paint"]))
    )
    at = refine(
        b, m, x=m.latent[m.index("gold-paint")], spp=4, passes=2, seed=1, l2="raw"
    )  # the default
    assert at.method == "control variate" and at.passes == 0 and "nothing to render" in at.summary()
    assert not np.any(at.rest) and np.all(at.pixel_se == 0)
    np.testing.assert_array_equal(
        at.image, blend(b, m, x=m.latent[m.index("gold-paint")], l2="raw")[0]
    )
    assert refine(b, m, x=x, spp=2, passes=1, control_variate=False).method == "l2+"
    with pytest.raises(InputError, match="`control_variate` must be 'auto', True or False"):
        refine(b, m, x=x, spp=2, passes=1, control_variate="yes")


def test_refinement_noise_estimate_matches_the_spread_of_independent_runs(basis):
    """The reported per-pixel standard error of the L2+ part is, on average over pixels, within
    a factor 1.6 of the standard deviation of that part over independent refinements."""
    b, m = basis
    x = _midpoint(m)
    runs = [refine(b, m, x=x, spp=16, passes=4, seed=10 + s) for s in range(10)]
    spread = np.stack([r.rest for r in runs]).std(axis=0, ddof=1)
    reported = np.mean([r.pixel_se for r in runs], axis=0)
    lit = spread > np.percentile(spread, 50)
    ratio = reported[lit].mean() / spread[lit].mean()
    assert 1 / 1.6 < ratio < 1.6, ratio
    assert all(np.isfinite(r.noise_rel_mse) and r.noise_rel_mse >= 0 for r in runs)


def test_progressive_estimates_add_samples_and_report_after_each_pass(basis):
    b, m = basis
    steps = list(refine_passes(b, m, x=m.latent[0], spp=9, passes=3, seed=1))
    assert [s.spp for s in steps] == [3, 6, 9] and [s.passes for s in steps] == [1, 2, 3]
    assert np.isnan(steps[0].noise_rel_mse) and np.isfinite(steps[-1].noise_rel_mse)
    assert "9 spp in 3 passes" in steps[-1].summary()


@pytest.mark.parametrize(
    "spp, passes, match",
    [
        (0, 1, "`spp` must be >= 1"),
        (4, 5, "`passes` must be in 1..spp"),
        (4, 0, "`passes` must be in 1..spp"),
    ],
)
def test_bad_sample_counts_are_refused_before_rendering(basis, spp, passes, match):
    b, m = basis
    with pytest.raises(InputError, match=match):
        refine(b, m, x=m.latent[0], spp=spp, passes=passes)


def test_blend_tool_refines_and_reports_the_error_before_and_after(basis, tmp_path):
    """``blend.py --refine SPP --render-reference``: the refined image is written, the tool says
    what it rendered and its noise, and the error against the reference before and after."""
    from guarantees_helpers import run_tool

    b, m = basis
    x = ",".join(repr(float(v)) for v in _midpoint(m))
    out = tmp_path / "img.exr"
    rc, so, se = run_tool(
        "blend",
        "--basis",
        b.folder,
        "--x",
        x,
        "--out",
        out,
        "--refine",
        16,
        "--refine-passes",
        2,
        "--render-reference",
        "--spp",
        64,
    )
    assert rc == 0, se
    assert "refined: L2+ rendered at the point with 16 spp in 2 passes" in so
    assert "before refining: relative MSE" in so and out.is_file()


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--refine", "0"], ["--refine", ">= 1"]),
        (["--refine", "4", "--refine-passes", "9"], ["--refine-passes", "1..--refine"]),
        (["--refine", "4", "--path", "gold-paint", "pink-fabric"], ["--refine", "--path"]),
    ],
)
def test_blend_tool_refuses_bad_refine_options_in_one_line(basis, tmp_path, extra, words):
    from guarantees_helpers import assert_one_error, run_tool

    b, m = basis
    args = ["--basis", b.folder, "--out", tmp_path / "img.exr"] + extra
    if "--path" not in extra:
        args += ["--x", ",".join(repr(float(v)) for v in m.latent[0])]
    rc, _, se = run_tool("blend", *args)
    assert_one_error(rc, se, *words)
    assert not (tmp_path / "img.exr").exists()


@pytest.mark.parametrize("control_variate", [True, False])
def test_a_refinement_after_another_point_is_the_one_of_a_fresh_scene(
    gi_basis, control_variate, monkeypatch
):
    """The scene a refinement loaded is kept for the next (the explorer refines on every release):
    at a second point the refinement on the kept scene (not loaded again) equals, same seed, the
    one on a scene loaded afresh, for the control variate and for the L2+ rendered at the point."""
    pytest.importorskip("pyoidn")  # the default blend denoises (a GPU machine may lack OIDN)
    from mitsuba_manifold.render.jobs import refine as refine_module

    b, m = gi_basis
    loads = []
    load = scenes.load_scene
    monkeypatch.setattr(scenes, "load_scene", lambda *a, **k: loads.append(a) or load(*a, **k))
    first, second = _midpoint(m), _midpoint(m, "gold-paint", "pink-fabric")
    kw = dict(spp=4, passes=2, control_variate=control_variate)
    monkeypatch.setattr(
        refine_module, "_SCENES", refine_module._SceneCache()
    )  # the first point loads it
    refine(b, m, x=first, seed=3, **kw)
    kept = refine(b, m, x=second, seed=5, **kw)
    assert len(loads) == 1
    monkeypatch.setattr(refine_module, "_SCENES", refine_module._SceneCache())  # loaded again
    fresh = refine(b, m, x=second, seed=5, **kw)
    assert len(loads) == 2
    assert kept.spp == fresh.spp == 4 and np.abs(fresh.rest).max() > 0
    assert kept.method == fresh.method == ("control variate" if control_variate else "l2+")
    np.testing.assert_allclose(
        kept.image, fresh.image, rtol=1e-4, atol=1e-6 * float(np.abs(fresh.image).max())
    )


def test_a_refinement_of_a_missing_manifold_says_so(gi_basis, tmp_path):
    pytest.importorskip("pyoidn")  # the default blend denoises (a GPU machine may lack OIDN)
    b, m = gi_basis
    with pytest.raises(errors.MismatchError, match=r"manifold .*gone\.npz does not exist"):
        next(
            refine_passes(
                b, m, x=_midpoint(m), spp=2, passes=1, manifold_file=str(tmp_path / "gone.npz")
            )
        )


def test_manifold_path_is_the_former_name_of_manifold_file(gi_basis, tmp_path):
    """``manifold_path=`` (a keyword of refine_passes, or a RefineRequest field) still reaches the
    same check, with a DeprecationWarning naming ``manifold_file``."""
    from mitsuba_manifold.render.jobs.refine import RefineRequest

    b, m = gi_basis
    gone = str(tmp_path / "gone.npz")
    with pytest.warns(DeprecationWarning, match=r"RefineRequest\(manifold_path=...\) is now"):
        request = RefineRequest(spp=2, passes=1, manifold_path=gone)
    assert request == RefineRequest(spp=2, passes=1, manifold_file=gone)
    with pytest.warns(DeprecationWarning, match=r"RefineRequest.manifold_path is now spelled"):
        assert request.manifold_path == gone
    with pytest.warns(DeprecationWarning, match=r"refine_passes\(manifold_path=...\) is now"):
        with pytest.raises(errors.MismatchError, match=r"manifold .*gone\.npz does not exist"):
            next(refine_passes(b, m, x=_midpoint(m), spp=2, passes=1, manifold_path=gone))
